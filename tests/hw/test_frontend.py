"""The whole front end (UART, filter, arbiter) on the Amaranth simulator."""

import random

import numpy as np
import pytest
from amaranth import Module
from amaranth.lib import wiring
from amaranth.lib.wiring import In

from maglog.hw.arch.frames import COUNTER_NAMES
from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import (ChannelConfig, DEFAULT_CHANNELS, FrontEnd, FrontEndRegisters,
                                divisor_for, register_address)
from maglog.hw.soc import csr
from maglog.sim.backends.amaranth import drive_line, run_simulation
from maglog.sim.stimulus import sentences
from maglog.sim.runners.frontend import FrontEndBench, read_counter
from maglog.sim.stimulus.uart_line import ChannelStimulus, encode, segments_from_levels
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.streams import demo_streams


def test_demo_flight_matches_reference():
    streams = demo_streams(seconds=2.0, seed=11)
    bench = FrontEndBench(backend="amaranth")
    stimuli = [ChannelStimulus(divisor=1, data=streams[name]) for name in ("mag", "gps", "cesium")]
    result = bench.run(stimuli)
    for k, (config, name) in enumerate(zip(DEFAULT_CHANNELS, ("mag", "gps", "cesium"))):
        ref = reference_filter(Kind(config.kind.value), streams[name])
        assert result.frames_of(k) == ref.frames
        assert result.counters[k] == ref.counters
    gps = reference_filter(Kind.NMEA, streams["gps"])
    assert result.flushes == len(gps.flushes) > 0


def test_line_faults_drop_only_the_damaged_frames():
    rng = random.Random(3)
    frames = [sentences.gga(100.0 + i, 48.1, 11.5, quality=1 + i % 3) for i in range(6)]
    data = b"".join(frames)
    starts = np.cumsum([0] + [len(f) for f in frames])
    # A framing error in frame 1, a break before frame 3, a glitch before frame 4.
    trace = encode(data, bit_cycles=16, framing_errors=[int(starts[1]) + 20],
                   breaks=[(int(starts[3]) + 5, 25)], glitches=[(int(starts[4]), 3)])
    bench = FrontEndBench([ChannelConfig(ChannelKind.NMEA, 9600)], backend="amaranth")
    result = bench.run([ChannelStimulus(divisor=1, segments=trace.segments)])
    expected = [frames[i] for i in (0, 2, 4, 5)]
    assert result.frames_of(0) == expected
    assert result.counters[0]["uart_error"] == 2
    assert result.counters[0] == reference_filter(Kind.NMEA, trace.expected).counters
    assert result.flushes == 4


@pytest.mark.parametrize("baud_error", [0.0, -0.02, 0.02])
@pytest.mark.parametrize("offset", [3, 29, 39, 43])
def test_continuous_stream_loses_only_the_damaged_frame(offset, baud_error):
    # Back-to-back characters, no idle time; one stop bit forced to space. Offsets 39-43
    # damage the `*hh` CR LF at the end of the frame, right before the next frame's `$`.
    frames = [sentences.pmag1(i, 1000.5 * i, -2.5 * i, 45000.0) for i in range(6)]
    data = b"".join(frames)
    clean = encode(data, bit_cycles=16, baud_error=baud_error)
    levels = clean.levels().copy()
    damaged = len(frames[0]) * 2 + offset        # a byte of frame 2
    bit = clean.bit_period
    stop = clean.byte_starts[damaged] + round(9 * bit)
    levels[stop:stop + round(bit)] = 0
    bench = FrontEndBench([ChannelConfig(ChannelKind.PMAG, 115200)], backend="amaranth")
    result = bench.run([ChannelStimulus(divisor=1, segments=segments_from_levels(levels))])
    assert result.frames_of(0) == frames[:2] + frames[3:]
    assert result.counters[0]["uart_error"] == 1


def test_divisors_default_to_the_nominal_rates():
    fe = FrontEnd(clk_freq=50e6)
    assert [c.divisor.init for c in fe.channels] == [divisor_for(50e6, 115200),
                                                     divisor_for(50e6, 9600),
                                                     divisor_for(50e6, 9600)] == [27, 326, 326]


def test_divisor_checks():
    with pytest.raises(ValueError, match=r"Baud rate 115200 from a 1 MHz clock is off by"):
        divisor_for(1_000_000, 115200)
    with pytest.raises(ValueError, match="Baud rate must be a positive integer, not 0"):
        ChannelConfig(ChannelKind.NMEA, 0)
    with pytest.raises(ValueError, match="The front end needs at least one channel"):
        FrontEnd([])


def test_counters_keep_up_at_the_fastest_divisor_with_the_bus_reading_every_other_cycle():
    """Divisor 1 and characters back to back, 2 % fast, where every character is an event
    (a `$` inside a frame drops it as a bad byte; damaged stop bits, UART errors), on all
    channels at once, while the bus reads a counter every other cycle (the most the bank
    allows): the counters still count every event."""
    data = [b"$" * 30] * 3
    traces = [encode(d, bit_cycles=16, baud_error=-0.02,
                     framing_errors=[5, 6, 7] if k == 2 else []) for k, d in enumerate(data)]
    dut = FrontEnd()
    done = [False]
    reads = [0]

    def line(k):
        async def drive(ctx):
            ctx.set(dut.divisor[k], 1)
            await drive_line(ctx, dut.uart_rx[k], traces[k].segments)
        return drive

    async def reader(ctx):
        rng = random.Random(2)
        while not done[0]:
            k, name = rng.randrange(3), rng.choice(COUNTER_NAMES)
            ctx.set(dut.counters.addr, register_address(k, name))
            ctx.set(dut.counters.r_stb, 1)
            await ctx.tick()
            ctx.set(dut.counters.r_stb, 0)
            await ctx.tick().repeat(1 + (rng.random() < 0.3))   # mostly every other cycle
            reads[0] += 1

    async def main(ctx):
        cycles = max(t.levels().size for t in traces) + 2000
        await ctx.tick().repeat(cycles)
        done[0] = True
        await ctx.tick().repeat(4)
        counts = [{n: await read_counter(ctx, dut, register_address(k, n)) for n in COUNTER_NAMES}
                  for k in range(3)]
        for k, (config, trace) in enumerate(zip(DEFAULT_CHANNELS, traces)):
            ref = reference_filter(Kind(config.kind.value), trace.expected)
            assert counts[k] == ref.counters, k
        assert counts[0]["bad_byte"] == counts[1]["bad_byte"] == 29
        assert counts[2]["uart_error"] == 1 and counts[2]["bad_byte"] > 20

    async def drain(ctx):
        ctx.set(dut.o.ready, 1)

    run_simulation(dut, [main], background=[line(k) for k in range(3)] + [reader, drain],
                   name="frontend_fastest_counters")
    assert reads[0] > 1500


def test_registers_answer_on_the_csr_bus_with_its_timing():
    """FrontEndRegisters with a front end, as the top wires them: the memory map names every
    register at its word address (8 per channel); divisors write and read back; counter
    reads come from the bank; read data is there the cycle after ``r_stb`` and zero
    otherwise."""
    class Registered(wiring.Component):
        def __init__(self):
            self.fe = FrontEnd()
            self.regs = FrontEndRegisters(3)
            super().__init__({"bus": In(csr.Signature(addr_width=5, data_width=32))})

        def elaborate(self, platform):
            m = Module()
            m.submodules.fe, m.submodules.regs = self.fe, self.regs
            wiring.connect(m, wiring.flipped(self.bus), self.regs.bus)
            wiring.connect(m, self.regs.counters, self.fe.counters)
            for k in range(3):
                m.d.comb += self.fe.divisor[k].eq(self.regs.divisor[k])
            return m

    dut = Registered()
    names = [("_".join(map(str, name)), start, end)
             for _, name, (start, end) in dut.regs.bus.memory_map.resources()]
    expected = [(f"ch{k}_{n}", 8 * k + i) for k in range(3)
                for i, n in enumerate(("divisor",) + COUNTER_NAMES)]
    assert names == [(name, address, address + 1) for name, address in expected]
    assert [register_address(k, n) for k in range(3) for n in ("divisor",) + COUNTER_NAMES] == \
        [address for _, address in expected]
    bus = dut.bus
    trace = encode(b"$" * 6, bit_cycles=16)

    async def read(ctx, address):
        ctx.set(bus.addr, address)
        ctx.set(bus.r_stb, 1)
        await ctx.tick()
        ctx.set(bus.r_stb, 0)
        value = ctx.get(bus.r_data)
        await ctx.tick()
        assert ctx.get(bus.r_data) == 0
        return value

    async def main(ctx):
        for k, value in ((0, 1), (1, 0x1234), (2, 0)):
            ctx.set(bus.addr, register_address(k, "divisor"))
            ctx.set(bus.w_data, 0xABCD0000 | value)
            ctx.set(bus.w_stb, 1)
            await ctx.tick()
            ctx.set(bus.w_stb, 0)
        assert [ctx.get(dut.fe.divisor[k]) for k in range(3)] == [1, 0x1234, 0]
        assert ctx.get(bus.r_data) == 0
        assert [await read(ctx, register_address(k, "divisor")) for k in range(3)] == [1, 0x1234, 0]
        await drive_line(ctx, dut.fe.uart_rx[0], trace.segments)
        await ctx.tick().repeat(200)
        counts = {n: await read(ctx, register_address(0, n)) for n in COUNTER_NAMES}
        assert counts == dict.fromkeys(COUNTER_NAMES, 0) | {"bad_byte": 5}
        for _ in range(64):                    # no strobe, no data (the bank is scanning)
            assert ctx.get(bus.r_data) == 0
            await ctx.tick()
        assert [await read(ctx, register_address(1, n)) for n in COUNTER_NAMES] == [0] * 7
        assert await read(ctx, 31) == 0                       # beyond the registers

    run_simulation(dut, [main], name="frontend_registers")


def test_the_counter_bank_limits_the_channel_count():
    """Eight channels sweep 64 words, in 129 cycles at most: inside the 144 between two
    characters at divisor 1. Nine would need 128 words and could miss events."""
    assert FrontEnd([ChannelConfig(ChannelKind.PMAG, 115200)] * 8).counter_bank.depth == 64
    with pytest.raises(ValueError, match="could miss events of characters 144 cycles apart"):
        FrontEnd([ChannelConfig(ChannelKind.PMAG, 115200)] * 9)
