"""Board platforms for the logger: a DE0-Nano with an SD card and the sensor UARTs on its GPIO
header, and an EP4CE6E22C8 logger board in the class of the original design.

Every resource the board top requests is 3.3-V LVTTL; SD CMD and DAT have the FPGA's weak
pull-ups (``WEAK_PULL_UP_RESISTOR``); the SDRAM pins ask Quartus to pack the SDRAM
controller's own pin registers into the I/O elements (``FAST_INPUT_REGISTER`` and
``FAST_OUTPUT_REGISTER`` / ``FAST_OUTPUT_ENABLE_REGISTER``), so the I/O timing does not
depend on placement and the controller's latency is unchanged.

:func:`pin_table` lists the pins of a board from these resources (docs/boards.md is made
from it, a test keeps the two equal).
"""

from dataclasses import dataclass

from amaranth.build import Attrs, Clock, Pins, PinsN, Resource, Subsignal
from amaranth.vendor import IntelPlatform
from amaranth_boards.de0nano import DE0NanoPlatform
from amaranth_boards.resources import ButtonResources, LEDResources, SDRAMResource

from ..arch.sdram import IS42S16160, MT48LC4M32B2


__all__ = ["LVTTL", "DE0NanoLoggerPlatform", "LoggerEP4CE6Platform", "Board", "BOARDS",
           "used_resources", "pin_table", "pin_table_markdown", "EQFP144_POWER",
           "EQFP144_CONFIG", "EQFP144_DUAL_PURPOSE", "EQFP144_CLOCK_INPUTS", "EQFP144_USER_IO",
           "EQFP144_OTHER"]

LVTTL = "3.3-V LVTTL"

#: Quartus assignments that pack the SDRAM controller's pin registers into the I/O elements.
_SDRAM_OUT = {"FAST_OUTPUT_REGISTER": "ON"}
_SDRAM_DQ = {"FAST_INPUT_REGISTER": "ON", "FAST_OUTPUT_REGISTER": "ON",
             "FAST_OUTPUT_ENABLE_REGISTER": "ON"}
_SDRAM_ATTRS = {"clk_en": _SDRAM_OUT, "cs": _SDRAM_OUT, "we": _SDRAM_OUT, "ras": _SDRAM_OUT,
                "cas": _SDRAM_OUT, "ba": _SDRAM_OUT, "a": _SDRAM_OUT, "dqm": _SDRAM_OUT,
                "dq": _SDRAM_DQ}
#: The SD bus lines that need pull-ups (SD Physical Layer spec: CMD and DAT, 10-100 kOhm).
_PULL_UP = {"WEAK_PULL_UP_RESISTOR": "ON"}


def _rebuild(sub, extra=None, *, top=True):
    """A copy of a resource (or subsignal) with every I/O standard set to 3.3-V LVTTL and the
    attributes of ``extra`` (subsignal name -> attrs) added."""
    extra = extra or {}
    args = []
    for io in sub.ios:
        args.append(_rebuild(io, extra, top=False) if isinstance(io, Subsignal) else io)
    if sub.clock is not None:
        args.append(Clock(sub.clock.frequency))
    attrs = {k: v for k, v in sub.attrs.items() if k.lower() not in ("io_standard", "iostandard")}
    if top or any(isinstance(io, (Pins,)) for io in sub.ios):
        attrs["io_standard"] = LVTTL
    if not top:
        attrs.update(extra.get(sub.name, {}))
    args.append(Attrs(**attrs))
    if top:
        return Resource(sub.name, sub.number, *args)
    return Subsignal(sub.name, *args)


def _sd_resource(conn, *, clk, cmd, dat):
    return Resource("sd_card", 0,
        Subsignal("clk", Pins(clk, dir="o", conn=conn, assert_width=1)),
        Subsignal("cmd", Pins(cmd, dir="io", conn=conn, assert_width=1), Attrs(**_PULL_UP)),
        Subsignal("dat", Pins(dat, dir="io", conn=conn, assert_width=4), Attrs(**_PULL_UP)),
        Attrs(io_standard=LVTTL))


def _uart_resources(conn, pins):
    return [Resource("sensor_uart", n,
                     Subsignal("rx", Pins(pin, dir="i", conn=conn, assert_width=1)),
                     Attrs(io_standard=LVTTL))
            for n, pin in enumerate(pins.split())]


class DE0NanoLoggerPlatform(DE0NanoPlatform):
    """DE0-Nano (EP4CE22F17C6, IS42S16160 SDRAM) with the logger's breakout on GPIO-0 (JP1).

    GPIO-0 header pins: sensor UART RX 0/1/2 on 1, 3, 5 (pins 1 and 3 are the header's
    input-only clock pins GPIO_0_IN0/IN1); SD card CLK 7, CMD 8, DAT0-3 9, 10, 13, 14;
    3.3 V on pin 29, GND on 12 and 30. KEY0 resets the board (it holds the PLL in reset),
    KEY1 is the logger's button, LED0-3 its LEDs.
    """
    resources = [
        *(_rebuild(r, _SDRAM_ATTRS if r.name == "sdram" else None)
          for r in DE0NanoPlatform.resources),
        _sd_resource(("gpio", 0), clk="7", cmd="8", dat="9 10 13 14"),
        *_uart_resources(("gpio", 0), "1 3 5"),
    ]
    connectors = DE0NanoPlatform.connectors


class LoggerEP4CE6Platform(IntelPlatform):
    """An EP4CE6E22C8 (EQFP144) logger board in the class of the original design: 50 MHz
    oscillator, MT48LC4M32B2 (x32) SDRAM, SD socket, three sensor UART inputs, four LEDs, a
    button and a reset button. A pin plan to adapt to a real board (docs/boards.md).

    Where the pins come from: clock (23), reset (25), LEDs (84-87), button (88) and the 16-bit
    SDRAM subset (clk 43, control, BA, A0-A11, DQ0-15, DQM0-1) are those of the RZ-EasyFPGA
    A2.2 board (amaranth-boards ``rz_easyfpga_a2_2``); CKE, DQ16-31 and DQM2-3, the SD socket
    and the UARTs are chosen here among the pins that board routes to its headers. The UART
    inputs use the input-only clock pins 89-91 (the RZ board's other keys).
    """
    device = "EP4CE6"
    package = "E22"
    speed = "C8"
    default_clk = "clk50"
    resources = [
        Resource("clk50", 0, Pins("23", dir="i"), Clock(50e6), Attrs(io_standard=LVTTL)),
        Resource("rst", 0, PinsN("25", dir="i"), Attrs(io_standard=LVTTL)),
        *LEDResources(pins="87 86 85 84", invert=True, attrs=Attrs(io_standard=LVTTL)),
        *ButtonResources(pins="88", invert=True, attrs=Attrs(io_standard=LVTTL)),
        _rebuild(SDRAMResource(0,
            clk="43", cke="58", cs_n="72", we_n="69", ras_n="71", cas_n="70",
            ba="73 74", a="76 77 80 83 68 67 66 65 64 60 75 59",
            dq="28 30 31 32 33 34 38 39 54 53 52 51 50 49 46 44 "
               "110 111 112 113 114 115 119 120 121 124 125 126 127 128 129 132",
            dqm="42 55 133 135"), _SDRAM_ATTRS),
        _sd_resource(None, clk="143", cmd="142", dat="141 138 137 136"),
        *_uart_resources(None, "89 90 91"),
    ]
    connectors = []


# The EP4CE6E22C8's EQFP144 package. Source: the pin functions of the KiCad symbol
# "Altera:EP4CE6E22" (public repository balmerdx/CycloneIV_dev_board,
# ep4ce10_0/cp4ce10_0-cache.lib), which follows Intel's pin-out; it agrees with the pins the
# RZ-EasyFPGA A2.2 board (amaranth-boards rz_easyfpga_a2_2) uses as I/O, and its user I/O
# count (87 + the 4 dual-purpose pins below = 91) is the device overview's for EP4CE6 E144.
#: Power: VCCINT 5 29 45 61 78 102 116 134; VCCA 35 107; VCCD_PLL 37 109; VCCIO 17 26 40 47
#: 56 62 81 93 117 122 130 139; GND 4 19 22 27 41 48 57 63 79 82 95 118 123 131 140; GNDA 36
#: 108 (and the exposed pad).
EQFP144_POWER = frozenset(str(p) for p in (
    5, 29, 45, 61, 78, 102, 116, 134, 35, 107, 37, 109,
    17, 26, 40, 47, 56, 62, 81, 93, 117, 122, 130, 139,
    4, 19, 22, 27, 41, 48, 57, 63, 79, 82, 95, 118, 123, 131, 140, 36, 108))
#: Dedicated configuration and JTAG: nSTATUS 9, DCLK 12, nCONFIG 14, TDI 15, TCK 16, TMS 18,
#: TDO 20, nCE 21, CONF_DONE 92, MSEL0-2 94 96 97.
EQFP144_CONFIG = frozenset(str(p) for p in (9, 12, 14, 15, 16, 18, 20, 21, 92, 94, 96, 97))
#: Dual-purpose pins the board plan leaves alone: the serial flash's ASDO 6, nCSO 8, DATA0 13
#: (active serial configuration), and nCEO 101 (I/O only with a device option).
EQFP144_DUAL_PURPOSE = frozenset({"6", "8", "13", "101"})
#: Dedicated clock inputs (input only): CLK1-3 23-25, CLK4-7 88-91.
EQFP144_CLOCK_INPUTS = frozenset({"23", "24", "25", "88", "89", "90", "91"})
#: The pins a board may use as I/O (clock inputs for inputs only).
EQFP144_USER_IO = (frozenset(str(p) for p in range(1, 145))
                   - EQFP144_POWER - EQFP144_CONFIG - EQFP144_DUAL_PURPOSE)
EQFP144_OTHER = EQFP144_POWER | EQFP144_CONFIG | EQFP144_DUAL_PURPOSE


@dataclass(frozen=True)
class Board:
    """A board the logger is built for.

    ``reset`` names the resource that holds the PLL (and so everything) in reset, ``button``
    the logger's button; ``uarts`` is the number of ``sensor_uart`` resources.
    """
    name: str
    platform: type
    chip: object
    reset: tuple
    button: tuple
    leds: int = 4
    uarts: int = 3
    title: str = ""


BOARDS = {
    "de0nano": Board("de0nano", DE0NanoLoggerPlatform, IS42S16160,
                     reset=("button", 0), button=("button", 1),
                     title="Terasic DE0-Nano (EP4CE22F17C6), SD card and UARTs on GPIO-0"),
    "logger-ep4ce6": Board("logger-ep4ce6", LoggerEP4CE6Platform, MT48LC4M32B2,
                           reset=("rst", 0), button=("button", 0),
                           title="EP4CE6E22C8 logger board (pin plan to adapt)"),
}


def used_resources(board):
    """(name, number) of every resource the board top requests, in table order."""
    return [("clk50", 0), board.reset, board.button,
            *(("led", n) for n in range(board.leds)),
            ("sdram", 0), ("sd_card", 0),
            *(("sensor_uart", n) for n in range(board.uarts))]


def _leaves(sub, path):
    for io in sub.ios:
        if isinstance(io, Subsignal):
            yield from _leaves(io, path + (io.name,))
        else:
            yield path, io


def pin_table(board):
    """Rows ``(signal, header pin, FPGA pin, direction, attributes)`` of every pin the board
    top uses, from the platform's resources (one row per bit)."""
    platform = board.platform()
    conn_pins = {conn_pin: pin for connector in platform.connectors.values()
                 for conn_pin, pin in connector}
    rows = []
    for name, number in used_resources(board):
        resource = platform.lookup(name, number)
        for path, pins in _leaves(resource, ()):
            attrs = {}
            # Attributes merge from the resource down to the leaf.
            node = resource
            attrs.update(node.attrs)
            for part in path:
                node = next(io for io in node.ios if isinstance(io, Subsignal) and io.name == part)
                attrs.update(node.attrs)
            fpga = pins.map_names(conn_pins, resource)
            signal = "_".join((f"{name}_{number}",) + path)
            for bit, (header, pin) in enumerate(zip(pins.names, fpga)):
                label = f"{signal}[{bit}]" if len(pins.names) > 1 else signal
                where = header.replace("_", " ", 1) if ":" in header else ""
                direction = pins.dir + ("" if not pins.invert else " (active low)")
                extra = ", ".join(f"{k}={v}" for k, v in attrs.items() if k != "io_standard")
                rows.append((label, where, pin, direction,
                             attrs.get("io_standard", "") + (f"; {extra}" if extra else "")))
    return rows


def pin_table_markdown(board):
    """The pin table of a board as a Markdown table (docs/boards.md)."""
    lines = ["| signal | header pin | FPGA pin | direction | I/O standard; assignments |",
             "|---|---|---|---|---|"]
    for row in pin_table(board):
        lines.append("| " + " | ".join(cell or "-" for cell in row) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    # python -m maglog.hw.platform.boards: the pin tables of docs/boards.md.
    for name, board in BOARDS.items():
        print(f"<!-- pins:{name} -->\n{pin_table_markdown(board)}\n<!-- /pins -->\n")
