"""The counter bank (hw/counters.py): counts every event at the closest spacing it allows
while the bus reads as often as it can, reads with the CSR bus's timing, the clearing sweep
after reset, and the carry through all 32 bits."""

import random

import pytest
from amaranth import *
from amaranth.hdl import ResetInserter
from amaranth.lib import wiring
from amaranth.lib.wiring import In

from maglog.hw.counters import CounterBank, read_signature
from maglog.sim.backends.amaranth import run_simulation

#: The front end's layout: 8 words per channel, the counters at 1..7 of each.
ADDRESSES = [8 * k + 1 + j for k in range(3) for j in range(7)]


class ResettableBank(wiring.Component):
    """A bank with a reset input of its own (the simulator's domain reset is not a port)."""
    def __init__(self, addresses):
        self.bank = CounterBank(addresses)
        super().__init__({
            "clear":  In(1),
            "events": In(len(addresses)),
            "read":   In(read_signature(self.bank.addr_width, 32)),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.bank = ResetInserter(self.clear)(self.bank)
        m.d.comb += self.bank.events.eq(self.events)
        wiring.connect(m, wiring.flipped(self.read), self.bank.read)
        return m


async def read(ctx, port, address):
    ctx.set(port.addr, address)
    ctx.set(port.r_stb, 1)
    await ctx.tick()
    ctx.set(port.r_stb, 0)
    value = ctx.get(port.r_data)
    await ctx.tick()
    assert ctx.get(port.r_data) == 0, "read data must be zero a cycle later"
    return value


def test_layout():
    bank = CounterBank(ADDRESSES)
    assert bank.depth == 32 and bank.addr_width == 5
    assert bank.min_event_spacing == 65
    assert CounterBank([0, 1]).depth == 2
    with pytest.raises(ValueError, match="distinct"):
        CounterBank([1, 1])
    with pytest.raises(ValueError, match="non-negative integers"):
        CounterBank([])
    with pytest.raises(ValueError, match="from 2 to 64"):
        CounterBank([1], width=1)


def test_no_event_is_lost_at_the_closest_spacing_under_the_busiest_bus():
    """Every counter gets events as close as ``min_event_spacing`` allows (and often all of
    them in the same cycle), while the bus reads every other cycle, the most it may: each
    read is at most one sweep behind, never ahead, and the final counts are exact."""
    dut = CounterBank(ADDRESSES)
    rng = random.Random(5)
    spacing = dut.min_event_spacing
    cycles = 6000
    times = []                 # per counter, the cycles of its events
    for _ in ADDRESSES:
        t, mine = rng.randrange(dut.depth + 2, dut.depth + 2 + spacing), []
        while t < cycles:
            mine.append(t)
            t += spacing + (0 if rng.random() < 0.7 else rng.randrange(40))
        times.append(mine)
    schedule = {}
    for i, mine in enumerate(times):
        for t in mine:
            schedule[t] = schedule.get(t, 0) | 1 << i
    assert max(len(m) for m in times) > cycles // (spacing + 40)
    checked = [0]

    async def events(ctx):
        for cycle in range(cycles):
            ctx.set(dut.events, schedule.get(cycle, 0))
            await ctx.tick()
        ctx.set(dut.events, 0)

    async def reader(ctx):
        cycle = 0
        while cycle < cycles:
            i = rng.randrange(len(ADDRESSES))
            value = await read(ctx, dut.read, ADDRESSES[i])
            # The read was strobed on `cycle`: events up to one sweep earlier are counted.
            done = sum(t < cycle - spacing for t in times[i])
            seen = sum(t < cycle for t in times[i])
            assert done <= value <= seen, (i, cycle, value, done, seen)
            checked[0] += 1
            cycle += 2
        await ctx.tick().repeat(spacing)
        for i, address in enumerate(ADDRESSES):
            assert await read(ctx, dut.read, address) == len(times[i]), ADDRESSES[i]

    run_simulation(dut, [events, reader], name="counter_bank_busy")
    assert checked[0] == cycles // 2


def test_reads_have_the_csr_timing_and_other_words_read_zero():
    dut = CounterBank([3, 5])

    async def bench(ctx):
        await ctx.tick().repeat(dut.depth + 1)           # the clearing sweep
        for _ in range(3):
            ctx.set(dut.events, 0b10)
            await ctx.tick()
            ctx.set(dut.events, 0)
            await ctx.tick().repeat(dut.min_event_spacing)
        for _ in range(2 * dut.depth):          # the scanner reads, the bus sees nothing
            assert ctx.get(dut.read.r_data) == 0
            await ctx.tick()
        assert [await read(ctx, dut.read, a) for a in range(dut.depth)] == [0] * 5 + [3] + [0] * 2

    run_simulation(dut, [bench], name="counter_bank_timing")


def test_reset_clears_every_word_with_a_sweep():
    dut = ResettableBank(ADDRESSES)
    bank = dut.bank

    async def bench(ctx):
        await ctx.tick().repeat(bank.depth + 1)
        ctx.set(dut.events, (1 << len(ADDRESSES)) - 1)
        await ctx.tick()
        ctx.set(dut.events, 0)
        await ctx.tick().repeat(bank.min_event_spacing)
        assert [await read(ctx, dut.read, a) for a in ADDRESSES] == [1] * len(ADDRESSES)
        ctx.set(dut.clear, 1)
        await ctx.tick()
        ctx.set(dut.clear, 0)
        # An event during the sweep waits in its flag; reads during it show zero.
        ctx.set(dut.events, 1)
        await ctx.tick()
        ctx.set(dut.events, 0)
        assert await read(ctx, dut.read, ADDRESSES[1]) == 0
        await ctx.tick().repeat(bank.depth + bank.min_event_spacing)
        assert [await read(ctx, dut.read, a) for a in ADDRESSES] == [1] + [0] * (len(ADDRESSES) - 1)

    run_simulation(dut, [bench], name="counter_bank_reset")


@pytest.mark.parametrize("start,end", [(0xFFFF, 0x10000), (0x7FFFFFFF, 0x80000000),
                                       (0xFFFFFFFE, 0xFFFFFFFF), (0xFFFFFFFF, 0)])
def test_the_increment_carries_through_all_32_bits(start, end):
    dut = CounterBank([1, 2])

    async def bench(ctx):
        await ctx.tick().repeat(dut.depth + 1)
        ctx.set(dut.memory.data[2], start)
        ctx.set(dut.events, 0b10)
        await ctx.tick()
        ctx.set(dut.events, 0)
        await ctx.tick().repeat(dut.min_event_spacing)
        assert await read(ctx, dut.read, 2) == end
        assert await read(ctx, dut.read, 1) == 0

    run_simulation(dut, [bench], name="counter_bank_carry")
