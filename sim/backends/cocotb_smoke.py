"""The smallest cocotb bench: it lets a design's clock run and reports which simulator ran it.

For checks of the build itself (which Verilator, which options), not of a design: the
stimulus names ``cycles``; the result holds the simulator's name and version and the value
of the design's ``count`` output after that many cycles out of reset.
"""

import json
import os

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import ClockCycles, ReadOnly, RisingEdge

from .amaranth import CLOCK_NS


@cocotb.test()
async def count_cycles(dut):
    with open(os.environ["MAGLOG_STIMULUS"]) as f:
        stimulus = json.load(f)
    Clock(dut.clk, CLOCK_NS, unit="ns", impl="gpi").start()
    dut.rst.value = 1
    await RisingEdge(dut.clk)
    dut.rst.value = 0
    await ClockCycles(dut.clk, stimulus["cycles"])
    await ReadOnly()
    result = {"simulator": cocotb.SIM_NAME, "version": cocotb.SIM_VERSION,
              "count": int(dut.count.value)}
    with open(os.environ["MAGLOG_RESULT"], "w") as f:
        json.dump(result, f)
