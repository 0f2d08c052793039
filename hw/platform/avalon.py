"""The logger behind an Avalon-MM slave, for a NIOS II system built in Platform Designer.

:class:`AvalonLogger` is the :class:`~maglog.hw.top.Logger` with its Wishbone register port
replaced by an Avalon-MM slave ``avs``: a bridge turns each Avalon transfer into one
Wishbone cycle on the logger's ``bus`` (and so one access of its CSR map).

Timing of ``avs`` (the component's ``_hw.tcl`` says the same, from :data:`AVS_TIMING`):

* address units are 32-bit words (``address`` is the register's word address; the NIOS
  sees register ``k`` at byte offset ``4 * k`` from the component's base);
* pipelined reads with variable latency: a command (read or write) is accepted in the cycle
  ``waitrequest`` is low, which is the cycle the logger's Wishbone ``ack`` arrives (today
  the command's third cycle: two under ``waitrequest``); the master holds its command while
  ``waitrequest`` is high. A read's data comes with ``readdatavalid`` in the cycle after it
  was accepted. At most one read is in flight (``maximumPendingReadTransactions`` 1: the
  next command cannot be accepted before that data); ``waitrequest`` is also high while no
  command is presented.

Byte enables: every register is 32 bits wide and is read and written whole.

* A write with ``byteenable`` ``0b1111`` writes the register.
* A write with any other ``byteenable`` (a NIOS ``stb``/``sth``) **changes nothing**: it
  completes with the usual timing, but no register sees a write strobe, so no byte of the
  register, enabled or not, is corrupted and no write action (a command bit, a FIFO push)
  fires. A read-modify-write was not chosen because some registers act on being read (the
  DMA's data window advances, counters are sampled), and a hidden read would do that.
* Reads ignore ``byteenable``: the whole word is returned (and a read's action fires once).
"""

from dataclasses import dataclass

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from ..frontend import DEFAULT_CHANNELS
from ..top import Logger


__all__ = ["AVS_TIMING", "TOPLEVEL_NAME", "avalon_slave_signature", "AvalonLogger", "Port",
           "verilog_ports", "generate_verilog"]

#: Module name of the Avalon logger's Verilog (and of the Platform Designer component).
TOPLEVEL_NAME = "maglog_logger_avalon"

#: Data width of ``avs`` (bits) and its byte lanes.
DATA_WIDTH = 32
BYTE_LANES = DATA_WIDTH // 8

#: The Avalon interface properties that describe ``avs``'s timing (Avalon Interface
#: Specifications, "Avalon Memory-Mapped Interface Properties"): pipelined with variable
#: latency (``readdatavalid``), one read in flight, ``waitrequest`` stretching every
#: transfer, no fixed wait or setup/hold times, addresses in words.
AVS_TIMING = {
    "addressUnits":                    "WORDS",
    "bitsPerSymbol":                   8,
    "readLatency":                     0,
    "readWaitTime":                    0,
    "writeWaitTime":                   0,
    "setupTime":                       0,
    "holdTime":                        0,
    "maximumPendingReadTransactions":  1,
    "maximumPendingWriteTransactions": 0,
    "timingUnits":                     "Cycles",
}


def avalon_slave_signature(addr_width):
    """An Avalon-MM slave port with 32-bit words, as its master sees it (``Out`` members
    are driven by the master; a slave holds it as ``In(avalon_slave_signature(...))``, as
    amaranth-soc's bus signatures are used).

    Members: ``address`` (word address, ``addr_width`` bits), ``read``, ``write``,
    ``writedata[31:0]``, ``byteenable[3:0]`` from the master; ``readdata[31:0]``,
    ``waitrequest``, ``readdatavalid`` from the slave.
    """
    if not isinstance(addr_width, int) or addr_width < 1:
        raise ValueError(f"Address width must be a positive integer, not {addr_width!r}")
    return wiring.Signature({
        "address":       Out(addr_width),
        "read":          Out(1),
        "write":         Out(1),
        "writedata":     Out(DATA_WIDTH),
        "byteenable":    Out(BYTE_LANES),
        "readdata":      In(DATA_WIDTH),
        "waitrequest":   In(1, init=1),
        "readdatavalid": In(1),
    })


class AvalonLogger(wiring.Component):
    """The logger with an Avalon-MM slave (see the module's text for its timing and byte
    enables) in place of the Wishbone port.

    Parameters
    ----------
    channels, **logger_kwargs :
        As for :class:`~maglog.hw.top.Logger` (``clk_freq``, ``chip``, ...).

    Members
    -------
    uart_rx, sd, sdram, led, button :
        As the Logger's.
    avs : ``In(avalon_slave_signature(addr_width))``
        ``addr_width`` is the Logger's register address width (word addresses).

    Attributes
    ----------
    logger : Logger
    logger_kwargs : dict
        The keyword arguments the logger was built with.
    csr_memory_map : MemoryMap
        The logger's register map; its word addresses are ``avs.address`` values.
    """
    def __init__(self, channels=DEFAULT_CHANNELS, **logger_kwargs):
        self.logger = Logger(channels, **logger_kwargs)
        self.logger_kwargs = dict(logger_kwargs)
        pins = self.logger.signature.members
        super().__init__({
            **{name: pins[name] for name in ("uart_rx", "sd", "sdram", "led", "button")},
            "avs": In(avalon_slave_signature(len(self.logger.bus.adr))),
        })

    @property
    def csr_memory_map(self):
        return self.logger.csr_memory_map

    def elaborate(self, platform):
        m = Module()
        logger = self.logger
        m.submodules.logger = logger
        for name in ("uart_rx", "button"):
            m.d.comb += getattr(logger, name).eq(getattr(self, name))
        m.d.comb += self.led.eq(logger.led)
        wiring.connect(m, logger.sd, wiring.flipped(self.sd))
        wiring.connect(m, logger.sdram, wiring.flipped(self.sdram))

        # Avalon → Wishbone: the command is held by the master while waitrequest is high,
        # so it drives the Wishbone cycle directly; the ack accepts it.
        avs, wb = self.avs, logger.bus
        command = avs.read | avs.write
        whole_word = avs.byteenable == (1 << BYTE_LANES) - 1
        read_data = Signal(DATA_WIDTH, reset_less=True)
        read_valid = Signal()
        m.d.comb += [
            wb.adr.eq(avs.address),
            wb.dat_w.eq(avs.writedata),
            wb.we.eq(avs.write),
            # A partial write runs its cycle without the select: no register is written.
            wb.sel.eq(Mux(avs.write, whole_word, 1)),
            wb.cyc.eq(command),
            wb.stb.eq(command),
            avs.waitrequest.eq(~wb.ack),
            avs.readdata.eq(read_data),
            avs.readdatavalid.eq(read_valid),
        ]
        # The Wishbone data is only good in the ack cycle: keep it for readdatavalid.
        m.d.sync += read_valid.eq(avs.read & ~avs.write & wb.ack)
        with m.If(avs.read & wb.ack):
            m.d.sync += read_data.eq(wb.dat_r)
        return m


@dataclass(frozen=True)
class Port:
    """One port of the Verilog module: its name, direction (``"input"``/``"output"``),
    width, the Platform Designer interface it belongs to and its role there."""
    name: str
    direction: str
    width: int
    interface: str
    role: str


#: Pins of the logger as Platform Designer conduits: (interface, member of AvalonLogger,
#: prefix of its Verilog ports). A single-signal member is one port named as the member.
CONDUITS = (("uart", "uart_rx", None), ("sd", "sd", "sd"), ("sdram", "sdram", "sdram"),
            ("led", "led", None), ("button", "button", None))


def _flat(component):
    """``(Port, signal)`` of every port but the clock and reset: ``avs_*``, then the
    conduits, each with the component's signal it stands for."""
    sig = component.signature.members
    groups = [("avs", "avs", "avs")] + list(CONDUITS)
    found = []
    for interface, name, prefix in groups:
        member, value = sig[name], getattr(component, name)
        if member.is_port:
            direction = "input" if member.flow == In else "output"
            found.append((Port(name, direction, Shape.cast(member.shape).width, interface,
                               name), value))
            continue
        for sub_name, sub in member.signature.members.items():
            # (An In(...) member's signature is already flipped: flows are the component's.)
            direction = "input" if sub.flow == In else "output"
            found.append((Port(f"{prefix}_{sub_name}", direction,
                               Shape.cast(sub.shape).width, interface, sub_name),
                          getattr(value, sub_name)))
    return found


def verilog_ports(component):
    """Every port of :func:`generate_verilog`'s module for ``component``, in order: the
    clock ``clk`` and the synchronous, active-high ``reset``, then ``avs_*``, then the
    conduits (from the component's signature)."""
    return [Port("clk", "input", 1, "clock", "clk"),
            Port("reset", "input", 1, "reset", "reset"),
            *(port for port, _ in _flat(component))]


class _VerilogTop(wiring.Component):
    """The Avalon logger with flat port names (``avs_address``, ``sd_cmd_o``, ...), the
    clock ``clk`` and the reset ``reset``, for the Verilog boundary only."""
    def __init__(self, inner):
        self.inner = inner
        members = {"reset": In(1)}
        for port, signal in _flat(inner):
            flow = In if port.direction == "input" else Out
            members[port.name] = flow(port.width, init=signal.init)
        super().__init__(members)
        self.domain = ClockDomain("sync")

    def elaborate(self, platform):
        m = Module()
        m.domains.sync = self.domain
        m.d.comb += self.domain.rst.eq(self.reset)
        m.submodules.logger = self.inner
        for port, signal in _flat(self.inner):
            outer = getattr(self, port.name)
            if port.direction == "input":
                m.d.comb += signal.eq(outer)
            else:
                m.d.comb += outer.eq(signal)
        return m


def generate_verilog(component=None):
    """The Verilog of an :class:`AvalonLogger` (the default one when none is given): module
    ``maglog_logger_avalon`` with the ports of :func:`verilog_ports`."""
    from amaranth.back import verilog
    if component is None:
        component = AvalonLogger()
    top = _VerilogTop(component)
    # The clock is no member of the signature: name every port.
    ports = {"clk": (top.domain.clk, None)}
    ports.update({name: (getattr(top, name), None) for name in top.signature.members})
    return verilog.convert(top, name=TOPLEVEL_NAME, ports=ports)
