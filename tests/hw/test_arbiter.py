"""FrameArbiter: frames never interleave, none is lost, and no channel starves."""

import random

import pytest

from maglog.hw.arbiter import FrameArbiter
from maglog.sim.backends.amaranth import collect_frames, run_simulation


def make_frames(rng, channel, count):
    return [bytes([0x24, channel]) + bytes(rng.randrange(256) for _ in range(rng.randrange(0, 30)))
            for _ in range(count)]


def run_arbiter(inputs, *, gaps=None, ready=None, tail=400, timing=None):
    """The arbiter's output frames as (bytes, {"channel": k}); ``timing`` (a dict), when
    given, gets "offered": per channel, the cycle each frame was first offered, and "ended":
    per output frame, the cycle its last byte left."""
    n = len(inputs)
    dut = FrameArbiter(n)
    out = []
    now = [0]                               # cycles since the start, counted by the sink
    if timing is not None:
        timing.update(offered=[[] for _ in range(n)], ended=[])

    def source(k):
        async def feed(ctx):
            stream = dut.i[k]
            for frame in inputs[k]:
                # A FrameFifo shows a frame only when it is whole: gaps fall between frames.
                if gaps is not None:
                    for _ in range(gaps(k)):
                        ctx.set(stream.valid, 0)
                        await ctx.tick()
                if timing is not None:
                    timing["offered"][k].append(now[0])
                for index, byte in enumerate(frame):
                    ctx.set(stream.payload, {"data": byte, "last": index == len(frame) - 1})
                    ctx.set(stream.valid, 1)
                    await ctx.tick().until(stream.ready)
            ctx.set(stream.valid, 0)
            await ctx.tick().repeat(tail)
        return feed

    class Timed(list):
        def append(self, frame):
            super().append(frame)
            if timing is not None:
                timing["ended"].append(now[0])

    def clocked_ready(cycle):
        now[0] = cycle
        return True if ready is None else ready(cycle)

    async def sink(ctx):
        await collect_frames(ctx, dut.o, frames, fields=("data", "channel"),
                             ready=clocked_ready)

    frames = Timed()

    run_simulation(dut, [source(k) for k in range(n)], background=[sink], name="arbiter",
                   deadline=1.0)
    out.extend(frames)
    return out


@pytest.mark.parametrize("channels", [1, 2, 3, 5])
def test_frames_whole_and_in_order_per_channel(channels):
    rng = random.Random(channels)
    inputs = [make_frames(rng, k, 40) for k in range(channels)]
    pattern = [rng.random() < 0.7 for _ in range(512)]
    out = run_arbiter(inputs, gaps=lambda k: rng.randrange(0, 8),
                      ready=lambda cycle: pattern[cycle % 512], tail=2000)
    for k in range(channels):
        # Every frame's bytes arrived together, tagged with its channel, in order.
        assert [frame for frame, tags in out if tags["channel"] == k] == inputs[k]
    # Frames do not interleave: each output frame carries its own channel byte.
    assert all(frame[1] == tags["channel"] for frame, tags in out)


def test_round_robin_when_every_channel_is_busy():
    rng = random.Random(5)
    inputs = [make_frames(rng, k, 12) for k in range(4)]
    out = run_arbiter(inputs)
    order = [tags["channel"] for _, tags in out]
    # With every channel always ready, service rotates 0, 1, 2, 3, 0, ...
    assert order == [k % 4 for k in range(48)]


def test_busy_channel_cannot_starve_a_quiet_one():
    rng = random.Random(9)
    busy = make_frames(rng, 0, 60)
    quiet = make_frames(rng, 1, 3)
    timing = {}
    out = run_arbiter([busy, quiet], gaps=lambda k: 0 if k == 0 else 50, timing=timing)
    order = [tags["channel"] for _, tags in out]
    assert order.count(1) == 3
    positions = [i for i, c in enumerate(order) if c == 1]
    for offered, position in zip(timing["offered"][1], positions):
        # A quiet channel's frame waits for at most the one frame in flight when it came:
        # of the frames before it, at most one ended after it was offered.
        waited_for = [i for i in range(position) if timing["ended"][i] > offered]
        assert len(waited_for) <= 1, (offered, position, waited_for)
    # After the quiet channel's frame became ready it was served next, not after all 60.
    assert order.index(1) < 10


def test_channel_count_is_checked():
    with pytest.raises(ValueError, match="Channel count must be a positive integer, not 0"):
        FrameArbiter(0)
