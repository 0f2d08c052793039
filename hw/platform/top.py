"""The board top: PLL, reset, the pins' buffers, the NIOS II system and the logger.

::

    clk50 ──► altpll ──c0──► sync (system clock, 50 MHz) ─┬─► logger, NIOS II system
               │      └─c1──► sdram_clk (same, phase-shifted) ──► DDR output ──► SDRAM CLK pin
               └─locked──► reset synchroniser ──► sync reset (held until the PLL locks)
    NIOS II reset: the sync reset, or a watchdog expiry (the logger's body resets too)

The NIOS II/e system (``maglog_cpu``, made by Platform Designer from the qsys-script of
:mod:`.quartus`) exports an Avalon-MM master (an ``altera_avalon_mm_bridge``) that reaches the
logger's registers: the logger is :class:`~.avalon.AvalonLogger`, its ``avs`` slave on the
bridge's master (byte addresses from the bridge, word addresses on ``avs``).

I/O registers. The SDRAM controller already registers every pin it drives and samples DQ into
a register; the board's resources ask Quartus to place those registers in the I/O elements
(``FAST_*_REGISTER``), so the controller's read latency is what its simulation tests check.
The SD lines are tristates (``o``/``oe``/``i`` from the logger's ``sd`` pins) with the
FPGA's weak pull-ups; their inputs go straight to the SD host, which samples them on the
system clock edge that raises SD CLK (an extra input register here would move that sample one
system clock earlier, before the card's data is valid at 25 MHz; docs/boards.md).
"""

from fractions import Fraction

from amaranth import *
from amaranth.lib import io
from amaranth.lib.cdc import ResetSynchronizer

from ..frontend import DEFAULT_CHANNELS
from .avalon import AvalonLogger
from .boards import BOARDS
from ..arch.units import hertz


__all__ = ["CPU_MODULE", "CPU_RESET_CLOCKS", "PllConfig", "pll_config", "BoardTop"]

#: Module name of the NIOS II system Platform Designer generates.
CPU_MODULE = "maglog_cpu"

#: System clocks the NIOS II is held in reset after a watchdog expiry.
CPU_RESET_CLOCKS = 4


class PllConfig:
    """An ``altpll`` setup for Cyclone IV E: one input, outputs as multiply/divide/phase.

    ``outputs`` is a list of ``(name, multiply_by, divide_by, phase_ps)``; ``frequency(k)``
    gives output k's frequency.
    """
    def __init__(self, f_in, outputs):
        self.f_in = f_in
        self.outputs = outputs

    def frequency(self, k):
        _, mul, div, _ = self.outputs[k]
        return self.f_in * mul / div

    def parameters(self):
        """The ``altpll`` parameters, as the MegaWizard writes them for Cyclone IV E."""
        params = {
            "bandwidth_type": "AUTO",
            "compensate_clock": "CLK0",
            "inclk0_input_frequency": round(1e12 / self.f_in),     # period in ps
            "intended_device_family": "Cyclone IV E",
            "lpm_type": "altpll",
            "operation_mode": "NORMAL",
            "pll_type": "AUTO",
            "port_areset": "PORT_USED",
            "port_inclk0": "PORT_USED",
            "port_inclk1": "PORT_UNUSED",
            "port_locked": "PORT_USED",
            "self_reset_on_loss_lock": "OFF",
            "width_clock": 5,
        }
        for k in range(5):
            if k < len(self.outputs):
                _, mul, div, phase = self.outputs[k]
                params.update({
                    f"clk{k}_multiply_by": mul,
                    f"clk{k}_divide_by": div,
                    f"clk{k}_duty_cycle": 50,
                    f"clk{k}_phase_shift": str(phase),
                    f"port_clk{k}": "PORT_USED",
                })
            else:
                params[f"port_clk{k}"] = "PORT_UNUSED"
        return params


def pll_config(f_in, f_sys, sdram_phase_ns):
    """System clock and SDRAM clock (the same frequency, shifted by ``sdram_phase_ns``;
    negative leads) from ``f_in``."""
    ratio = Fraction(f_sys / f_in).limit_denominator(64)
    if float(f_in * ratio) != float(f_sys):
        raise ValueError(f"{hertz(f_sys)} is not a ratio of small integers of {hertz(f_in)}")
    period_ps = 1e12 / f_sys
    if not -period_ps < sdram_phase_ns * 1000 < period_ps:
        raise ValueError(f"SDRAM clock phase {sdram_phase_ns} ns exceeds a period")
    mul, div = ratio.numerator, ratio.denominator
    return PllConfig(f_in, [("sys", mul, div, 0),
                            ("sdram", mul, div, round(sdram_phase_ns * 1000))])


class BoardTop(Elaboratable):
    """The logger on a board of :data:`~.boards.BOARDS`.

    Parameters
    ----------
    board : str or Board
    channels : sequence of ChannelConfig
        One per UART input of the board.
    sdram_phase_ns : float
        Phase of the SDRAM clock against the system clock (negative: it leads).
    **logger_kwargs :
        For :class:`~maglog.hw.top.Logger` (``chip`` and ``clk_freq`` come from the board).

    Attributes
    ----------
    logger : AvalonLogger
    bridge_address_width : int
        Byte address bits of the NIOS II system's exported master (the logger's window).
    """
    def __init__(self, board, *, channels=DEFAULT_CHANNELS, sdram_phase_ns=-3.0,
                 **logger_kwargs):
        if isinstance(board, str):
            board = BOARDS[board]
        self.board = board
        if len(channels) != board.uarts:
            raise ValueError(f"The logger has {len(channels)} channels, the board "
                             f"{board.name} {board.uarts} UART inputs")
        self.f_sys = 50e6
        self.pll = pll_config(50e6, self.f_sys, sdram_phase_ns)
        self.logger = AvalonLogger(channels, chip=board.chip, clk_freq=self.f_sys,
                                   **logger_kwargs)
        self.bridge_address_width = len(self.logger.avs.address) + 2

    def elaborate(self, platform):
        m = Module()
        board, logger = self.board, self.logger

        # Clocks and reset.
        def input_pin(name, number):
            buffer = io.Buffer("i", platform.request(name, number, dir="-"))
            m.submodules[f"{name}_{number}"] = buffer
            return buffer.i

        clk50 = input_pin("clk50", 0)
        reset_button = input_pin(*board.reset)
        pll_clk = Signal(5)
        locked = Signal()
        m.submodules.pll = Instance("altpll",
            **{f"p_{k}": v for k, v in self.pll.parameters().items()},
            i_inclk=Cat(clk50, C(0, 1)),
            i_areset=reset_button,
            o_clk=pll_clk,
            o_locked=locked,
        )
        m.domains.sync = ClockDomain("sync")
        m.domains.sdram_clk = ClockDomain("sdram_clk", reset_less=True)
        m.d.comb += [
            ClockSignal("sync").eq(pll_clk[0]),
            ClockSignal("sdram_clk").eq(pll_clk[1]),
        ]
        m.submodules.reset_sync = ResetSynchronizer(~locked, domain="sync")

        # The logger and the NIOS II system.
        m.submodules.logger = logger
        # The NIOS II is reset with the logger: by the PLL's lock, and by a watchdog expiry
        # (which resets the logger's body; the firmware restarts and reads the watchdog's
        # reset_cause). The one-cycle `fire` is stretched to CPU_RESET_CLOCKS and ends in a
        # register, so the system's asynchronous reset input sees a clean pulse.
        fire = logger.logger.watchdog.fire
        fired = Signal(CPU_RESET_CLOCKS - 1)
        cpu_reset = Signal()
        m.d.sync += [fired.eq(Cat(fire, fired[:-1])), cpu_reset.eq(fire | fired.any())]
        avs = logger.avs
        bridge_address = Signal(self.bridge_address_width)
        m.d.comb += avs.address.eq(bridge_address[2:])
        m.submodules.cpu = Instance(CPU_MODULE,
            i_clk_clk=ClockSignal("sync"),
            i_reset_reset_n=~(ResetSignal("sync") | cpu_reset),
            o_bridge_address=bridge_address,
            o_bridge_read=avs.read,
            o_bridge_write=avs.write,
            o_bridge_writedata=avs.writedata,
            o_bridge_byteenable=avs.byteenable,
            o_bridge_burstcount=Signal(1, name="bridge_burstcount"),
            o_bridge_debugaccess=Signal(1, name="bridge_debugaccess"),
            i_bridge_readdata=avs.readdata,
            i_bridge_waitrequest=avs.waitrequest,
            i_bridge_readdatavalid=avs.readdatavalid,
        )

        # SDRAM: the controller's registered pins straight to the pads (Quartus packs the
        # registers into the I/O elements); CLK from a DDR output in the shifted clock.
        sdram = platform.request("sdram", 0, dir="-")
        pins = logger.sdram
        m.submodules.sdram_clk = clk_buf = io.DDRBuffer("o", sdram.clk, o_domain="sdram_clk")
        m.d.comb += clk_buf.o.eq(0b01)       # high in the first half of each period
        outputs = {"clk_en": pins.cke, "ba": pins.ba, "a": pins.a, "dqm": pins.dqm,
                   # PinsN ports: drive the active-low levels as they are.
                   "cs": pins.cs_n, "we": pins.we_n, "ras": pins.ras_n, "cas": pins.cas_n}
        for name, value in outputs.items():
            port = getattr(sdram, name)
            if port.invert[0]:
                port = ~port
            m.submodules[f"sdram_{name}"] = buf = io.Buffer("o", port)
            m.d.comb += buf.o.eq(value)
        m.submodules.sdram_dq = dq = io.Buffer("io", sdram.dq)
        m.d.comb += [dq.o.eq(pins.dq_o), dq.oe.eq(pins.dq_oe), pins.dq_i.eq(dq.i)]

        # SD card: tristate CMD and DAT (pulled up), CLK out.
        sd = platform.request("sd_card", 0, dir="-")
        m.submodules.sd_clk = sd_clk = io.Buffer("o", sd.clk)
        m.submodules.sd_cmd = sd_cmd = io.Buffer("io", sd.cmd)
        m.submodules.sd_dat = sd_dat = io.Buffer("io", sd.dat)
        m.d.comb += [
            sd_clk.o.eq(logger.sd.clk),
            sd_cmd.o.eq(logger.sd.cmd_o), sd_cmd.oe.eq(logger.sd.cmd_oe),
            logger.sd.cmd_i.eq(sd_cmd.i),
            sd_dat.o.eq(logger.sd.dat_o), sd_dat.oe.eq(logger.sd.dat_oe),
            logger.sd.dat_i.eq(sd_dat.i),
        ]

        # Sensor UARTs (the logger synchronises them), LEDs, button.
        for n in range(board.uarts):
            uart = platform.request("sensor_uart", n, dir="-")
            m.submodules[f"uart_{n}"] = rx = io.Buffer("i", uart.rx)
            m.d.comb += logger.uart_rx[n].eq(rx.i)
        for n in range(board.leds):
            m.submodules[f"led_{n}"] = led = io.Buffer("o", platform.request("led", n, dir="-"))
            m.d.comb += led.o.eq(logger.led[n])
        m.d.comb += logger.button.eq(input_pin(*board.button))
        return m
