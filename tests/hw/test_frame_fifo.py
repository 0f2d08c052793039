"""FrameFifo: commit and discard, with and without backpressure.

The writer behaves like the frame filter: it writes a frame byte by byte, commits or
discards it, sometimes discards and starts the next frame in the same cycle, and gives up a
frame when the FIFO says it is full. Every committed frame must come out whole and in order,
and no byte of a discarded frame may come out.
"""

import random

import pytest

from maglog.hw.frame_fifo import FrameFifo
from maglog.sim.backends.amaranth import collect_frames, run_simulation


def run_random(seed, *, depth, frames, ready=None):
    rng = random.Random(seed)
    dut = FrameFifo(depth=depth)
    committed, out, levels = [], [], []

    async def writer(ctx):
        restart = False          # this frame's `$` was written with the previous discard
        for index in range(frames):
            length = rng.randrange(2 if restart else 1, depth + 3)
            keep = rng.random() < 0.6
            frame = bytes((index * 31 + k) & 0xFF for k in range(length))
            written = 0
            gave_up = False
            for k, byte in enumerate(frame):
                if restart and k == 0:
                    written = 1
                    continue
                full = ctx.get(dut.full)
                if full:
                    gave_up = True
                    break
                last = k == length - 1
                ctx.set(dut.w_en, 1)
                ctx.set(dut.w_data, byte)
                ctx.set(dut.w_last, last and keep)
                ctx.set(dut.commit, last and keep)
                await ctx.tick()
                ctx.set(dut.w_en, 0)
                ctx.set(dut.commit, 0)
                written += 1
                levels.append(ctx.get(dut.level))
                while rng.random() < 0.15:
                    await ctx.tick()
            restart = False
            if keep and not gave_up:
                committed.append(frame)
                continue
            # Dropped: discard, sometimes starting the next frame in the same cycle.
            ctx.set(dut.discard, 1)
            if rng.random() < 0.5 and not ctx.get(dut.full_committed):
                ctx.set(dut.w_en, 1)
                ctx.set(dut.w_data, ((index + 1) * 31) & 0xFF)
                ctx.set(dut.w_last, 0)
                restart = True
            await ctx.tick()
            ctx.set(dut.discard, 0)
            ctx.set(dut.w_en, 0)
        if restart:
            ctx.set(dut.discard, 1)
            await ctx.tick()
            ctx.set(dut.discard, 0)
        await ctx.tick().repeat(8 * depth + 64)

    async def reader(ctx):
        await collect_frames(ctx, dut.o, out, ready=ready)

    run_simulation(dut, [writer], background=[reader], name="frame_fifo", deadline=1.0)
    return committed, out, levels


@pytest.mark.parametrize("seed", range(3))
def test_commit_discard_reader_always_ready(seed):
    committed, out, levels = run_random(seed, depth=32, frames=400)
    assert out == committed
    assert len(committed) > 100
    assert max(levels) <= 32


@pytest.mark.parametrize("seed", range(3))
def test_commit_discard_under_backpressure(seed):
    rng = random.Random(1000 + seed)
    pattern = [rng.random() < 0.3 for _ in range(997)]
    committed, out, levels = run_random(seed, depth=16, frames=400,
                                        ready=lambda cycle: pattern[cycle % 997])
    assert out == committed
    # The FIFO did fill (frames were given up) and still kept its promises.
    assert max(levels) == 16
    assert len(committed) > 50


def test_depth_is_checked():
    with pytest.raises(ValueError, match="Depth must be a power of two, at least 2, not 12"):
        FrameFifo(depth=12)
