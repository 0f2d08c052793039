"""SdramController against the timing-checking chip model: random traffic equals a plain
memory, over many refresh intervals, for both presets and CAS latency 2 and 3."""

import random

import pytest

from maglog.hw.arch.sdram import IS42S16160, MT48LC4M32B2
from maglog.hw.sdram import SdramController
from maglog.sim.backends.amaranth import CLOCK_HZ
from maglog.sim.backends.amaranth import run_requests

#: The simulated clock, which the controller and the chip model time their rules by.
CLK_FREQ = CLOCK_HZ


def traffic(rng, geometry, count, *, sequential=False):
    """Word requests: (write, addr, data, mask); addresses from a few rows of every bank."""
    words = geometry.words
    rows = [rng.randrange(geometry.rows) for _ in range(3)]
    requests = []
    addr = rng.randrange(words)
    for _ in range(count):
        if sequential:
            addr = (addr + 1) % words
        else:
            row = rng.choice(rows)
            bank = rng.randrange(geometry.banks)
            column = rng.randrange(geometry.columns)
            addr = ((row * geometry.banks + bank) << geometry.column_bits) | column
        write = rng.random() < 0.5
        mask = rng.choice([(1 << geometry.data_width // 8) - 1, 1, 0b10])
        requests.append((write, addr, rng.getrandbits(geometry.data_width), mask))
    return requests


def expected_reads(requests, geometry):
    """What a plain memory returns for the reads (unwritten words are 0)."""
    memory, reads = {}, []
    for write, addr, data, mask in requests:
        if write:
            word = memory.get(addr, 0)
            for byte in range(geometry.data_width // 8):
                if mask >> byte & 1:
                    lane = 0xFF << (8 * byte)
                    word = (word & ~lane) | (data & lane)
            memory[addr] = word
        else:
            reads.append(memory.get(addr, 0))
    return reads


def run(chip, cas_latency, requests):
    return run_requests(chip, requests, clk_freq=CLK_FREQ, cas_latency=cas_latency)


@pytest.mark.parametrize("chip", [MT48LC4M32B2, IS42S16160], ids=lambda c: c.name)
@pytest.mark.parametrize("cas_latency", [2, 3])
def test_random_traffic_equals_a_plain_memory(chip, cas_latency):
    rng = random.Random(f"{chip.name}-{cas_latency}")
    requests = traffic(rng, chip.geometry, 3000)
    got, info, model = run(chip, cas_latency, requests)
    assert got == expected_reads(requests, chip.geometry)
    assert model.errors == []
    assert info["refreshes"] >= 3


@pytest.mark.parametrize("chip", [MT48LC4M32B2, IS42S16160], ids=lambda c: c.name)
def test_random_traffic_at_a_fast_clock_keeps_every_timing_rule(chip):
    # At 133 MHz tRAS, tRC, tRP, tRCD and tWR are several clocks each, so the timers (not
    # the order of the states) must keep them; rows of one bank are switched often.
    clk_freq = 133e6
    rng = random.Random(f"fast-{chip.name}")
    requests = traffic(rng, chip.geometry, 3000)
    got, info, model = run_requests(chip, requests, clk_freq=clk_freq, cas_latency=3)
    assert got == expected_reads(requests, chip.geometry)
    assert model.errors == []
    assert info["refreshes"] >= 2


def test_long_run_over_many_refresh_intervals():
    chip = IS42S16160                      # 390 clocks between refreshes at 50 MHz
    rng = random.Random(4)
    requests = traffic(rng, chip.geometry, 12000)
    got, info, model = run(chip, 2, requests)
    assert got == expected_reads(requests, chip.geometry)
    assert info["refreshes"] >= 30


@pytest.mark.parametrize("chip", [MT48LC4M32B2, IS42S16160], ids=lambda c: c.name)
def test_sequential_reads_stream_at_near_one_word_a_clock(chip):
    rng = random.Random(2)
    count = 4 * chip.geometry.columns
    requests = [(False, k, 0, 0) for k in range(count)]
    got, info, model = run(chip, 2, requests)
    assert len(got) == count
    assert count / (info["last"] - info["first"] + 1) > 0.8


def test_parameters_are_checked():
    with pytest.raises(ValueError, match="CAS latency must be 2 or 3, not 4"):
        SdramController(MT48LC4M32B2, clk_freq=CLK_FREQ, cas_latency=4)
    with pytest.raises(TypeError, match="Chip must be an arch.sdram.Chip"):
        SdramController("MT48", clk_freq=CLK_FREQ)


@pytest.mark.cocotb
@pytest.mark.parametrize("simulator", ["icarus", "verilator"])
def test_controller_verilog_against_the_model_under_cocotb(simulator, external, tmp_path):
    from amaranth.back import verilog
    from maglog.sim.backends.cocotb import CocotbBuild
    external.simulator(simulator)
    chip = IS42S16160
    build = CocotbBuild(simulator, tmp_path, "maglog_sdram")
    build.build(verilog.convert(SdramController(chip, clk_freq=CLK_FREQ, cas_latency=3),
                                name="maglog_sdram"))
    result = build.run("maglog.sim.backends.cocotb_sdram",
                       {"chip": chip.name, "seed": 9, "requests": 2500})
    assert result["mismatches"] == [] and result["errors"] == []
    assert result["refreshes"] >= 3 and result["reads"] > 1000
