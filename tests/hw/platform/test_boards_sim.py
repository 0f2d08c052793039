"""The board top in simulation (Icarus, the generated Verilog with the megafunction stand-ins):
a NIOS II stand-in that reads and writes the logger's registers through the exported Avalon
master (byte addresses, waitrequest, readdatavalid), and the SDRAM pins after reset (levels
and polarity on the pins, the first command of the initialisation)."""

import re
import subprocess

import pytest

from maglog.hw.platform.boards import BOARDS
from maglog.hw.platform.quartus import MEGAFUNCTION_STANDINS, PROJECT_NAME, project
from maglog.hw.top import LOGGER_ID
from maglog.sw.regmap import RegisterMap

FW_VALUE = 0x0ABCDE5      # state 5, error 0xDE, file 0xABC (logger.fw_status fields)


def _cpu(address_width, id_addr, fw_addr, wd_control, wd_status):
    """A NIOS II stand-in: reads logger.id, writes logger.fw_status and reads it back, each
    as an Avalon-MM master must (command held while waitrequest, data on readdatavalid);
    then starts the watchdog with a 0 ms timeout and waits to be reset by it, and after the
    reset reads fw_status (cleared with the logger) and the watchdog's reset_cause."""
    return f"""\
`timescale 1ns/1ps
module maglog_cpu(
    input clk_clk, input reset_reset_n,
    output reg [{address_width - 1}:0] bridge_address, output reg bridge_read,
    output reg bridge_write, output reg [31:0] bridge_writedata,
    output [3:0] bridge_byteenable, output bridge_burstcount, output bridge_debugaccess,
    input [31:0] bridge_readdata, input bridge_waitrequest, input bridge_readdatavalid);
    assign bridge_byteenable = 4'hF;
    assign bridge_burstcount = 1'b1;
    assign bridge_debugaccess = 1'b0;
    reg [31:0] data;
    task read(input [{address_width - 1}:0] address);
        begin
            bridge_address <= address; bridge_read <= 1'b1;
            @(posedge clk_clk);
            while (bridge_waitrequest) @(posedge clk_clk);
            bridge_read <= 1'b0;
            @(posedge clk_clk);
            while (!bridge_readdatavalid) @(posedge clk_clk);
            data = bridge_readdata;
        end
    endtask
    task write(input [{address_width - 1}:0] address, input [31:0] value);
        begin
            bridge_address <= address; bridge_writedata <= value; bridge_write <= 1'b1;
            @(posedge clk_clk);
            while (bridge_waitrequest) @(posedge clk_clk);
            bridge_write <= 1'b0;
        end
    endtask
    initial begin
        bridge_read = 1'b0; bridge_write = 1'b0; bridge_address = 0; bridge_writedata = 0;
        wait (reset_reset_n === 1'b1);
        repeat (4) @(posedge clk_clk);
        read({4 * id_addr});
        $display("ID %08x", data);
        write({4 * fw_addr}, 32'h{FW_VALUE:08x});
        read({4 * fw_addr});
        $display("FW %08x", data);
        write({4 * wd_control}, 32'h00000001);        // enable, timeout_ms 0
        wait (reset_reset_n === 1'b0);
        wait (reset_reset_n === 1'b1);
        repeat (4) @(posedge clk_clk);
        read({4 * fw_addr});
        $display("FW AFTER %08x", data);
        read({4 * wd_status});
        $display("CAUSE %08x", data);
    end
endmodule
"""


def _bench(board, cycles):
    reset = "rst_0__io" if board.reset == ("rst", 0) else "button_0__io"
    button = f"{board.button[0]}_{board.button[1]}__io"
    width = board.chip.geometry.data_width
    uarts = "".join(f", .sensor_uart_{n}__rx__io(1'b1)" for n in range(board.uarts))
    return f"""\
`timescale 1ns/1ps
module tb;
    reg clk = 1'b0;
    always #10 clk = ~clk;
    wire [{width - 1}:0] dq;
    wire cmd;
    wire [3:0] dat;
    pullup (cmd);
    pullup (dat[0]); pullup (dat[1]); pullup (dat[2]); pullup (dat[3]);
    wire sdram_clk, cs, ras, cas, we;
    wire [{board.chip.geometry.address_bits - 1}:0] a;
    {PROJECT_NAME} dut(
        .clk50_0__io(clk), .{reset}(1'b1), .{button}(1'b1){uarts},
        .sdram_0__clk__io(sdram_clk), .sdram_0__cs__io(cs), .sdram_0__ras__io(ras),
        .sdram_0__cas__io(cas), .sdram_0__we__io(we), .sdram_0__a__io(a),
        .sdram_0__dq__io(dq), .sd_card_0__cmd__io(cmd), .sd_card_0__dat__io(dat));
    // A command is a clock edge with CS# low and RAS# CAS# WE# not 111 (NOP).
    integer first_command = -1, cycle = 0, nop_or_deselect = 0, clock_edges = 0;
    always @(posedge clk) cycle <= cycle + 1;
    always @(negedge dut.cpu.reset_reset_n) if (cycle > 2) $display("CPU RESET %0d", cycle);
    always @(posedge sdram_clk) begin
        clock_edges = clock_edges + 1;
        if (first_command < 0 && cycle > 2) begin
            if (cs === 1'b1 || (cs === 1'b0 && {{ras, cas, we}} === 3'b111))
                nop_or_deselect = nop_or_deselect + 1;
            else begin
                first_command = cycle;
                $display("CMD %0d %b %b%b%b A10 %b", cycle, cs, ras, cas, we, a[10]);
            end
        end
    end
    initial begin
        #({cycles} * 20);
        $display("IDLE %0d EDGES %0d", nop_or_deselect, clock_edges);
        $finish;
    end
endmodule
"""


@pytest.mark.parametrize("name", sorted(BOARDS))
def test_board_top_registers_and_sdram_pins(name, tmp_path, external):
    iverilog = external.tool("iverilog", why="simulating the board top")
    vvp = external.tool("vvp", why="simulating the board top")
    board = BOARDS[name]
    top, files = project(name)
    regs = RegisterMap(top.logger.csr_memory_map)
    (tmp_path / "top.v").write_text(files[f"{PROJECT_NAME}.v"])
    (tmp_path / "standins.v").write_text(MEGAFUNCTION_STANDINS)
    (tmp_path / "cpu.v").write_text(_cpu(
        top.bridge_address_width, regs["logger_id"].address, regs["logger_fw_status"].address,
        regs["watchdog_control"].address, regs["watchdog_status"].address))
    # Cycles at 50 MHz: the power-up wait (the controller times it in refresh intervals).
    t = board.chip.timing
    power_up = round(t.power_up_us * 50)
    refresh = round(t.t_ref_ms * 1e-3 / board.chip.geometry.rows * 50e6)
    # The run also covers the watchdog's first millisecond tick (at most 1 ms after start).
    (tmp_path / "tb.v").write_text(_bench(board, max(power_up + refresh, 50_000) + 1000))
    build = subprocess.run([iverilog, "-g2012", "-o", "sim.vvp", "-s", "tb", "tb.v", "cpu.v",
                            "standins.v", "top.v"], cwd=tmp_path, capture_output=True,
                           text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-3000:]
    run = subprocess.run([vvp, "-n", "sim.vvp"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = run.stdout
    assert f"ID {LOGGER_ID:08x}" in out, out
    assert f"FW {FW_VALUE:08x}" in out, out
    # The watchdog resets the NIOS II (and the logger's body, so fw_status is 0 again) and
    # says so in reset_cause.
    resets = [int(c) for c in re.findall(r"CPU RESET (\d+)", out)]
    assert len(resets) == 1 and resets[0] <= 50_000 + 1000, out
    assert "FW AFTER 00000000" in out and "CAUSE 00000001" in out, out
    # Through the power-up time the pins carry NOP or deselect (levels as the chip reads
    # them: active-low pins not inverted twice), with the SDRAM clock running; the first
    # command is a PRECHARGE ALL (CS# RAS# CAS# WE# = 0 0 1 0, A10 high).
    idle, edges = map(int, re.search(r"IDLE (\d+) EDGES (\d+)", out).groups())
    assert edges >= power_up
    m = re.search(r"CMD (\d+) 0 (\d{3}) A10 (\d)", out)
    assert m is not None, out
    assert m.group(2) == "010" and m.group(3) == "1"
    assert power_up <= int(m.group(1)) < power_up + refresh + 100
    assert idle == int(m.group(1)) - 3
