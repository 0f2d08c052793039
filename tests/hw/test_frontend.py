"""The whole front end (UART, filter, arbiter) on the Amaranth simulator."""

import random

import numpy as np
import pytest

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig, DEFAULT_CHANNELS, FrontEnd, divisor_for
from maglog.sim.stimulus import sentences
from maglog.sim.runners.frontend import FrontEndBench
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
    with pytest.raises(ValueError, match=r"Baud rate 115200 from a 1000000 Hz clock is off by"):
        divisor_for(1_000_000, 115200)
    with pytest.raises(ValueError, match="Baud rate must be a positive integer, not 0"):
        ChannelConfig(ChannelKind.NMEA, 0)
    with pytest.raises(ValueError, match="The front end needs at least one channel"):
        FrontEnd([])
