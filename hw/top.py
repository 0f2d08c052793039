"""The whole logger: front end → record gate → storage, the SoC peripherals, and one register
bus behind a Wishbone slave (standing in for the NIOS II data master)."""

from amaranth import *
from amaranth.hdl import ResetInserter
from amaranth.lib import enum, stream, wiring
from amaranth.lib.wiring import In, Out

from .arbiter import TaggedFrameByte
from .arch import frames as arch_frames
from .arch.sdram import MT48LC4M32B2
from .frame_fifo import FrameByte
from .frontend import DEFAULT_CHANNELS, FrontEnd, FrontEndRegisters
from .peripherals import Button, Events, GpsTime, Leds, Rtc, Watchdog
from .sdio.host import sd_pins_signature
from .sdram import sdram_pins_signature
from .soc import WishboneCSRBridge, WordBridge, csr, wishbone
from .storage import Storage


__all__ = ["LOGGER_ID", "EVENT_NAMES", "TOPLEVEL_NAME", "RecordGate", "LoggerRegisters",
           "Logger", "generate_verilog", "component_verilog"]

#: Module name of the logger's generated Verilog.
TOPLEVEL_NAME = "maglog_logger"

#: `logger.id`: "MGLG" in ASCII, so firmware can tell it is talking to this gateware.
LOGGER_ID = 0x4D474C47

#: Fields of `events.status`, in bit order.
EVENT_NAMES = ("fix", "dma_done", "sd_error", "ring_overflow", "button", "zda")

#: The channel whose kept frames carry the GPS's sentences (LED3, the ZDA capture; with a
#: single channel, that one).
GPS_CHANNEL = 1

#: Address bits of the logger's CSR bus (32-bit words): room for every window.
CSR_ADDR_WIDTH = 7


class _Gate(enum.Enum, shape=2):
    IDLE  = 0    # between frames: the next first byte decides
    STORE = 1    # passing a frame to the ring, up to its last byte
    DRAIN = 2    # dropping a frame that began while not recording, up to its last byte


class RecordGate(wiring.Component):
    """Lets whole frames through while ``record`` is set, and drains them otherwise.

    The decision is taken at a frame's first byte and holds to its last, so a frame is
    stored or drained whole whatever ``record`` does meanwhile. Drained frames never reach
    the ring (so they are not ring drops).

    Members
    -------
    i : ``In(stream.Signature(TaggedFrameByte(channels)))``
    o : ``Out(stream.Signature(FrameByte))``
    record : ``In(1)``
    in_frame : ``Out(1)``
        A frame is passing into the ring (between its first and its last byte).
    """
    def __init__(self, channels):
        if not isinstance(channels, int) or channels < 1:
            raise ValueError(f"Channel count must be a positive integer, not {channels!r}")
        super().__init__({
            "i":        In(stream.Signature(TaggedFrameByte(channels))),
            "o":        Out(stream.Signature(FrameByte())),
            "record":   In(1),
            "in_frame": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        state = Signal(_Gate)
        store = Signal()
        m.d.comb += [
            store.eq(Mux(state == _Gate.IDLE, self.record, state == _Gate.STORE)),
            self.in_frame.eq(state == _Gate.STORE),
            self.o.payload.data.eq(self.i.payload.data),
            self.o.payload.last.eq(self.i.payload.last),
        ]
        with m.If(store):
            m.d.comb += [self.o.valid.eq(self.i.valid), self.i.ready.eq(self.o.ready)]
        with m.Else():
            m.d.comb += self.i.ready.eq(1)
        with m.If(self.i.valid & self.i.ready):
            with m.If(self.i.payload.last):
                m.d.sync += state.eq(_Gate.IDLE)
            with m.Else():
                m.d.sync += state.eq(Mux(store, _Gate.STORE, _Gate.DRAIN))
        return m


class LoggerRegisters(wiring.Component):
    """Window ``logger``: identification, the record switch, status, and the firmware's own
    status word.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    record : ``Out(1)``
    in_frame, sdram_ready, button : ``In(1)``
    """

    class Id(csr.Register, access="r"):
        """0x4D474C47 ("MGLG"): the logger's gateware is there."""
        magic: csr.Field(csr.action.R, 32)

    class Control(csr.Register, access="rw"):
        """`record` 1: frames reach the ring; the gate acts at frame boundaries (a frame is
        stored or drained whole, decided at its first byte)."""
        record: csr.Field(csr.action.RW, 1)

    class Status(csr.Register, access="r"):
        """`in_frame`: a frame is passing the gate into the ring; `sdram_ready`: the SDRAM
        controller is initialised; `button`: the debounced button level."""
        in_frame:    csr.Field(csr.action.R, 1)
        sdram_ready: csr.Field(csr.action.R, 1)
        button:      csr.Field(csr.action.R, 1)

    class FwStatus(csr.Register, access="rw"):
        """Written by the firmware only (codes in sw/app.py): its state, last error, and the
        number of the LOG file being written (0: none)."""
        state: csr.Field(csr.action.RW, 4)
        error: csr.Field(csr.action.RW, 8)
        file:  csr.Field(csr.action.RW, 17)

    def __init__(self):
        regs = csr.Builder(addr_width=2, data_width=32, granularity=8)
        self._id = regs.add("id", self.Id())
        self._control = regs.add("control", self.Control())
        self._status = regs.add("status", self.Status())
        self._fw_status = regs.add("fw_status", self.FwStatus())
        self._bridge = WordBridge(regs.as_memory_map())
        super().__init__({
            "bus":         In(csr.Signature(addr_width=regs.addr_width, data_width=32)),
            "record":      Out(1),
            "in_frame":    In(1),
            "sdram_ready": In(1),
            "button":      In(1),
        })
        self.bus.memory_map = self._bridge.bus.memory_map

    def elaborate(self, platform):
        m = Module()
        m.submodules.bridge = self._bridge
        wiring.connect(m, wiring.flipped(self.bus), self._bridge.bus)
        status = self._status.f
        m.d.comb += [
            self._id.f.magic.r_data.eq(LOGGER_ID),
            self.record.eq(self._control.f.record.data),
            status.in_frame.r_data.eq(self.in_frame),
            status.sdram_ready.r_data.eq(self.sdram_ready),
            status.button.r_data.eq(self.button),
        ]
        return m


class Logger(wiring.Component):
    """The logger's gateware.

    Windows of the CSR map (32-bit words; ``csr_memory_map``, also reached through
    ``bus.memory_map``): ``sdio`` and ``dma`` (storage), ``frontend``, ``logger``,
    ``leds``, ``button``, ``rtc``, ``watchdog``, ``gps``, ``events``.

    The Wishbone slave ``bus`` is 32 bits wide with a granularity of 32 (``sel`` is one
    bit): ``adr`` is the register's word address, an access takes two cycles to ``ack``.

    A watchdog expiry resets everything but the RTC and the watchdog (whose ``reset_cause``
    says so); the SDRAM controller then runs its initialisation again.

    Parameters
    ----------
    channels : sequence of ChannelConfig
    clk_freq : float
    chip : arch.sdram.Chip
    cas_latency : int
    ring_capacity : int or None
        Bytes of ring (default: the whole chip).
    max_frame, fifo_depth :
        As for :class:`FrontEnd`.
    debounce_s, led_stretch_s : float
        Button debounce time; how long a kept frame lights its activity LED.

    Members
    -------
    uart_rx : ``In(N)``
    sd : ``Out(sd_pins_signature())``
    sdram : ``Out(sdram_pins_signature(chip.geometry))``
    led : ``Out(4)``
    button : ``In(1)``
        Active high (pressed), asynchronous.
    bus : ``In(wishbone.Signature(addr_width=7, data_width=32, granularity=32))``
    """
    def __init__(self, channels=DEFAULT_CHANNELS, *, clk_freq=50e6, chip=MT48LC4M32B2,
                 cas_latency=2, ring_capacity=None, max_frame=arch_frames.DEFAULT_MAX_FRAME,
                 fifo_depth=1024, debounce_s=0.01, led_stretch_s=0.05):
        self.frontend = FrontEnd(channels, clk_freq=clk_freq, max_frame=max_frame,
                                 fifo_depth=fifo_depth)
        n = len(self.frontend.channels)
        self.frontend_regs = FrontEndRegisters(n)
        self.gate = RecordGate(n)
        self.logger_regs = LoggerRegisters()
        self.storage = Storage(chip, clk_freq=clk_freq, cas_latency=cas_latency,
                               capacity=ring_capacity)
        # The RTC's millisecond tick times the LEDs, the button and the watchdog too.
        self.leds = Leds(clk_freq, stretch_s=led_stretch_s, shared_tick=True)
        self.button_in = Button(clk_freq, debounce_s=debounce_s, shared_tick=True)
        self.rtc = Rtc(clk_freq)
        self.watchdog = Watchdog(clk_freq, shared_tick=True)
        self.gps = GpsTime(n, channel=min(GPS_CHANNEL, n - 1))
        self.events = Events(EVENT_NAMES)

        self._decoder = csr.Decoder(addr_width=CSR_ADDR_WIDTH, data_width=32)
        self._decoder.add(self.storage.bus)               # windows sdio and dma
        self._decoder.add(self.frontend_regs.bus, name="frontend")
        self._decoder.add(self.logger_regs.bus, name="logger")
        for name, block in (("leds", self.leds), ("button", self.button_in),
                            ("rtc", self.rtc), ("watchdog", self.watchdog),
                            ("gps", self.gps), ("events", self.events)):
            self._decoder.add(block.bus, name=name)
        self._bridge = WishboneCSRBridge(self._decoder.bus, data_width=32)
        super().__init__({
            "uart_rx": In(n, init=(1 << n) - 1),
            "sd":      Out(sd_pins_signature()),
            "sdram":   Out(sdram_pins_signature(chip.geometry)),
            "led":     Out(4),
            "button":  In(1),
            "bus":     In(wishbone.Signature(addr_width=CSR_ADDR_WIDTH, data_width=32,
                                             granularity=32)),
        })
        self.bus.memory_map = self._bridge.wb_bus.memory_map

    @property
    def csr_memory_map(self):
        """The CSR decoder's map: windows by name, word addresses."""
        return self._decoder.bus.memory_map

    def elaborate(self, platform):
        m = Module()
        # The RTC and the watchdog are reset by `rst` only; all else by a watchdog expiry too.
        m.submodules.rtc = self.rtc
        m.submodules.watchdog = self.watchdog
        # The tick comes from outside the watchdog's reset, so it runs on through one.
        m.d.comb += [self.watchdog.tick.eq(self.rtc.tick), self.leds.tick.eq(self.rtc.tick),
                     self.button_in.tick.eq(self.rtc.tick)]
        body = Module()
        m.submodules.body = ResetInserter({"sync": self.watchdog.fire})(body)

        fe, gate, storage = self.frontend, self.gate, self.storage
        body.submodules.frontend = fe
        body.submodules.frontend_regs = self.frontend_regs
        body.submodules.gate = gate
        body.submodules.logger_regs = self.logger_regs
        body.submodules.storage = storage
        body.submodules.leds = self.leds
        body.submodules.button = self.button_in
        body.submodules.gps = self.gps
        body.submodules.events = self.events
        body.submodules.decoder = self._decoder
        body.submodules.bridge = self._bridge

        wiring.connect(body, wiring.flipped(self.bus), self._bridge.wb_bus)

        # Data: front end → record gate → storage; the GPS time capture taps the front end.
        body.d.comb += fe.uart_rx.eq(self.uart_rx)
        wiring.connect(body, fe.o, gate.i)
        wiring.connect(body, gate.o, storage.i)
        body.d.comb += [
            self.gps.i.valid.eq(fe.o.valid),
            self.gps.i.ready.eq(fe.o.ready),
            self.gps.i.payload.eq(fe.o.payload),
        ]
        wiring.connect(body, storage.sdram, wiring.flipped(self.sdram))
        wiring.connect(body, storage.sd, wiring.flipped(self.sd))

        # Registers.
        for k in range(len(fe.channels)):
            body.d.comb += fe.divisor[k].eq(self.frontend_regs.divisor[k])
        wiring.connect(body, self.frontend_regs.counters, fe.counters)
        body.d.comb += [
            gate.record.eq(self.logger_regs.record),
            self.logger_regs.in_frame.eq(gate.in_frame),
            self.logger_regs.sdram_ready.eq(storage.sdram_ready),
            self.logger_regs.button.eq(self.button_in.level),
        ]

        # LEDs, button, events.
        body.d.comb += [
            self.leds.activity.eq(fe.kept[:2]),
            self.led.eq(self.leds.led),
            self.button_in.button.eq(self.button),
        ]
        sources = {
            "fix":           fe.flush,
            "dma_done":      storage.dma_done,
            "sd_error":      storage.sd_error,
            "ring_overflow": storage.ring_overflow,
            "button":        self.button_in.press,
            "zda":           self.gps.zda,
        }
        body.d.comb += self.events.sources.eq(Cat(sources[name] for name in EVENT_NAMES))
        return m


class _VerilogTop(wiring.Component):
    """The logger with DESIGN.md's flat port names, for the Verilog boundary only."""
    def __init__(self, logger):
        self.logger = logger
        g = logger.sdram.signature.members
        n = len(logger.uart_rx)
        members = {
            "uart_rx": In(n, init=(1 << n) - 1),
            **{f"sd_{name}": member for name, member in logger.sd.signature.members.items()},
            **{f"sdram_{name}": member for name, member in g.items()},
            "led":     Out(4),
            "button":  In(1),
            **{f"wb_{name}": member
               for name, member in logger.bus.signature.members.items()},
        }
        super().__init__(members)

    def elaborate(self, platform):
        m = Module()
        logger = self.logger
        m.submodules.logger = logger
        inner = {"uart_rx": logger.uart_rx, "led": logger.led, "button": logger.button}
        for prefix, interface in (("sd", logger.sd), ("sdram", logger.sdram),
                                  ("wb", logger.bus)):
            for name in interface.signature.members:
                inner[f"{prefix}_{name}"] = getattr(interface, name)
        for name, member in self.signature.members.items():
            if member.flow == In:
                m.d.comb += inner[name].eq(getattr(self, name))
            else:
                m.d.comb += getattr(self, name).eq(inner[name])
        return m


def component_verilog(component, *, name):
    """The Verilog of a component on its own, its ports named as Amaranth names them.

    Amaranth 0.5's ``verilog.convert`` takes every member of a signature as a port and
    refuses the ``Const(1)`` of an ``always_ready`` stream's ``ready``; such members are
    left out here (they are no wire).
    """
    from amaranth.back import verilog
    from amaranth.hdl import Const, ValueCastable
    ports = {}
    for path, member, value in component.signature.flatten(component):
        if isinstance(value, ValueCastable):
            value = value.as_value()
        if isinstance(value, Const):
            continue
        ports["__".join(map(str, path))] = (value, None)
    return verilog.convert(component, name=name, ports=ports)


def generate_verilog(logger=None):
    """The Verilog of a logger (the default one when none is given): module
    ``maglog_logger`` with DESIGN.md's port names."""
    from amaranth.back import verilog
    if logger is None:
        logger = Logger()
    return verilog.convert(_VerilogTop(logger), name=TOPLEVEL_NAME)
