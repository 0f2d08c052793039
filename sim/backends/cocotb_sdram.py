"""cocotb bench: the SDRAM controller's generated Verilog against the chip model.

The stimulus names the chip preset, CAS latency, clock and a seed; random word requests go
in through the native port, read data is checked against a plain memory, and the chip model
checks every timing rule at every clock (Python per clock: keep runs short).
"""

import json
import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import ReadOnly, RisingEdge

from ...hw.arch import sdram as arch
from ..models.sdram import PINS
from .amaranth import CLOCK_HZ, CLOCK_NS


async def run_chip(dut, model, *, prefix="pins__"):
    """The chip model on the ``{prefix}*`` ports (``pins__`` on the controller's own Verilog,
    ``sdram_`` on the logger's): it sees the values each edge samples."""
    pins = [(name, getattr(dut, prefix + name)) for name in PINS]
    dq_o, dq_i = getattr(dut, prefix + "dq_o"), getattr(dut, prefix + "dq_i")
    while True:
        await ReadOnly()
        levels = {name: int(pin.value) for name, pin in pins}
        dq = int(dq_o.value)
        await RisingEdge(dut.clk)
        out = model.edge(**levels, dq=dq)
        dq_i.value = 0 if out is None else out


@cocotb.test()
async def random_traffic(dut):
    from ..models.sdram import SdramChip
    with open(os.environ["MAGLOG_STIMULUS"]) as f:
        stimulus = json.load(f)
    chip = arch.CHIPS[stimulus["chip"]]
    g = chip.geometry
    model = SdramChip(chip, clk_freq=CLOCK_HZ, strict=False)
    Clock(dut.clk, CLOCK_NS, unit="ns", impl="gpi").start()
    dut.i__valid.value = 0
    dut.rst.value = 1
    for _ in range(2):
        await RisingEdge(dut.clk)
    dut.rst.value = 0
    cocotb.start_soon(run_chip(dut, model))

    rng = random.Random(stimulus["seed"])
    memory, expected, got = {}, [], []

    async def sink():
        while True:
            await ReadOnly()
            if str(dut.o__valid.value) == "1":
                got.append(int(dut.o__payload.value))
                await RisingEdge(dut.clk)
            else:
                await RisingEdge(dut.o__valid)

    while str(dut.ready.value) != "1":
        await RisingEdge(dut.clk)
    cocotb.start_soon(sink())
    rows = [rng.randrange(g.rows) for _ in range(2)]
    full = (1 << g.data_width // 8) - 1
    for _ in range(stimulus["requests"]):
        addr = (((rng.choice(rows) * g.banks + rng.randrange(g.banks)) << g.column_bits)
                | rng.randrange(g.columns))
        write = rng.random() < 0.5
        data = rng.getrandbits(g.data_width)
        mask = rng.choice([full, 1])
        if write:
            word = memory.get(addr, 0)
            for byte in range(g.data_width // 8):
                if mask >> byte & 1:
                    lane = 0xFF << (8 * byte)
                    word = (word & ~lane) | (data & lane)
            memory[addr] = word
        else:
            expected.append(memory.get(addr, 0))
        payload = (int(write) | addr << 1 | data << (1 + g.word_address_bits)
                   | mask << (1 + g.word_address_bits + g.data_width))
        dut.i__payload.value = payload
        dut.i__valid.value = 1
        while True:
            await ReadOnly()
            taken = str(dut.i__ready.value) == "1"
            await RisingEdge(dut.clk)
            if taken:
                break
    dut.i__valid.value = 0
    for _ in range(64):
        await RisingEdge(dut.clk)
    result = {"mismatches": [], "errors": model.errors[:20],
              "refreshes": int(dut.refreshes.value), "reads": len(got)}
    if got != expected:
        first = next((k for k, (a, b) in enumerate(zip(got, expected)) if a != b),
                     min(len(got), len(expected)))
        result["mismatches"].append(f"read {first} differs ({len(got)} reads, "
                                    f"{len(expected)} expected)")
    with open(os.environ["MAGLOG_RESULT"], "w") as f:
        json.dump(result, f)
    assert not result["mismatches"] and not model.errors, result
