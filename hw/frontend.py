"""Serial front end: a UART receiver and a frame filter per channel, and the arbiter."""

import math
from dataclasses import dataclass

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from .arbiter import FrameArbiter, TaggedFrameByte
from .arch import frames as arch_frames
from .arch import uart as arch_uart
from .counters import CounterBank, read_signature
from .frame_filter import ChannelKind, FrameFilter, counters_signature
from .frame_fifo import FrameByte
from .arch.units import hertz
from .soc import csr
from .uart import UartRx


__all__ = ["ChannelConfig", "DEFAULT_CHANNELS", "TOPLEVEL_NAME", "Channel", "FrontEnd",
           "FrontEndRegisters", "divisor_for", "MAX_BAUD_ERROR", "register_address",
           "generate_verilog"]


#: Module name of the front end's generated Verilog.
TOPLEVEL_NAME = "maglog_frontend"

#: Width of each channel's run-time baud divisor.
DIVISOR_BITS = 16

#: Width of the frame counters the registers show: 2^32 frames at 50 Hz is 994 days.
COUNTER_BITS = 32

#: Words of the ``frontend`` window per channel: the divisor, then the counters.
REGISTERS_PER_CHANNEL = 1 + len(arch_frames.COUNTER_NAMES)


def register_address(channel, name):
    """Word address in the ``frontend`` window of channel ``channel``'s ``divisor`` or
    counter ``name``: the CSR registers and the counter bank's words alike."""
    index = 0 if name == "divisor" else 1 + arch_frames.COUNTER_NAMES.index(name)
    return channel * REGISTERS_PER_CHANNEL + index


@dataclass(frozen=True)
class ChannelConfig:
    """One serial channel: its rule set and its nominal baud rate."""
    kind: ChannelKind
    baud: int

    def __post_init__(self):
        object.__setattr__(self, "kind", ChannelKind(self.kind))
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError(f"Baud rate must be a positive integer, not {self.baud!r}")


#: The logger's channels, in `uart_rx` order: magnetometer, GPS, cesium (DESIGN.md, Formats).
DEFAULT_CHANNELS = (
    ChannelConfig(ChannelKind.PMAG,   115200),
    ChannelConfig(ChannelKind.NMEA,   9600),
    ChannelConfig(ChannelKind.CESIUM, 9600),
)


#: The largest error of a receiver's own rate (``clk_freq / (16 * divisor)`` against the
#: nominal baud rate) that a channel may be built with. The receiver (hw/uart.py) takes a
#: continuous stream of characters whose bits are up to 3.75 % shorter or 5.55 % longer than
#: its own at the divisors of 9600 and 115200 baud from 1.8432 to 40 MHz (12 to 260; the
#: stop bit's vote must come before the next start bit, 154 of 160 ticks, and its middle
#: sample after data bit 7, 152 of 144; divisors 1 and 2 take 4.06 / 5.90 % and
#: 3.91 / 5.72 %): measured with the model's receiver (sim/models/logger_uart.py), which
#: tests/sim/models/test_logger_uart.py holds to UartRx on the Amaranth simulator, and on
#: UartRx itself at divisor 22. Within ±1.5 % of its own, a transmitter may still be 2.3 %
#: fast or 3.8 % slow (the receiver 1.5 % slow or fast) and every character arrive intact.
MAX_BAUD_ERROR = 0.015


def divisor_for(clk_freq, baud):
    """The UartRx divisor nearest to ``baud`` at ``clk_freq``, checked against
    :data:`MAX_BAUD_ERROR`; a refusal names the clocks near ``clk_freq`` that give ``baud``
    exactly."""
    ideal = clk_freq / (arch_uart.OVERSAMPLING * baud)
    divisor = round(ideal)
    if not 1 <= divisor < 1 << DIVISOR_BITS:
        raise ValueError(f"Baud rate {baud} cannot be reached from a {hertz(clk_freq)} clock")
    error = clk_freq / (arch_uart.OVERSAMPLING * divisor) / baud - 1
    if abs(error) > MAX_BAUD_ERROR:
        near = [arch_uart.OVERSAMPLING * baud * d for d in (math.floor(ideal),
                                                            math.floor(ideal) + 1)
                if 1 <= d < 1 << DIVISOR_BITS]
        raise ValueError(f"Baud rate {baud} from a {hertz(clk_freq)} clock is off by "
                         f"{error:+.2%}: beyond the receiver's ±{MAX_BAUD_ERROR:.1%} (the rest "
                         f"of what it tolerates is left to the transmitter); "
                         f"{' or '.join(hertz(f) for f in near)} would give it exactly")
    return divisor


class Channel(wiring.Component):
    """A UART receiver feeding a frame filter.

    Members
    -------
    rx : ``In(1)``
    divisor : ``In(16)``
    o : ``Out(stream.Signature(FrameByte))``
    flush : ``Out(1)``
    kept : ``Out(1)``
        One-cycle strobe as the last byte of a kept frame leaves the channel.
    events : ``Out(len(COUNTER_NAMES))``
        The filter's counter events.
    counters : ``Out(counters_signature(counter_width))``
        Only when ``counter_width`` is not 0.
    """
    def __init__(self, kind, *, divisor_init=1, max_frame=arch_frames.DEFAULT_MAX_FRAME,
                 fifo_depth=1024, counter_width=32):
        self.uart = UartRx(divisor_bits=DIVISOR_BITS, divisor_init=divisor_init)
        self.filter = FrameFilter(kind, max_frame=max_frame, fifo_depth=fifo_depth,
                                  counter_width=counter_width)
        members = {
            "rx":      In(1, init=arch_uart.MARK),
            "divisor": In(DIVISOR_BITS, init=divisor_init),
            "o":       Out(stream.Signature(FrameByte())),
            "flush":   Out(1),
            "kept":    Out(1),
            "events":  Out(len(arch_frames.COUNTER_NAMES)),
        }
        if counter_width:
            members["counters"] = Out(counters_signature(counter_width))
        super().__init__(members)

    def elaborate(self, platform):
        m = Module()
        m.submodules.uart = self.uart
        m.submodules.filter = self.filter
        m.d.comb += [
            self.uart.rx.eq(self.rx),
            self.uart.divisor.eq(self.divisor),
            self.flush.eq(self.filter.flush),
            self.kept.eq(self.o.valid & self.o.ready & self.o.payload.last),
            self.events.eq(self.filter.events),
        ]
        wiring.connect(m, self.uart.o, self.filter.i)
        wiring.connect(m, self.filter.o, wiring.flipped(self.o))
        if "counters" in self.signature.members:
            wiring.connect(m, self.filter.counters, wiring.flipped(self.counters))
        return m


class FrontEnd(wiring.Component):
    """The logger's serial front end.

    Parameters
    ----------
    channels : sequence of ChannelConfig
        One per ``uart_rx`` line.
    clk_freq : float
        System clock, for the divisors after reset.
    max_frame, fifo_depth :
        As for :class:`FrameFilter`.

    Members
    -------
    uart_rx : ``In(N)``
        Serial lines (asynchronous, idle high).
    divisor : ``In(16)`` × N
        Baud divisors (``f_clk / (16 * baud)``); 0 selects the channel's nominal rate.
    o : ``Out(stream.Signature(TaggedFrameByte(N)))``
        Kept frames from all channels, never interleaved.
    flush : ``Out(1)``
        A kept GGA with a fix (from any NMEA channel).
    kept : ``Out(N)``
        Per channel, a one-cycle strobe as a kept frame's last byte leaves it (activity LEDs).
    counters : ``In(read_signature(addr_width, 32))``
        The frame counters (kept, then dropped by cause), 32 bits each, at the word addresses
        of :func:`register_address` (the ``frontend`` window's): ``r_data`` is the counter
        at ``addr`` on the cycle after ``r_stb``, zero on other cycles and for the
        ``depth`` cycles after reset (while the counters are cleared). Two reads need a
        cycle between them.

    The counters live in one block RAM (:class:`~maglog.hw.counters.CounterBank`), each
    counted by a scanner that must visit it between two of its events. A filter makes at
    most one event per received character, and a character takes 10 bit times on the line;
    the receiver reports characters at least 9 bit times apart (the stop bit is decided at
    its middle, and the next start bit may follow at once), so at the fastest divisor (1)
    a counter's events are at least 9 * 16 = 144 cycles apart. The bank's sweep is one
    cycle per word of its memory (32 words for up to 4 channels), two with the bus reading
    every other cycle: 65 cycles at most, well inside.
    """
    def __init__(self, channels=DEFAULT_CHANNELS, *, clk_freq=50e6,
                 max_frame=arch_frames.DEFAULT_MAX_FRAME, fifo_depth=1024):
        channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                         for c in channels)
        if not channels:
            raise ValueError("The front end needs at least one channel")
        self._configs = channels
        self._clk_freq = clk_freq
        self.channels = [
            Channel(c.kind, divisor_init=divisor_for(clk_freq, c.baud), max_frame=max_frame,
                    fifo_depth=fifo_depth, counter_width=0)
            for c in channels
        ]
        self.arbiter = FrameArbiter(len(channels))
        n = len(channels)
        self.counter_bank = CounterBank(
            [register_address(k, name) for k in range(n) for name in arch_frames.COUNTER_NAMES],
            width=COUNTER_BITS)
        spacing = (arch_uart.CHARACTER_BITS - 1) * arch_uart.OVERSAMPLING
        if self.counter_bank.min_event_spacing > spacing:
            raise ValueError(f"The counter bank of {n} channels could miss events of "
                             f"characters {spacing} cycles apart; use fewer channels")
        super().__init__({
            "uart_rx":  In(n, init=(1 << n) - 1),
            "divisor":  In(DIVISOR_BITS).array(n),
            "o":        Out(stream.Signature(TaggedFrameByte(n))),
            "flush":    Out(1),
            "kept":     Out(n),
            "counters": In(read_signature(self.counter_bank.addr_width, COUNTER_BITS)),
        })

    @property
    def configs(self):
        return self._configs

    def elaborate(self, platform):
        m = Module()
        m.submodules.arbiter = self.arbiter
        m.submodules.counter_bank = bank = self.counter_bank
        wiring.connect(m, wiring.flipped(self.counters), bank.read)
        m.d.comb += bank.events.eq(Cat(channel.events for channel in self.channels))
        flushes = []
        for k, channel in enumerate(self.channels):
            m.submodules[f"channel{k}"] = channel
            m.d.comb += [
                channel.rx.eq(self.uart_rx[k]),
                channel.divisor.eq(Mux(self.divisor[k] == 0, channel.divisor.init,
                                       self.divisor[k])),
            ]
            wiring.connect(m, channel.o, self.arbiter.i[k])
            flushes.append(channel.flush)
            m.d.comb += self.kept[k].eq(channel.kept)
        wiring.connect(m, self.arbiter.o, wiring.flipped(self.o))
        m.d.comb += self.flush.eq(Cat(flushes).any())
        return m


class FrontEndRegisters(wiring.Component):
    """The front end's divisors and counters as CSR registers (window ``frontend``).

    Per channel ``k``: ``ch{k}_divisor``, then ``ch{k}_{name}`` for each counter of
    :data:`~maglog.hw.arch.frames.COUNTER_NAMES` (kept, then drops by cause), at the word
    addresses of :func:`register_address`.

    The bus is served here rather than by a ``csr.Multiplexer``: the divisors are the
    :class:`Divisor` registers' own fields (written on the cycle of ``w_stb``), and the
    counters come from the front end's counter bank, whose read port has the CSR bus's
    timing (data on the cycle after ``r_stb``, zero otherwise); every read goes to it (it
    reads zero where a divisor lives) and a divisor read adds the divisor. The
    :class:`Counter` registers only name the counters in the memory map.

    Parameters
    ----------
    channels : int
        Channel count.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    divisor : ``Out(16)`` × channels
        To :attr:`FrontEnd.divisor`.
    counters : ``Out(read_signature(addr_width, 32))``
        To :attr:`FrontEnd.counters`.
    """

    class Divisor(csr.Register, access="rw"):
        """Baud divisor of the channel (f_clk / (16 * baud)); 0 selects its nominal rate."""
        value: csr.Field(csr.action.RW, DIVISOR_BITS)

    class Counter(csr.Register, access="r"):
        """Frames of the channel: kept, or dropped for the cause the register is named after
        (32 bits: 2^32 frames at 50 Hz is 994 days, no silent wrap)."""
        count: csr.Field(csr.action.R, COUNTER_BITS)

    def __init__(self, channels):
        if not isinstance(channels, int) or channels < 1:
            raise ValueError(f"Channel count must be a positive integer, not {channels!r}")
        self._channels = channels
        granularity = 8
        regs = csr.Builder(addr_width=max(1, (channels * REGISTERS_PER_CHANNEL - 1).bit_length()),
                           data_width=32, granularity=granularity)

        def add(k, name, reg):
            offset = register_address(k, name) * (32 // granularity)
            return regs.add(f"ch{k}_{name}", reg, offset=offset)

        self._divisors = []
        self._counters = []
        for k in range(channels):
            self._divisors.append(add(k, "divisor", self.Divisor()))
            self._counters.extend((f"ch{k}_{name}", add(k, name, self.Counter()))
                                  for name in arch_frames.COUNTER_NAMES)
        memory_map = regs.as_memory_map()
        super().__init__({
            "bus":      In(csr.Signature(addr_width=regs.addr_width, data_width=32)),
            "divisor":  Out(DIVISOR_BITS).array(channels),
            "counters": Out(read_signature(regs.addr_width, COUNTER_BITS)),
        })
        self.bus.memory_map = memory_map

    def elaborate(self, platform):
        m = Module()
        bus = self.bus
        for k, reg in enumerate(self._divisors):
            m.submodules[f"ch{k}_divisor"] = reg
        for name, reg in self._counters:
            # No logic: the counter bank answers for them.
            m.submodules[name] = reg

        m.d.comb += [
            self.counters.addr.eq(bus.addr),
            self.counters.r_stb.eq(bus.r_stb),
        ]
        divisor_read = Signal(self._channels)   # which divisor the last cycle's strobe read
        selects = [bus.addr == register_address(k, "divisor") for k in range(self._channels)]
        m.d.sync += divisor_read.eq(Cat(bus.r_stb & select for select in selects))
        r_data = self.counters.r_data
        for k, reg in enumerate(self._divisors):
            m.d.comb += [
                self.divisor[k].eq(reg.f.value.data),
                reg.element.w_stb.eq(bus.w_stb & selects[k]),
                reg.element.w_data.eq(bus.w_data),
            ]
            r_data = r_data | Mux(divisor_read[k], reg.f.value.data, 0)
        m.d.comb += bus.r_data.eq(r_data)
        return m


def generate_verilog(front_end=None):
    """The Verilog of a front end (the default logger's when none is given)."""
    from amaranth.back import verilog
    if front_end is None:
        front_end = FrontEnd()
    return verilog.convert(front_end, name=TOPLEVEL_NAME)
