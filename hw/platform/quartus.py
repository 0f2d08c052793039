"""A complete Quartus project for a board, written without Quartus.

:func:`build_project` writes Amaranth's plan for the Intel platform (``maglog_board.qsf``,
``.sdc``, ``.v``, ``build_maglog_board.sh``) with this module's additions:

* the SDC constraints of :func:`sdc_constraints` (PLL clocks, the SDRAM and SD clocks on
  their pins, SDRAM and SD input/output delays from the chips' data sheets, false paths on
  the asynchronous pins);
* ``maglog_cpu.tcl``, the qsys-script that creates the NIOS II/e system (``maglog_cpu``)
  the board top instantiates, and ``build.sh`` that runs qsys-script, qsys-generate and
  ``quartus_sh --flow compile``;
* ``maglog_board.qpf`` (so the Quartus GUI opens the folder as a project) and ``pins.md``,
  the board's pin table;
* ``yosys/standins.v``: behavioural stand-ins of the megafunctions (``altpll``,
  ``altiobuf_*``, ``altddio_out``, ``altera_std_synchronizer*``) and of ``maglog_cpu`` (an
  idle master), so Yosys can read and elaborate the top. Quartus never reads them.

None of this has been run through Quartus here (it is not installed); docs/boards.md says
what to check when it is.
"""

import os
from dataclasses import dataclass
from pathlib import Path

from .boards import BOARDS, pin_table_markdown
from .top import CPU_MODULE, BoardTop


__all__ = ["PROJECT_NAME", "SdramIoTiming", "SDRAM_TIMING", "SdIoTiming", "SD_DEFAULT_SPEED",
           "LOGGER_BASE", "sdc_constraints", "qsys_script", "build_script",
           "MEGAFUNCTION_STANDINS", "CPU_STANDIN", "project",
           "build_project", "project_files"]

#: The Quartus revision and top-level module.
PROJECT_NAME = "maglog_board"

#: Where the logger's registers sit in the NIOS II's address space.
LOGGER_BASE = 0x9000


@dataclass(frozen=True)
class SdramIoTiming:
    """An SDR SDRAM's I/O timing (ns) at CAS latency 2 (the logger's default)."""
    t_ac: float     # access time from CLK, CL2 (max)
    t_oh: float     # output hold time (min)
    t_is: float     # input (address, command, data) setup time
    t_ih: float     # input hold time


# Ref: Micron/Alliance MT48LC4M32B2 data sheet, Table "Electrical Characteristics and
#      Recommended AC Operating Conditions", -6 speed grade: tAC(2) 7.5 ns, tOH 2 ns,
#      tAS/tCMS/tDS 1.5 ns, tAH/tCMH/tDH 1 ns.
# Ref: ISSI SDR SDRAM data sheets of the IS42S16160's family (IS42S16800A -7: tAC CL2 6 ns,
#      tOH 2.5 ns, tAS/tCS/tDS 1.5 ns, tAH/tCH/tDH 0.8 ns; IS42S32160C -75: tAC CL2 6.5 ns,
#      taken to be safe). The IS42S16160's own sheet was not at hand: check these.
SDRAM_TIMING = {
    "MT48LC4M32B2": SdramIoTiming(t_ac=7.5, t_oh=2.0, t_is=1.5, t_ih=1.0),
    "IS42S16160":   SdramIoTiming(t_ac=6.5, t_oh=2.5, t_is=1.5, t_ih=0.8),
}


@dataclass(frozen=True)
class SdIoTiming:
    """SD bus timing (ns), card side."""
    t_odly: float   # card output delay after the falling CLK edge (max)
    t_oh: float     # card output hold (min)
    t_isu: float    # card input setup before the rising CLK edge
    t_ih: float     # card input hold after it


# Ref: SD Physical Layer Simplified Specification, "Bus Timing (Default)" (default speed,
#      up to 25 MHz): tISU 5 ns, tIH 5 ns, tODLY 14 ns (data transfer mode), tOH 0 ns.
SD_DEFAULT_SPEED = SdIoTiming(t_odly=14.0, t_oh=0.0, t_isu=5.0, t_ih=5.0)


def _ports(names):
    return "[get_ports {" + " ".join(names) + "}]"


def sdc_constraints(board, *, trace_ns=0.5):
    """The SDC lines added to Amaranth's (which creates the 50 MHz input clock on its pin).

    ``trace_ns`` is the board delay each way (0.5 ns: about 7 cm of trace).
    """
    sdram = SDRAM_TIMING[board.chip.name]
    sd = SD_DEFAULT_SPEED
    sdram_out = [f"sdram_0__{n}__io{'[*]' if bus else ''}"
                 for n, bus in (("clk_en", False), ("cs", False), ("we", False),
                                ("ras", False), ("cas", False), ("ba", True), ("a", True),
                                ("dqm", True))]
    dq = ["sdram_0__dq__io[*]"]
    sd_io = ["sd_card_0__cmd__io", "sd_card_0__dat__io[*]"]
    async_in = [f"sensor_uart_{n}__rx__io" for n in range(board.uarts)]
    async_in += [f"{board.button[0]}_{board.button[1]}__io",
                 f"{board.reset[0]}_{board.reset[1]}__io"]
    leds = [f"led_{n}__io" for n in range(board.leds)]
    pll_sys = "[get_pins -compatibility_mode {*|pll1|clk[0]}]"
    pll_sdram = "[get_pins -compatibility_mode {*|pll1|clk[1]}]"
    t = trace_ns
    lines = [
        "# --- maglog board constraints (hw/platform/quartus.py) ---",
        "# PLL outputs: c0 the system clock, c1 the SDRAM clock (same frequency, shifted).",
        "derive_pll_clocks",
        "derive_clock_uncertainty",
        "",
        "# The SDRAM clock as it leaves its pin (a DDR output clocked by c1).",
        f"create_generated_clock -name sdram_clk_pin -source {pll_sdram} "
        f"{_ports(['sdram_0__clk__io'])}",
        "# The SD clock as it leaves its pin: a register toggled by the system clock, at most",
        "# f_sys / 2 (divisor 0, 25 MHz at 50 MHz).",
        f"create_generated_clock -name sd_clk_pin -source {pll_sys} -divide_by 2 "
        f"{_ports(['sd_card_0__clk__io'])}",
        "",
        f"# SDRAM ({board.chip.name}, CL2): the chip samples on its clock's rising edge",
        f"# (tIS {sdram.t_is} ns, tIH {sdram.t_ih} ns) and drives read data tAC {sdram.t_ac} ns",
        f"# after an edge, held tOH {sdram.t_oh} ns after the next; board trace {t} ns.",
        f"set_output_delay -clock sdram_clk_pin -max {sdram.t_is + t:g} {_ports(sdram_out + dq)}",
        f"set_output_delay -clock sdram_clk_pin -min {-sdram.t_ih + t:g} {_ports(sdram_out + dq)}",
        f"set_input_delay -clock sdram_clk_pin -max {sdram.t_ac + t:g} {_ports(dq)}",
        f"set_input_delay -clock sdram_clk_pin -min {sdram.t_oh + t:g} {_ports(dq)}",
        "# Read data launched at one SDRAM clock edge is captured by the controller at the",
        "# system clock edge after the next one (its read pipeline counts CL + 2 from the",
        "# command): two system clock periods from launch to capture, less the shift.",
        f"set_multicycle_path -setup -end 2 -from {_ports(dq)}",
        "",
        "# SD card (default speed): the card drives CMD/DAT tODLY after the falling CLK edge",
        "# and samples them on the rising edge. The host changes its outputs on the falling",
        "# edge, a system clock before a rising one at the fastest divisor: hold is one",
        "# system clock further than the default relation.",
        f"set_input_delay -clock sd_clk_pin -clock_fall -max {sd.t_odly + 2 * t:g} "
        f"{_ports(sd_io)}",
        f"set_input_delay -clock sd_clk_pin -clock_fall -min {sd.t_oh + 2 * t:g} "
        f"{_ports(sd_io)}",
        f"set_output_delay -clock sd_clk_pin -max {sd.t_isu + t:g} {_ports(sd_io)}",
        f"set_output_delay -clock sd_clk_pin -min {-sd.t_ih + t:g} {_ports(sd_io)}",
        f"set_multicycle_path -hold 1 -to {_ports(sd_io)}",
        "",
        "# Asynchronous inputs (synchronised inside) and LEDs: no timing relation.",
        f"set_false_path -from {_ports(async_in)}",
        f"set_false_path -to {_ports(leds)}",
    ]
    return "\n".join(lines) + "\n"


def qsf_settings(board):
    """Global assignments added to Amaranth's qsf."""
    return "\n".join([
        "# --- maglog board settings (hw/platform/quartus.py) ---",
        'set_global_assignment -name FAMILY "Cyclone IV E"',
        'set_global_assignment -name STRATIX_DEVICE_IO_STANDARD "3.3-V LVTTL"',
        f"set_global_assignment -name SDC_FILE {PROJECT_NAME}.sdc",
        f"set_global_assignment -name QIP_FILE {CPU_MODULE}/synthesis/{CPU_MODULE}.qip",
    ]) + "\n"


#: Bytes of on-chip memory for the NIOS II firmware, per board (M9K blocks are 1 KiB: the
#: EP4CE6 has 30, the logger itself is budgeted at 20, the NIOS II/e takes about 2).
FIRMWARE_BYTES = {"de0nano": 32768, "logger-ep4ce6": 8192}


def qsys_script(board, *, logger_address_width):
    """The qsys-script Tcl that creates the NIOS II/e system ``maglog_cpu``: clock source,
    NIOS II/e (Tiny), on-chip memory for the firmware, JTAG UART, and an Avalon-MM bridge
    whose master is exported as ``bridge`` (the board top connects it to the logger)."""
    platform = board.platform()
    device = f"{platform.device}{platform.package}{platform.speed}"
    memory = FIRMWARE_BYTES[board.name]
    return f"""\
# qsys-script --script=maglog_cpu.tcl : creates maglog_cpu.qsys (generated by maglog,
# hw/platform/quartus.py). NIOS II/e, {memory} bytes of on-chip memory, JTAG UART, and an
# Avalon-MM bridge exported as `bridge` for the logger's registers at 0x{LOGGER_BASE:04X}.
package require -exact qsys 16.1

create_system {CPU_MODULE}
set_project_property DEVICE_FAMILY {{Cyclone IV E}}
set_project_property DEVICE {device}

add_instance clk_0 clock_source
set_instance_parameter_value clk_0 clockFrequency 50000000.0
set_instance_parameter_value clk_0 clockFrequencyKnown true
set_instance_parameter_value clk_0 resetSynchronousEdges DEASSERT

add_instance cpu altera_nios2_gen2
set_instance_parameter_value cpu impl Tiny
set_instance_parameter_value cpu resetSlave onchip_memory.s1
set_instance_parameter_value cpu resetOffset 0x00000000
set_instance_parameter_value cpu exceptionSlave onchip_memory.s1
set_instance_parameter_value cpu exceptionOffset 0x00000020

add_instance onchip_memory altera_avalon_onchip_memory2
set_instance_parameter_value onchip_memory dataWidth 32
set_instance_parameter_value onchip_memory memorySize {memory}.0
set_instance_parameter_value onchip_memory initMemContent true
set_instance_parameter_value onchip_memory useNonDefaultInitFile true
set_instance_parameter_value onchip_memory initializationFileName maglog_fw.hex

add_instance jtag_uart altera_avalon_jtag_uart

add_instance bridge altera_avalon_mm_bridge
set_instance_parameter_value bridge DATA_WIDTH 32
set_instance_parameter_value bridge SYMBOL_WIDTH 8
set_instance_parameter_value bridge ADDRESS_WIDTH {logger_address_width}
set_instance_parameter_value bridge ADDRESS_UNITS SYMBOLS
set_instance_parameter_value bridge MAX_BURST_SIZE 1
set_instance_parameter_value bridge MAX_PENDING_RESPONSES 1
set_instance_parameter_value bridge PIPELINE_COMMAND 1
set_instance_parameter_value bridge PIPELINE_RESPONSE 1

# Clocks and resets.
foreach target {{cpu.clk onchip_memory.clk1 jtag_uart.clk bridge.clk}} {{
    add_connection clk_0.clk $target
}}
foreach target {{cpu.reset onchip_memory.reset1 jtag_uart.reset bridge.reset}} {{
    add_connection clk_0.clk_reset $target
    add_connection cpu.debug_reset_request $target
}}

# Address map.
add_connection cpu.instruction_master onchip_memory.s1
set_connection_parameter_value cpu.instruction_master/onchip_memory.s1 baseAddress 0x0000
add_connection cpu.data_master onchip_memory.s1
set_connection_parameter_value cpu.data_master/onchip_memory.s1 baseAddress 0x0000
add_connection cpu.instruction_master cpu.debug_mem_slave
set_connection_parameter_value cpu.instruction_master/cpu.debug_mem_slave baseAddress 0x8000
add_connection cpu.data_master cpu.debug_mem_slave
set_connection_parameter_value cpu.data_master/cpu.debug_mem_slave baseAddress 0x8000
add_connection cpu.data_master bridge.s0
set_connection_parameter_value cpu.data_master/bridge.s0 baseAddress 0x{LOGGER_BASE:04X}
add_connection cpu.data_master jtag_uart.avalon_jtag_slave
set_connection_parameter_value cpu.data_master/jtag_uart.avalon_jtag_slave baseAddress 0x9800
add_connection cpu.irq jtag_uart.irq
set_connection_parameter_value cpu.irq/jtag_uart.irq irqNumber 0

# Exports: clk_clk, reset_reset_n, bridge_* (the board top's instance of {CPU_MODULE}).
add_interface clk clock sink
set_interface_property clk EXPORT_OF clk_0.clk_in
add_interface reset reset sink
set_interface_property reset EXPORT_OF clk_0.clk_in_reset
add_interface bridge avalon master
set_interface_property bridge EXPORT_OF bridge.m0

save_system {CPU_MODULE}.qsys
"""


def build_script(board):
    """``build.sh``: the NIOS II system, then the whole project (needs Quartus Prime on PATH:
    qsys-script, qsys-generate, quartus_sh)."""
    platform = board.platform()
    device = f"{platform.device}{platform.package}{platform.speed}"
    return f"""\
#!/bin/sh
# Builds {PROJECT_NAME}.sof for {board.name} (generated by maglog hdl build). Needs Quartus
# Prime (Lite) with Platform Designer on PATH. The NIOS II firmware image maglog_fw.hex
# (on-chip memory contents) is made by the NIOS II SBT from the firmware sources; without
# it the memory starts empty and the firmware is loaded over JTAG (nios2-download).
set -e
cd "$(dirname "$0")"
missing=""
for tool in qsys-script qsys-generate quartus_sh; do
  command -v "$tool" >/dev/null 2>&1 || missing="$missing $tool"
done
if [ -n "$missing" ]; then
  echo "build.sh: Quartus Prime with Platform Designer is not on PATH (not found:$missing);" \
       "add its bin folders (quartus/bin, quartus/sopc_builder/bin) to PATH" >&2
  exit 1
fi
qsys-script --script={CPU_MODULE}.tcl
qsys-generate {CPU_MODULE}.qsys --synthesis=VERILOG --output-directory={CPU_MODULE} \\
    --family="Cyclone IV E" --part={device}
quartus_sh --flow compile {PROJECT_NAME}
"""


#: Behavioural stand-ins for Yosys of the megafunctions Amaranth's Intel platform and the board
#: top instantiate (with :data:`CPU_STANDIN`, ``yosys/standins.v``). Not for Quartus.
MEGAFUNCTION_STANDINS = """\
// Stand-ins for Yosys only (maglog hw/platform/quartus.py): Quartus uses its own megafunctions
// and the NIOS II system Platform Designer generates. Enough behaviour to elaborate the top.
module altpll #(
    parameter bandwidth_type = "AUTO", parameter compensate_clock = "CLK0",
    parameter inclk0_input_frequency = 20000, parameter intended_device_family = "",
    parameter lpm_type = "altpll", parameter operation_mode = "NORMAL",
    parameter pll_type = "AUTO", parameter port_areset = "", parameter port_inclk0 = "",
    parameter port_inclk1 = "", parameter port_locked = "", parameter port_clk0 = "",
    parameter port_clk1 = "", parameter port_clk2 = "", parameter port_clk3 = "",
    parameter port_clk4 = "", parameter self_reset_on_loss_lock = "OFF",
    parameter width_clock = 5,
    parameter clk0_multiply_by = 1, parameter clk0_divide_by = 1,
    parameter clk0_duty_cycle = 50, parameter clk0_phase_shift = "0",
    parameter clk1_multiply_by = 1, parameter clk1_divide_by = 1,
    parameter clk1_duty_cycle = 50, parameter clk1_phase_shift = "0"
) (input [1:0] inclk, input areset, output [4:0] clk, output locked);
    // Unity ratios only (the board top's); the phase shift is not modelled.
    assign clk = {3'b000, inclk[0], inclk[0]};
    assign locked = ~areset;
endmodule

module altiobuf_in #(parameter enable_bus_hold = "FALSE", parameter number_of_channels = 1,
                     parameter use_differential_mode = "FALSE")
    (input [number_of_channels-1:0] datain, output [number_of_channels-1:0] dataout);
    assign dataout = datain;
endmodule

module altiobuf_out #(parameter enable_bus_hold = "FALSE", parameter number_of_channels = 1,
                      parameter use_differential_mode = "FALSE", parameter use_oe = "TRUE")
    (input [number_of_channels-1:0] datain, input [number_of_channels-1:0] oe,
     output [number_of_channels-1:0] dataout);
    genvar k;
    generate for (k = 0; k < number_of_channels; k = k + 1) begin : ch
        assign dataout[k] = oe[k] ? datain[k] : 1'bz;
    end endgenerate
endmodule

module altiobuf_bidir #(parameter enable_bus_hold = "FALSE", parameter number_of_channels = 1,
                        parameter use_differential_mode = "FALSE")
    (input [number_of_channels-1:0] datain, input [number_of_channels-1:0] oe,
     inout [number_of_channels-1:0] dataio, output [number_of_channels-1:0] dataout);
    genvar k;
    generate for (k = 0; k < number_of_channels; k = k + 1) begin : ch
        assign dataio[k] = oe[k] ? datain[k] : 1'bz;
    end endgenerate
    assign dataout = dataio;
endmodule

module altddio_out #(parameter width = 1)
    (input [width-1:0] datain_h, input [width-1:0] datain_l, input outclock,
     output [width-1:0] dataout);
    reg [width-1:0] high, low;
    always @(posedge outclock) high <= datain_h;
    always @(negedge outclock) low <= datain_l;
    assign dataout = outclock ? high : low;
endmodule

module altera_std_synchronizer #(parameter depth = 3)
    (input clk, input reset_n, input din, output dout);
    reg [depth-1:0] chain;
    always @(posedge clk or negedge reset_n)
        if (!reset_n) chain <= 0;
        else chain <= {chain[depth-2:0], din};
    assign dout = chain[depth-1];
endmodule

module altera_std_synchronizer_bundle #(parameter width = 1, parameter depth = 3)
    (input clk, input reset_n, input [width-1:0] din, output [width-1:0] dout);
    genvar k;
    generate for (k = 0; k < width; k = k + 1) begin : lane
        altera_std_synchronizer #(.depth(depth)) sync (
            .clk(clk), .reset_n(reset_n), .din(din[k]), .dout(dout[k]));
    end endgenerate
endmodule

"""

#: A stand-in for the NIOS II system: a master that never starts a transfer.
CPU_STANDIN = """\
// The NIOS II system: a master that never starts a transfer.
module maglog_cpu #(parameter ADDRESS_WIDTH = 9)
    (input clk_clk, input reset_reset_n,
     output [ADDRESS_WIDTH-1:0] bridge_address, output bridge_read, output bridge_write,
     output [31:0] bridge_writedata, output [3:0] bridge_byteenable,
     output bridge_burstcount, output bridge_debugaccess,
     input [31:0] bridge_readdata, input bridge_waitrequest, input bridge_readdatavalid);
    assign bridge_address = 0;
    assign bridge_read = 1'b0;
    assign bridge_write = 1'b0;
    assign bridge_writedata = 32'd0;
    assign bridge_byteenable = 4'hF;
    assign bridge_burstcount = 1'b1;
    assign bridge_debugaccess = 1'b0;
endmodule
"""


def project_files(board, **kwargs):
    """``{relative path: text}`` of every file of the project (nothing is written)."""
    return project(board, **kwargs)[1]


def project(board, **kwargs):
    """The board top (elaborated) and ``{relative path: text}`` of the project's files."""
    if isinstance(board, str):
        if board not in BOARDS:
            raise ValueError(f"unknown board {board!r} (boards: {', '.join(BOARDS)})")
        board = BOARDS[board]
    top = BoardTop(board, **kwargs)
    platform = board.platform()
    plan = platform.build(top, name=PROJECT_NAME, do_build=False,
                          add_settings=qsf_settings(board),
                          add_constraints=sdc_constraints(board))
    files = {}
    for name, content in plan.files.items():
        files[name] = content if isinstance(content, str) else content.decode()
    files.pop(f"{PROJECT_NAME}.debug.v", None)
    files[f"{CPU_MODULE}.tcl"] = qsys_script(
        board, logger_address_width=top.bridge_address_width)
    files[f"{PROJECT_NAME}.qpf"] = f'PROJECT_REVISION = "{PROJECT_NAME}"\n'
    files["build.sh"] = build_script(board)
    files["pins.md"] = f"# {board.title}\n\n{pin_table_markdown(board)}\n"
    files["yosys/standins.v"] = MEGAFUNCTION_STANDINS + CPU_STANDIN
    return top, files


def build_project(board, directory, *, force=False, **kwargs):
    """Write the Quartus project for ``board`` (a name of :data:`BOARDS`) into ``directory``.

    ``directory`` must not exist, or be an empty folder, or ``force`` be set. ``kwargs`` go
    to :class:`~.top.BoardTop` (``sdram_phase_ns``, and the logger's own parameters).
    Returns the paths written.
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"{directory}: exists and is not a folder")
    if directory.is_dir() and any(directory.iterdir()) and not force:
        raise ValueError(f"{directory}: folder is not empty (use --force to write into it)")
    files = project_files(board, **kwargs)
    written = []
    for name, text in sorted(files.items()):
        path = directory / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        if name.endswith(".sh"):
            os.chmod(path, 0o755)
        written.append(path)
    return written
