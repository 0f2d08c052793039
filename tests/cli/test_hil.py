"""``maglog replay`` and ``maglog record`` (cli/hil.py) over real pseudo-terminal pairs and
pyserial's ``loop://``: bytes and pacing of a replayed scenario, the log and counters of a
recording against the reference filter, and a recorded calibration flight calibrated."""

import fcntl
import os
import threading
import time

import pytest
import serial

from maglog.cli.hil import expected_counters, record, replay
from maglog.cli.main import main
from maglog.cli.run import load
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.sentences import nmea_sentence
from maglog.sim.stimulus.scenario import make_flight

SPEED = 20.0


class Pty:
    """A pseudo-terminal pair: ``port`` a pyserial port on the slave, ``master`` the fd the
    test reads and writes; ``chunks`` what a reader thread got, with its arrival times."""

    def __init__(self, baud=9600):
        self.master, slave = os.openpty()
        self.path = os.ttyname(slave)
        self.port = serial.Serial(self.path, baud, timeout=0)
        os.close(slave)
        self.chunks = []

    def start_reading(self):
        def read():
            while True:
                try:
                    data = os.read(self.master, 65536)
                except OSError:
                    return
                if not data:
                    return
                self.chunks.append((time.monotonic(), data))
        thread = threading.Thread(target=read, daemon=True)
        thread.start()
        return thread

    def received(self):
        return b"".join(data for _, data in self.chunks)

    def close(self):
        for close in (self.port.close, lambda: os.close(self.master)):
            try:
                close()
            except OSError:
                pass


@pytest.fixture(scope="module")
def short():
    return load("short").system


@pytest.fixture(scope="module")
def replayed(short):
    """The short scenario replayed at SPEED into mag and cesium only (gps left unmapped)."""
    ptys = {k: Pty(short.channels[k].baud) for k in range(3)}
    for pty in ptys.values():
        pty.start_reading()
    result = replay(short, {0: ptys[0].port, 2: ptys[2].port}, speed=SPEED)
    time.sleep(0.1)
    yield result, ptys
    for pty in ptys.values():
        pty.close()


def test_replay_sends_each_channels_bytes(short, replayed):
    result, ptys = replayed
    assert ptys[0].received() == short.channel_bytes(0)
    assert ptys[2].received() == short.channel_bytes(2)
    assert ptys[1].received() == b""          # unmapped: nothing sent
    assert set(result.channels) == {0, 2}
    assert result.channels[0].bytes == len(short.channel_bytes(0))
    assert not result.interrupted


def test_replay_is_paced(short, replayed):
    """Every byte arrives after its burst's scheduled instant and within 50 ms of it; the
    whole replay takes the scenario's time divided by the speed."""
    result, ptys = replayed
    assert result.wall_s == pytest.approx(short.until / SPEED, abs=0.15)
    for k in (0, 2):
        bursts = short.channel_bursts(k)
        due = [result.started + b.start / SPEED for b in bursts]
        ends, total = [], 0
        for burst in bursts:
            total += len(burst.data)
            ends.append(total)
        arrived, count = [], 0
        for at, data in ptys[k].chunks:
            count += len(data)
            arrived.append((at, count))
        times = [at for at, _ in arrived]
        assert times == sorted(times)
        # Never ahead of the schedule: by each arrival, no byte of a later burst.
        for at, count in arrived:
            scheduled = sum(len(b.data) for b, d in zip(bursts, due) if d <= at)
            assert count <= scheduled
        # Never far behind: each burst's last byte within 50 ms of its instant.
        for end, d in zip(ends, due):
            first = next(at for at, count in arrived if count >= end)
            assert first - d < 0.05
        assert result.channels[k].max_late_s < 0.05


def test_replay_over_loop_url(short):
    port = serial.serial_for_url("loop://", timeout=0)
    result = replay(short, {2: port}, speed=200.0, until=5.0)
    sent = b"".join(b.data for b in short.channel_bursts(2) if b.start < 5.0)
    assert port.read(len(sent) + 100) == sent
    assert result.channels[2].bursts == sum(1 for b in short.channel_bursts(2) if b.start < 5)


def _pmag(n, checksum=None):
    return nmea_sentence(f"PMAG1,{n:05d},+42669.2,-10749.8,+24327.0", checksum=checksum)


GGA = nmea_sentence("GPGGA,100000.00,4730.00000,N,00830.00000,E,1,08,0.9,500.0,M,45.0,M,,")
MAG_STREAM = (_pmag(1) + _pmag(2, checksum=0) + b"noise$PM\x00\xff" + _pmag(3)
              + b"$PMAG1,00004,+1" + b"\r\n" + _pmag(5))
GPS_STREAM = (GGA + nmea_sentence("GPRMC,100000.00,A,4730.0,N,00830.0,E,0.0,0.0,010626,,")
              + GGA[:-5] + b"00\r\n")
CESIUM_STREAM = b"$ 48395.039,1500\r\n$ 4839\r\n$149895.131,0001\r\n"


def _feed(ptys, pieces):
    for name, data in pieces:
        os.write(ptys[name].master, data)
        time.sleep(0.05)


def test_record_keeps_exactly_the_reference_filters_frames(tmp_path):
    """Known frames (valid, bad checksum, noise, cut short, not whitelisted) on three ptys:
    the log is the reference filter's kept frames in arrival order, and the counters are
    its counters."""
    kinds = {"mag": Kind.PMAG, "gps": Kind.NMEA, "cesium": Kind.CESIUM}
    streams = {"mag": MAG_STREAM, "gps": GPS_STREAM, "cesium": CESIUM_STREAM}
    ptys = {name: Pty() for name in kinds}
    # Arrival order: each piece is one complete frame's worth (or junk) fed in turn.
    half = len(MAG_STREAM) // 2
    pieces = [("mag", MAG_STREAM[:half]), ("gps", GPS_STREAM), ("mag", MAG_STREAM[half:]),
              ("cesium", CESIUM_STREAM)]
    feeder = threading.Thread(target=_feed, args=(ptys, pieces))
    out = open(tmp_path / "LOG00001.TXT", "wb")
    feeder.start()
    result = record({n: p.port for n, p in ptys.items()}, out, seconds=0.6)
    feeder.join()
    out.close()
    for pty in ptys.values():
        pty.close()
    refs = {n: reference_filter(kinds[n], streams[n]) for n in kinds}
    expected = []
    for name, data in pieces:
        got = reference_filter(kinds[name], b"".join(d for n, d in pieces[:pieces.index(
            (name, data)) + 1] if n == name)).frames
        before = reference_filter(kinds[name], b"".join(d for n, d in pieces[:pieces.index(
            (name, data))] if n == name)).frames
        expected += got[len(before):]
    assert (tmp_path / "LOG00001.TXT").read_bytes() == b"".join(expected)
    assert result.frames == len(expected) == sum(len(r.frames) for r in refs.values())
    for name in kinds:
        assert result.channels[name].counters == refs[name].counters
        assert result.channels[name].bytes == len(streams[name])
    # The streams exercise several verdicts (a test of the test).
    assert [refs["mag"].counters[c] for c in ("kept", "checksum", "bad_byte")] == [3, 2, 1]
    assert refs["gps"].counters["not_whitelisted"] == refs["cesium"].counters[
        "not_whitelisted"] == 1
    assert result.reason == "seconds"


def test_record_stops_when_the_ports_close_and_keeps_what_it_wrote(tmp_path):
    pty = Pty(115200)
    path = tmp_path / "LOG.TXT"
    out = open(path, "wb")
    box = {}
    thread = threading.Thread(target=lambda: box.update(
        result=record({"mag": pty.port}, out, seconds=10)))
    thread.start()
    os.write(pty.master, _pmag(1) + _pmag(2) + b"$PMAG1,0000")     # the last one left open
    time.sleep(0.2)
    assert path.read_bytes() == _pmag(1) + _pmag(2)     # written (flushed) as it went
    os.close(pty.master)
    thread.join(5)
    out.close()
    assert not thread.is_alive()
    result = box["result"]
    assert result.reason == "closed" and result.channels["mag"].closed
    assert result.channels["mag"].counters["kept"] == 2
    assert path.read_bytes() == _pmag(1) + _pmag(2)


def test_record_over_loop_url(tmp_path):
    port = serial.serial_for_url("loop://", timeout=0)
    port.write(CESIUM_STREAM)
    with open(tmp_path / "LOG.TXT", "wb") as out:
        result = record({"cesium": port}, out, seconds=0.2)
    ref = reference_filter(Kind.CESIUM, CESIUM_STREAM)
    assert (tmp_path / "LOG.TXT").read_bytes() == b"".join(ref.frames)
    assert result.channels["cesium"].counters == ref.counters


def test_replay_into_record_counts_what_the_reference_filter_expects(short, tmp_path):
    """The short scenario's first 6 s replayed into ptys whose other ends feed a recording
    (a loopback cable in software): the counters are the reference filter's over the bytes
    sent."""
    until = 6.0
    a = {k: Pty() for k in range(3)}
    b = {k: Pty() for k in range(3)}

    def bridge(k):
        while True:
            try:
                data = os.read(a[k].master, 65536)
            except OSError:
                return
            os.write(b[k].master, data)
    for k in range(3):
        threading.Thread(target=bridge, args=(k,), daemon=True).start()
    out = open(tmp_path / "LOG.TXT", "wb")
    box = {}
    recorder = threading.Thread(target=lambda: box.update(result=record(
        {name: b[k].port for k, name in enumerate(("mag", "gps", "cesium"))}, out,
        seconds=until / SPEED + 0.6)))
    recorder.start()
    replay(short, {k: a[k].port for k in range(3)}, speed=SPEED, until=until)
    recorder.join()
    out.close()
    for pty in list(a.values()) + list(b.values()):
        pty.close()
    result = box["result"]
    log = (tmp_path / "LOG.TXT").read_bytes()
    kept = 0
    for k, name in enumerate(("mag", "gps", "cesium")):
        sent = b"".join(x.data for x in short.channel_bursts(k) if x.start < until)
        ref = reference_filter(Kind(short.channels[k].kind.value), sent)
        assert result.channels[name].counters == ref.counters, name
        kept += len(ref.frames)
        assert result.channels[name].counters["kept"] > 0
    assert result.frames == kept == log.count(b"\n")
    assert expected_counters(short, 2)["kept"] >= result.channels["cesium"].counters["kept"]


def _wait_locked(path, timeout=10.0):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return
            fcntl.flock(fd, fcntl.LOCK_UN)
            time.sleep(0.01)
        raise TimeoutError(f"{path} was not opened")
    finally:
        os.close(fd)


def _split_by_channel(log):
    lines = log.splitlines(keepends=True)
    return [("mag" if line.startswith(b"$PMAG") else "cesium" if line[1:2] in b" 1"
             else "gps", line) for line in lines]


def test_record_of_a_calibration_flight_calibrates(tmp_path, capsys):
    """A one-minute synthetic calibration flight's frames sent on three ptys, recorded by
    ``maglog record``, then ``maglog calibrate LOG.TXT`` on the result."""
    data = make_flight(coverage="uav", seconds=60, seed=5).log()
    pieces = _split_by_channel(data)
    ptys = {name: Pty() for name in ("mag", "gps", "cesium")}

    def feed():
        # pyserial empties a port's input when it opens it: feed once the CLI holds all
        # three (it locks them).
        for pty in ptys.values():
            _wait_locked(pty.path)
        time.sleep(0.1)
        for name, line in pieces:
            os.write(ptys[name].master, line)
            time.sleep(0.0002)
        time.sleep(0.3)
        for pty in ptys.values():
            os.close(pty.master)      # the sensors go away: the recording ends
    feeder = threading.Thread(target=feed)
    feeder.start()
    # The CLI opens the ports itself: give it the slaves' paths, free them here first.
    for pty in ptys.values():
        pty.port.close()
    log = tmp_path / "LOG00001.TXT"
    status = main(["record", "--port", f"mag={ptys['mag'].path}", "--port",
                   f"gps={ptys['gps'].path}", "--port", f"cesium={ptys['cesium'].path}",
                   "-o", str(log), "--seconds", "20"])
    feeder.join()
    out = capsys.readouterr().out
    assert status == 0, out
    assert "every port closed" in out
    recorded = log.read_bytes()
    assert sorted(recorded.splitlines()) == sorted(data.splitlines())
    for name in ("mag", "gps", "cesium"):
        sent = b"".join(line for n, line in pieces if n == name)
        assert b"".join(line for line in recorded.splitlines(keepends=True)
                        if _split_by_channel(line)[0][0] == name) == sent
    status = main(["calibrate", str(log), "--method", "lm", "--out", str(tmp_path / "rep")])
    out = capsys.readouterr().out
    assert status == 0
    assert "total-field RMS" in out


@pytest.mark.parametrize("argv, status, message", [
    (["record", "--port", "nowhere=/dev/null", "-o", "x"], 2, "channel must be one of"),
    (["record", "--port", "/dev/no-such-tty", "-o", "{tmp}/L.TXT"], 1, "no such port"),
    (["record", "--port", "/dev/null", "-o", "{tmp}/L.TXT"], 1, "not a serial port"),
    (["record", "--port", "mag=loop://", "--baud", "mag=7", "-o", "x"], 2, "baud rate"),
    # A missing folder is made (as every -o); a file where a folder must be is not.
    (["record", "--port", "loop://", "-o", "{tmp}/a-file/L.TXT"], 1, "cannot write"),
    (["record", "--port", "loop://", "--baud", "gps=9600", "-o", "{tmp}/L.TXT"], 1,
     "has no --port"),
    (["replay", "short", "--port", "a", "--port", "b", "--port", "c", "--port", "d"], 1,
     "4 ports for 3 channels"),
    (["replay", "short", "--port", "mag=foo://x"], 1, "foo://x"),
    (["replay", "short", "--port", "mag=loop://", "--speed", "0"], 2, "--speed"),
    (["replay", "no-such.toml", "--port", "loop://"], 1, "no-such.toml"),
])
def test_bad_input_is_one_line(tmp_path, capsys, argv, status, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    (tmp_path / "a-file").write_text("not a folder\n")
    code = _run(argv)
    err = capsys.readouterr().err
    assert code == status
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "L.TXT").exists()


def test_a_busy_port_is_refused(tmp_path, capsys):
    pty = Pty()
    pty.port.close()
    holder = serial.Serial(pty.path, 9600, exclusive=True)
    try:
        code = main(["record", "--port", pty.path, "-o", str(tmp_path / "L.TXT")])
    finally:
        holder.close()
        pty.close()
    assert code == 1
    assert "busy" in capsys.readouterr().err


def _run(argv):
    try:
        return main(argv)
    except SystemExit as exit:
        return exit.code


def test_replay_command_maps_channels_and_says_what_is_left_out(short, capsys):
    pty = Pty()
    pty.port.close()            # the command opens it; a plain fd keeps the pair up
    keep = os.open(pty.path, os.O_RDWR | os.O_NOCTTY)
    pty.start_reading()
    try:
        code = main(["replay", "short", "--port", f"cesium={pty.path}", "--speed", "500"])
        time.sleep(0.1)
    finally:
        os.close(keep)
        pty.close()
    captured = capsys.readouterr()
    assert pty.received() == short.channel_bytes(2)
    assert code == 0, captured.err
    assert "mag: no port given" in captured.err and "gps: no port given" in captured.err
    assert captured.err.count("button press") == len(short.presses)
    row = next(line for line in captured.out.splitlines() if line.startswith("cesium"))
    kept = expected_counters(short, 2)["kept"]
    assert f"{len(short.channel_bytes(2))}" in row.split() and f"{kept}" in row.split()
    assert not any(line.startswith(("mag", "gps")) for line in captured.out.splitlines())


def test_replay_with_baud_faults_switches_the_port_for_them(short):
    """The scenario's gps line runs 1.5 % fast: with baud_faults every gps burst goes out at
    its own rate, the port back at 9600 afterwards; the bytes are the same."""
    from serial.urlhandler.protocol_loop import Serial as Loop

    class WatchedLoop(Loop):
        """``loop://`` that notes the rate each write goes out at."""
        writes = []

        def write(self, data):
            self.writes.append((self.baudrate, bytes(data)))
            return super().write(data)
    port = WatchedLoop("loop://", timeout=0, baudrate=9600)
    bursts = [b for b in short.channel_bursts(1) if b.start < 3.0]
    assert bursts and all(b.baud is not None and b.baud != 9600 for b in bursts)
    result = replay(short, {1: port}, speed=100.0, until=3.0, baud_faults=True)
    assert port.read(10000) == b"".join(b.data for b in bursts)
    assert port.writes == [(round(b.baud), b.data) for b in bursts]
    assert result.channels[1].off_nominal == len(bursts)
    assert port.baudrate == 9600


def test_record_command_stops_on_ctrl_c_and_keeps_its_frames(tmp_path):
    """``maglog record`` in its own process, interrupted by SIGINT: status 0, the frames so
    far in the log, the counters printed."""
    import signal
    import subprocess
    import sys
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    log = tmp_path / "LOG.TXT"
    process = subprocess.Popen([sys.executable, "-m", "maglog.cli", "record", "--port",
                                f"mag={path}", "-o", str(log)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_locked(path)
        time.sleep(0.2)
        os.write(master, _pmag(1) + _pmag(2, checksum=0) + _pmag(3))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and log.read_bytes().count(b"\n") < 2:
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
        os.close(master)
    assert process.returncode == 0, err
    assert log.read_bytes() == _pmag(1) + _pmag(3)
    assert "ended on Ctrl-C" in out
    row = next(line for line in out.splitlines() if line.startswith("mag")).split()
    assert row[3:5] == ["2", "1"]           # kept, checksum


def test_a_replay_into_a_port_nobody_reads_ends_with_a_write_timeout(capsys, monkeypatch):
    # loop:// holds 4 KiB; with nothing reading it the writes would wait for ever.
    from maglog.cli import hil
    monkeypatch.setattr(hil, "WRITE_SLACK_S", 0.3)
    start = time.monotonic()
    code = main(["replay", "short", "--port", "mag=loop://", "--speed", "1e4"])
    captured = capsys.readouterr()
    assert time.monotonic() - start < 30
    err = captured.err.strip().splitlines()
    assert code == 1 and err[-1].startswith("maglog: error: the replay stopped: mag: "), err
    assert "write timeout" in err[-1] and "nothing reads its other end" in err[-1]
    # The speed beyond what the line carries is said before the replay starts.
    assert any(line.startswith("note: mag's bytes need") for line in err)


def test_write_timeout_covers_the_buffer_draining_onto_the_line():
    from maglog.cli.hil import OS_BUFFER_BYTES, write_timeout
    assert write_timeout(100, 50) > (100 + OS_BUFFER_BYTES) * 10 / 50
    assert write_timeout(100, 115200) < 3.0


@pytest.mark.parametrize("speed", ["1e6", "1e5", "0", "-1", "nan", "inf"])
def test_replay_speed_range(capsys, speed):
    with pytest.raises(SystemExit) as exit_:
        main(["replay", "short", "--port", "mag=loop://", f"--speed={speed}"])
    code = exit_.value.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--speed" in err[0]


@pytest.mark.parametrize("device", ["p" * 5000, "/tmp/" + "p" * 300, "foo://" + "x" * 5000])
def test_a_long_device_name_is_echoed_cut_short(capsys, tmp_path, device):
    for argv in (["replay", "short", "--port", f"mag={device}"],
                 ["record", "-o", str(tmp_path / "LOG.TXT"), "--port", f"mag={device}",
                  "--seconds", "1"]):
        code = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and err[-1].startswith("maglog: error: ") and len(err[-1]) < 250, err


def test_a_port_that_cannot_be_opened_leaves_the_output_as_it_was(capsys, tmp_path):
    # With --force the log is replaced only once the ports are open: an earlier recording
    # stays whole, and what -o names is never removed.
    log = tmp_path / "LOG.TXT"
    log.write_bytes(b"an earlier recording")
    code = main(["record", "-o", str(log), "--port", "mag=/nonexistent/tty", "--seconds",
                 "1", "--force"])
    assert code == 1 and "no such port" in capsys.readouterr().err
    assert log.read_bytes() == b"an earlier recording"
    code = main(["record", "-o", str(tmp_path / "new.txt"), "--port", "mag=foo://x",
                 "--seconds", "1"])
    assert code == 1 and not (tmp_path / "new.txt").exists()
