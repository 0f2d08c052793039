"""Every real GPS capture in ../shared/data/nmea through the gateware, against the reference.

Two paths: the frame filter alone on the Amaranth simulator (one byte a cycle, every file),
and the whole front end (UART receivers included) on Verilator under cocotb, with the files
spread over four NMEA channels and a break between files on a line.
"""

import pytest

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.sim.stimulus.captures import capture_files, load_capture
from maglog.sim.runners.frontend import FrontEndBench
from maglog.sim.stimulus.uart_line import ChannelStimulus, Segments
from maglog.sim.runners.frontend import run_frame_filter as run_filter
from maglog.sim.reference import reference_filter

#: One test per capture; without any, one test that ends through ``external.captures()``
#: (a skip that says why, a failure under CI=true).
FILES = [pytest.param(path, id=path.name) for path in capture_files()] or [
    pytest.param(None, id="no-data")]


@pytest.mark.parametrize("path", FILES)
def test_capture_through_frame_filter(path, external):
    if path is None:
        external.captures()
        pytest.fail("capture_files() found no captures, external.captures() found some")
    stream = load_capture(path)
    frames, counters, flushes = run_filter(ChannelKind.NMEA, list(stream))
    ref = reference_filter("nmea", stream)
    assert frames == ref.frames
    # A frame still open at the end of the file is judged by neither.
    assert counters == ref.counters
    assert flushes == len(ref.flushes)


LINES = 4
#: A break between two files on one line: the first file's unfinished frame is dropped
#: (uart_error) instead of running on into the next file.
BREAK = Segments([(0, 16 * 12), (1, 16 * 2)])


@pytest.mark.cocotb
def test_all_captures_through_the_front_end_on_verilator(external, tmp_path):
    captures = external.captures()
    external.simulator("verilator")
    streams = {path.name: load_capture(path) for path in captures}
    # Spread the files over the lines, biggest first, onto the least loaded line.
    lines = [[] for _ in range(LINES)]
    for name in sorted(streams, key=lambda n: -len(streams[n])):
        min(lines, key=lambda line: sum(len(streams[n]) for n in line)).append(name)
    bench = FrontEndBench([ChannelConfig(ChannelKind.NMEA, 9600)] * LINES,
                          backend="verilator", build_dir=tmp_path)
    stimuli = []
    for names in lines:
        parts, expected = [], []
        for name in names:
            parts += [streams[name], BREAK]
            expected += reference_filter("nmea", streams[name]).frames
        stimuli.append(ChannelStimulus(divisor=1, parts=parts, expected=expected))
    result = bench.run(stimuli)
    assert result.mismatches == []
    for k, names in enumerate(lines):
        expected = [f for n in names for f in reference_filter("nmea", streams[n]).frames]
        assert result.frames_of(k) == expected
    assert sum(c["kept"] for c in result.counters) == sum(
        len(reference_filter("nmea", s).frames) for s in streams.values())
