"""The front end's generated Verilog under cocotb, on Icarus and on Verilator.

Lines are driven by cocotbext-uart's UartSource (plain streams) or segment by segment (baud
error and faults); the cocotb scoreboard checks each channel's frames in order against the
reference filter's, and the counters are compared here.
"""

import random

import pytest

from maglog.hw.frontend import DEFAULT_CHANNELS
from maglog.sim.stimulus import sentences
from maglog.sim.backends.cocotb import COCOTB_SIMULATORS
from maglog.sim.runners.frontend import FrontEndBench
from maglog.sim.stimulus.uart_line import ChannelStimulus, Segments, encode
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.streams import demo_streams

SIMULATORS = tuple(COCOTB_SIMULATORS)
NAMES = ("mag", "gps", "cesium")
KINDS = [Kind(c.kind.value) for c in DEFAULT_CHANNELS]

pytestmark = pytest.mark.cocotb


@pytest.fixture(scope="module", params=SIMULATORS)
def bench(request, external, tmp_path_factory):
    external.simulator(request.param)
    bench = FrontEndBench(DEFAULT_CHANNELS, backend=request.param,
                          build_dir=tmp_path_factory.mktemp(f"frontend_{request.param}"))
    bench.build()
    return bench


def check(result, events_per_channel):
    assert result.mismatches == []
    for k, events in enumerate(events_per_channel):
        ref = reference_filter(KINDS[k], events)
        assert result.frames_of(k) == ref.frames, f"channel {k}"
        assert result.counters[k] == ref.counters, f"channel {k}"
    return result


def test_demo_flight_scoreboard(bench):
    streams = demo_streams(seconds=2.0, seed=21)
    data = [streams[name] for name in NAMES]
    stimuli = [ChannelStimulus(divisor=1, data=d, expected=reference_filter(kind, d).frames)
               for d, kind in zip(data, KINDS)]
    result = check(bench.run(stimuli), data)
    assert result.flushes == len(reference_filter(Kind.NMEA, data[1]).flushes) > 0


@pytest.mark.parametrize("simulator", SIMULATORS)
def test_output_backpressure_keeps_frames_whole(simulator, external, tmp_path):
    external.simulator(simulator)
    streams = demo_streams(seconds=1.0, seed=4)
    data = [streams[name] for name in NAMES]
    bench = FrontEndBench(DEFAULT_CHANNELS, backend=simulator, build_dir=tmp_path,
                          backpressure=0.6, seed=3)
    stimuli = [ChannelStimulus(divisor=1, data=d, expected=reference_filter(kind, d).frames)
               for d, kind in zip(data, KINDS)]
    check(bench.run(stimuli), data)


def _mutated(rng, frames):
    """Frames with some damaged by a flipped, inserted or lost byte."""
    out = bytearray()
    for frame in frames:
        frame = bytearray(frame)
        roll = rng.random()
        if roll < 0.1:
            frame[rng.randrange(1, len(frame))] ^= 1 << rng.randrange(7)
        elif roll < 0.15:
            frame.insert(rng.randrange(1, len(frame)), rng.randrange(256))
        elif roll < 0.2:
            del frame[rng.randrange(len(frame))]
        out += frame
    return bytes(out)


def test_random_streams_scoreboard(bench):
    rng = random.Random(f"cocotb-{bench.backend}")
    mag = _mutated(rng, [sentences.pmag1(i, rng.uniform(-6e4, 6e4), rng.uniform(-6e4, 6e4),
                                         rng.uniform(-6e4, 6e4)) for i in range(150)])
    gps = _mutated(rng, [rng.choice([
        sentences.gga(i, rng.uniform(-80, 80), rng.uniform(-170, 170), quality=rng.randrange(3),
                      talker=rng.choice(["GP", "GN", "GL"])),
        sentences.vtg(rng.uniform(0, 359), rng.uniform(0, 30), talker="GN"),
        sentences.nmea_sentence("GPGSA,A,3,04,05,,09,12,,,24,,,,,2.5,1.3,2.1"),
    ]) for i in range(80)])
    cesium = _mutated(rng, [sentences.cesium(rng.uniform(2e4, 1.2e5), rng.randrange(10000))
                            for _ in range(300)])
    data = [mag, gps, cesium]
    stimuli = [ChannelStimulus(divisor=1, data=d, expected=reference_filter(kind, d).frames)
               for d, kind in zip(data, KINDS)]
    check(bench.run(stimuli), data)


BAUD_ERRORS = (-0.03, -0.02, -0.01, 0.0, 0.01, 0.02, 0.03)


def test_baud_error_sweep_loses_no_frame(bench):
    # Each channel runs through every baud error in turn, characters back to back.
    rng = random.Random(5)
    divisor = 2
    frames_of = [
        lambda i: sentences.pmag1(i, rng.uniform(-9e4, 9e4), 0.0, 4.5e4),
        lambda i: sentences.gga(i, 47.5, 8.5, quality=1, talker="GN"),
        lambda i: sentences.cesium(rng.uniform(4e4, 6e4), 1000 + i),
    ]
    stimuli, events = [], []
    for k in range(3):
        segments, expected = Segments(), []
        for error in BAUD_ERRORS:
            data = b"".join(frames_of[k](i) for i in range(8))
            trace = encode(data, bit_cycles=16 * divisor, baud_error=error)
            segments.extend(trace.segments)
            expected.extend(trace.expected)
        stimuli.append(ChannelStimulus(divisor=divisor, segments=segments))
        events.append(expected)
    result = check(bench.run(stimuli), events)
    assert [c["kept"] for c in result.counters] == [8 * len(BAUD_ERRORS)] * 3


def test_line_faults(bench):
    rng = random.Random(8)
    stimuli, events = [], []
    for k in range(3):
        frames = [sentences.pmag1(i, 1.0, 2.0, 3.0) if k == 0 else
                  sentences.gga(i, 1.0, 2.0) if k == 1 else sentences.cesium(5e4 + i, 7)
                  for i in range(12)]
        data = b"".join(frames)
        n = len(data)
        trace = encode(data, bit_cycles=16, gap_bits=0.5,
                       framing_errors=rng.sample(range(n), 3),
                       breaks=[(rng.randrange(n), 11 + rng.randrange(20)) for _ in range(2)],
                       glitches=[(rng.randrange(n), rng.randrange(1, 4)) for _ in range(6)])
        stimuli.append(ChannelStimulus(divisor=1, segments=trace.segments))
        events.append(trace.expected)
    result = check(bench.run(stimuli), events)
    assert all(c["uart_error"] >= 1 for c in result.counters)
