"""Serial front end: a UART receiver and a frame filter per channel, and the arbiter."""

from dataclasses import dataclass

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from .arbiter import FrameArbiter, TaggedFrameByte
from .arch import frames as arch_frames
from .arch import uart as arch_uart
from .frame_filter import ChannelKind, FrameFilter, counters_signature
from .frame_fifo import FrameByte
from .soc import csr
from .uart import UartRx


__all__ = ["ChannelConfig", "DEFAULT_CHANNELS", "TOPLEVEL_NAME", "Channel", "FrontEnd",
           "FrontEndRegisters", "divisor_for", "generate_verilog"]


#: Module name of the front end's generated Verilog.
TOPLEVEL_NAME = "maglog_frontend"

#: Width of each channel's run-time baud divisor.
DIVISOR_BITS = 16

#: Width of the frame counters the registers show: 2^32 frames at 50 Hz is 994 days.
COUNTER_BITS = 32


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


def divisor_for(clk_freq, baud):
    """The UartRx divisor nearest to ``baud`` at ``clk_freq``, checked against ±1 % error."""
    divisor = round(clk_freq / (arch_uart.OVERSAMPLING * baud))
    if not 1 <= divisor < 1 << DIVISOR_BITS:
        raise ValueError(f"Baud rate {baud} cannot be reached from a {clk_freq} Hz clock")
    error = clk_freq / (arch_uart.OVERSAMPLING * divisor) / baud - 1
    if abs(error) > 0.01:
        raise ValueError(f"Baud rate {baud} from a {clk_freq} Hz clock is off by "
                         f"{error:+.2%}; use a clock that divides better")
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
    counters : ``Out(counters_signature(counter_width))``
    """
    def __init__(self, kind, *, divisor_init=1, max_frame=arch_frames.DEFAULT_MAX_FRAME,
                 fifo_depth=1024, counter_width=32):
        self.uart = UartRx(divisor_bits=DIVISOR_BITS, divisor_init=divisor_init)
        self.filter = FrameFilter(kind, max_frame=max_frame, fifo_depth=fifo_depth,
                                  counter_width=counter_width)
        super().__init__({
            "rx":       In(1, init=arch_uart.MARK),
            "divisor":  In(DIVISOR_BITS, init=divisor_init),
            "o":        Out(stream.Signature(FrameByte())),
            "flush":    Out(1),
            "kept":     Out(1),
            "counters": Out(counters_signature(counter_width)),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.uart = self.uart
        m.submodules.filter = self.filter
        m.d.comb += [
            self.uart.rx.eq(self.rx),
            self.uart.divisor.eq(self.divisor),
            self.flush.eq(self.filter.flush),
            self.kept.eq(self.o.valid & self.o.ready & self.o.payload.last),
        ]
        wiring.connect(m, self.uart.o, self.filter.i)
        wiring.connect(m, self.filter.o, wiring.flipped(self.o))
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
    max_frame, fifo_depth, counter_width :
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
    counters : ``Out(counters_signature(counter_width))`` × N
    """
    def __init__(self, channels=DEFAULT_CHANNELS, *, clk_freq=50e6,
                 max_frame=arch_frames.DEFAULT_MAX_FRAME, fifo_depth=1024, counter_width=32):
        channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                         for c in channels)
        if not channels:
            raise ValueError("The front end needs at least one channel")
        self._configs = channels
        self._clk_freq = clk_freq
        self.channels = [
            Channel(c.kind, divisor_init=divisor_for(clk_freq, c.baud), max_frame=max_frame,
                    fifo_depth=fifo_depth, counter_width=counter_width)
            for c in channels
        ]
        self.arbiter = FrameArbiter(len(channels))
        n = len(channels)
        super().__init__({
            "uart_rx":  In(n, init=(1 << n) - 1),
            "divisor":  In(DIVISOR_BITS).array(n),
            "o":        Out(stream.Signature(TaggedFrameByte(n))),
            "flush":    Out(1),
            "kept":     Out(n),
            "counters": Out(counters_signature(counter_width)).array(n),
        })

    @property
    def configs(self):
        return self._configs

    def elaborate(self, platform):
        m = Module()
        m.submodules.arbiter = self.arbiter
        flushes = []
        for k, channel in enumerate(self.channels):
            m.submodules[f"channel{k}"] = channel
            m.d.comb += [
                channel.rx.eq(self.uart_rx[k]),
                channel.divisor.eq(Mux(self.divisor[k] == 0, channel.divisor.init,
                                       self.divisor[k])),
            ]
            wiring.connect(m, channel.o, self.arbiter.i[k])
            wiring.connect(m, channel.counters, wiring.flipped(self.counters[k]))
            flushes.append(channel.flush)
            m.d.comb += self.kept[k].eq(channel.kept)
        wiring.connect(m, self.arbiter.o, wiring.flipped(self.o))
        m.d.comb += self.flush.eq(Cat(flushes).any())
        return m


class FrontEndRegisters(wiring.Component):
    """The front end's divisors and counters as CSR registers (window ``frontend``).

    Per channel ``k``: ``ch{k}_divisor``, then ``ch{k}_{name}`` for each counter of
    :data:`~maglog.hw.arch.frames.COUNTER_NAMES` (kept, then drops by cause).

    Parameters
    ----------
    channels : int
        Channel count.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    divisor : ``Out(16)`` × channels
        To :attr:`FrontEnd.divisor`.
    counters : ``In(counters_signature(32))`` × channels
        From :attr:`FrontEnd.counters`.
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
        per_channel = 1 + len(arch_frames.COUNTER_NAMES)
        regs = csr.Builder(addr_width=max(1, (channels * per_channel - 1).bit_length()),
                           data_width=32, granularity=8)
        self._divisors = []
        self._counters = []
        for k in range(channels):
            self._divisors.append(regs.add(f"ch{k}_divisor", self.Divisor()))
            self._counters.append({name: regs.add(f"ch{k}_{name}", self.Counter())
                                   for name in arch_frames.COUNTER_NAMES})
        self._bridge = csr.Bridge(regs.as_memory_map())
        super().__init__({
            "bus":      In(csr.Signature(addr_width=regs.addr_width, data_width=32)),
            "divisor":  Out(DIVISOR_BITS).array(channels),
            "counters": In(counters_signature(COUNTER_BITS)).array(channels),
        })
        self.bus.memory_map = self._bridge.bus.memory_map

    def elaborate(self, platform):
        m = Module()
        m.submodules.bridge = self._bridge
        wiring.connect(m, wiring.flipped(self.bus), self._bridge.bus)
        for k in range(self._channels):
            m.d.comb += self.divisor[k].eq(self._divisors[k].f.value.data)
            for name, reg in self._counters[k].items():
                m.d.comb += reg.f.count.r_data.eq(getattr(self.counters[k], name))
        return m


def generate_verilog(front_end=None):
    """The Verilog of a front end (the default logger's when none is given)."""
    from amaranth.back import verilog
    if front_end is None:
        front_end = FrontEnd()
    return verilog.convert(front_end, name=TOPLEVEL_NAME)
