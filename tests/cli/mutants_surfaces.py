"""A seeded mutation run of the surfaces issue 23's fuzz reached first: scenario TOML files
(through ``maglog simulate --backend model`` with a small ``--max-seconds``; calibration
flights through ``maglog run --backend model``, their parameter verdict judged), ``card
format``, ``hdl`` (verilog, regmap, build, component), ``replay`` and ``record`` (pyserial
``loop://`` ports). Each input runs through ``maglog.cli.main.main`` in process, in worker
processes (one per core) with an alarm and an address-space limit per input, and is
classified as tests/calib/mutants.py does.

Outcomes (:data:`OUTCOMES`):

``ok``
    exit 0 and what the command writes is there and well formed (the card image, strict
    JSON truth and simulation record; the run's summary.json, no parameter passed that the
    flight does not determine; the Verilog's module; the project's build script; the log);
``error``
    exit 1 and a last line ``maglog: error: ...`` of at most :data:`LINE_MAX` characters;
``usage``
    the argument parser's exit 2 with its one-line message;
``traceback``
    an exception escaped ``main``;
``hang``
    no answer within the time limit;
``oom``
    out of memory (``MemoryError`` under the limit, or "out of memory" said);
``nonsense``
    exit 0 without its output, output that is not strict JSON, an error line over
    :data:`LINE_MAX` characters or over several lines, an exit status other than 0, 1, 2.

Used by ``tests/cli/test_surfaces_mutation.py`` (a short run by default, the long one under
``-m slow``) and ``bench/cli/surfaces_mutation.py`` (the long run, its counts as JSON).
"""

import contextlib
import io
import json
import multiprocessing
import os
import resource
import shutil
import signal
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Input classes, in the order a run cycles through them (scenario files weigh most).
CLASSES = ("scenario:value", "scenario:structure", "scenario:value", "scenario:sensor",
           "card:format", "hdl:verilog", "scenario:value", "hdl:regmap", "hdl:build",
           "hdl:component", "scenario:structure", "replay", "record", "scenario:sensor",
           "scenario:run")
OUTCOMES = ("ok", "error", "usage", "traceback", "hang", "oom", "nonsense")
#: The failures the run exists to find.
FAILURES = ("traceback", "hang", "oom", "nonsense")
#: Seconds an input may take (an elaboration and a short model flight take a few each on
#: a loaded machine).
TIME_LIMIT = 90
#: Address space a worker may take: beyond it an allocation fails (MemoryError) instead of
#: the machine's out-of-memory killer ending the worker.
MEMORY_LIMIT = 8 << 30
#: Longest error line a user should get.
LINE_MAX = 400
#: ``--max-seconds`` the scenario inputs run with: a longer flight is refused at once.
MAX_SECONDS = "40"

#: The base scenario: 20 s of flight (one calibration heading, no lines), one fault.
BASE = {
    "scenario": {"seed": 3},
    "flight": {"ground": {"seconds": 6.0}, "takeoff": {"seconds": 3.0, "height_m": 10.0},
               "calibration": {"headings_deg": [0.0], "seconds": 6.0, "turn_s": 1.0},
               "survey": {"legs": 0}, "landing": {"seconds": 3.0}},
    "faults": {"noise_burst": [{"channel": "mag", "start_s": 7.0, "end_s": 9.0}]},
}

#: TOML value texts a new user's files and editors produce.
WEIRD_VALUES = (
    "0", "-0", "-1", "1", "0.0", "-0.0", "1e-300", "-1e-300", "1e300", "-1e300", "nan", "inf",
    "-inf", "9223372036854775807", "-9223372036854775808", "9007199254740993", "2147483648",
    "4294967296", "65536", "9.2e18", "1e7", "1e9", "3600.0", "86400", "21600", "21601",
    "0.001", "1e-6", "9" * 5000, "1" + "0" * 400, "'abc'", "''", "'" + "x" * 10_000 + "'",
    "true", "false", "[]", "[1, 2, 3]", "[" + ", ".join(["1.5"] * 2000) + "]", "[[1], [2]]",
    "{a = 1}", "1979-05-27T07:32:00Z", "1979-05-27", "07:32:00", "'\u00c4\u00d6\u00dc'",
    "'\\u0000'", "0x7fffffff", "0o777", "0b1010", "1_000", "+5", "'GP'", "'gp'", "'mag'",
    "'cesium'", "'rate'", "'stream'", "'paper_a'", "'shared:missing.txt'", "'/dev/null'",
    "'/proc/self/mem'", "'.'", "12.5", "99.9", "100.0", "60.0", "0.25", "0.5", "1000.0",
    "10000.0", "1e5", "-90.0", "90.0", "180.0", "-360.0", "720.0")
#: Raw documents that are not the schema's shape.
STRUCTURES = (
    "", "\x00\x01\x02", "\xff\xfe not utf-8", "[scenario", "[scenario]\nseed = 1\nseed = 2\n",
    "a = 1\n", "[sitex]\na = 1\n", "[flight.hover]\nseconds = 3\n", "[flight]\nground = 3\n",
    "[faults]\nnoise_burst = 3\n", "[[faults.lightning]]\nstart_s = 1\n",
    "[anomaly]\ndipole = 3\n", "[[anomaly.rock]]\na = 1\n", "[channels]\nimu = {baud = 3}\n",
    "x = " + "[" * 5000 + "]" * 5000 + "\n", "[" + "t" * 10_000 + "]\n",
    "[site]\n" + "k" * 10_000 + " = 1\n", "[scenario]\nseed = " + "9" * 5000 + "\n",
    "[scenario]\nname = '''" + "n" * 100_000 + "'''\n",
    "\n".join(f"[[faults.gps_outage]]\nstart_s = {k}.0\nend_s = {k}.5" for k in range(1500)),
    "\n".join(f"[[anomaly.dipole]]\nnorth_m = {k}.0\neast_m = 0.0\ndepth_m = 5.0\n"
              f"moment_Am2 = 100.0" for k in range(150)),
    "[flight.ground]\nseconds = 20000.0\n[flight.landing]\nseconds = 5000.0\n",
    "[flight.survey]\nlegs = 10000\nleg_length_m = 100000.0\n",
    "[flight.ground]\nseconds = 3600.0\n", "[flight.ground]\nseconds = 39.0\n",
    "[recording]\nstart_s = 10.0\n", "[recording]\nquiet_before_s = 10.0\nquiet_after_s = 10.0\n",
    "[flight.calibration]\nheadings_deg = [" + ", ".join(["10.0"] * 400) + "]\n",
    "[[faults.card_busy]]\nstart_s = 1.0\nend_s = 3.0\nbusy_s = 10.0\n",
    "[[faults.baud_error]]\nchannel = 'mag'\nstart_s = 0.0\nend_s = 100.0\nerror = 0.25\n",
    "[[faults.noise_burst]]\nchannel = 'mag'\nstart_s = 7.0\nend_s = 9.0\ncount = 1000000\n",
    "[channels.mag]\ncapture = '/dev/null'\n", "[channels.gps]\ncapture = '.'\n",
    "[channels.cesium]\ncapture = 'shared:none.txt'\n",
)
SIZES = ("0", "1", "511", "512", "1MiB", "32MiB", "64MiB", "1GB", "2GiB", "4GB", "32GiB",
         "33GiB", "1e9", "-1", "abc", "", "64 MiB", "64mib", "9" * 40, "1TB", "0x100000")
LABELS = ("MAGLOG", "", " ", "a" * 11, "a" * 12, "x" * 10_000, "\u00c4\u00d6\u00dc", "A.B",
          "A*B", "\x00", "NO NAME", "lower", "\t", "\u3042")
CHANNELS = ("pmag:115200,nmea:9600,cesium:9600", "pmag:0", "pmag:1", "pmag:999999999",
            "imu:9600", "", "pmag", "pmag:115200," * 40, "cesium:9600", "nmea:-5",
            "pmag:1e5", "pmag:115200,nmea:9600,cesium:9600,pmag:9600")
CLOCKS = ("50e6", "0", "-1", "nan", "inf", "1e3", "999", "500e6", "5e8", "1e12", "x", "")
FRAMES = ("128", "0", "1", "4096", "4097", "-1", "1e3", "x", "9" * 50)
FIFOS = ("1024", "2", "3", "1", "0", "1023", "65536", "1e3", "x")
PHASES = ("-3", "-inf", "inf", "nan", "-nan", "0", "-1e-3", "1e3", "-20", "20", "x", "",
          "-infinity", "1e308")
SPEEDS = ("1e4", "5e3", "1000", "1e6", "0", "-1", "nan", "inf", "1e-4", "x", "")
PORTS = ("mag=loop://", "loop://", "mag=foo://x", "mag=/dev/null", "mag=/nonexistent/tty",
         "mag=", "=loop://", "imu=loop://", "", "mag=" + "p" * 5000, "gps=loop://",
         "cesium=loop://", "mag=/proc/self/mem", "mag=spy://loop://")
SECONDS = ("0.2", "0.5", "0", "-1", "nan", "inf", "1e8", "x", "")
BAUDS = ("mag=115200", "mag=0", "mag=49", "mag=4000001", "gps=9600", "imu=9600", "mag=x",
         "mag", "cesium=1e5", "gps=-5")
OUTPUTS = ("{work}/out", "/proc/maglog-x", "{work}/FILE", "{work}/FILE/sub", "",
           "{work}/" + "n" * 300, "{work}/a/b/c", "/dev/null", "{work}/full")


@dataclass
class Case:
    """One input: files to create in a fresh folder, the argv (``{work}`` that folder), and
    which command's output judges an exit 0."""
    index: int
    kind: str
    detail: str
    argv: list
    judge: str
    files: dict = field(default_factory=dict)


# --- scenario files -----------------------------------------------------------------------

def _toml(value):
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def _document(data, raw=None):
    """TOML text of ``data`` (tables of keys, [[arrays]] under faults and anomaly); ``raw``
    {(table, key): TOML text} replaces those values."""
    raw = dict(raw or {})
    lines = []

    def table(name, keys):
        lines.append(f"[{name}]")
        for key, value in keys.items():
            lines.append(f"{key} = {raw.pop((name, key), None) or _toml(value)}")
        for (t, key), text in list(raw.items()):
            if t == name:
                lines.append(f"{key} = {text}")
                del raw[(t, key)]
    for top, value in data.items():
        if top in ("faults", "anomaly"):
            for kind, entries in value.items():
                for number, entry in enumerate(entries, 1):
                    name = f"{top}.{kind}"
                    lines.append(f"[[{name}]]")
                    for key, v in entry.items():
                        text = raw.pop((f"{name}#{number}", key), None) or _toml(v)
                        lines.append(f"{key} = {text}")
                    for (t, key), text in list(raw.items()):
                        if t == f"{name}#{number}":
                            lines.append(f"{key} = {text}")
                            del raw[(t, key)]
        elif top in ("flight", "channels"):
            for sub, keys in value.items():
                table(f"{top}.{sub}", keys)
        else:
            table(top, value)
    extra = {}
    for (name, key), text in raw.items():      # tables the base does not have
        extra.setdefault(name, []).append(f"{key} = {text}")
    for name, keys in extra.items():
        header = f"[[{name.split('#')[0]}]]" if "#" in name else f"[{name}]"
        lines += [header] + keys
    return "\n".join(lines) + "\n"


def _schema_keys():
    from maglog.sim.stimulus.config import DIPOLE_SCHEMA, FAULT_SCHEMA, SCHEMA
    keys = [(table, key) for table, schema in SCHEMA.items() for key in schema]
    keys += [("faults.noise_burst#1", key) for key in FAULT_SCHEMA["noise_burst"]]
    keys += [(f"faults.{kind}#1", key) for kind, schema in FAULT_SCHEMA.items()
             if kind != "noise_burst" for key in schema]
    keys += [("anomaly.dipole#1", key) for key in DIPOLE_SCHEMA]
    return keys


def _fault_base(table):
    """The base document with the fault or dipole table ``table`` complete but for the
    mutated key (so that the mutation is what is judged)."""
    import copy
    data = copy.deepcopy(BASE)
    kind = table.split("#")[0]
    if kind == "anomaly.dipole":
        data["anomaly"] = {"dipole": [{"north_m": 20.0, "east_m": 10.0, "depth_m": 10.0,
                                       "moment_Am2": 1e4}]}
    elif kind.startswith("faults.") and kind != "faults.noise_burst":
        name = kind.split(".")[1]
        entry = {"start_s": 10.0, "end_s": 12.0}
        if name in ("dropped_bytes", "bad_checksum", "baud_error"):
            entry["channel"] = "gps"
        if name == "baud_error":
            entry["error"] = 0.01
        if name == "card_busy":
            entry["busy_s"] = 0.05
        data["faults"][name] = [entry]
    return data


def _scenario_value(rng):
    keys = _schema_keys()
    count = 1 if rng.random() < 0.8 else int(rng.integers(2, 4))
    picks = [keys[int(rng.integers(len(keys)))] for _ in range(count)]
    data = _fault_base(picks[0][0]) if "#" in picks[0][0] else BASE
    raw = {}
    for table, key in picks:
        raw[(table, key)] = WEIRD_VALUES[int(rng.integers(len(WEIRD_VALUES)))]
    detail = "; ".join(f"[{t}] {k} = {v[:30]}" for (t, k), v in raw.items())
    return _document(data, raw), detail


def _scenario_structure(rng):
    text = STRUCTURES[int(rng.integers(len(STRUCTURES)))]
    if rng.random() < 0.5 and not text.startswith(("\x00", "\xff")):
        text = _document(BASE) + text
    return text, f"document: {text[:40]!r} ({len(text)} chars)"


def _scenario_sensor(rng):
    """Geophysics and error settings near and beyond what the sensors' formats carry."""
    import copy
    data = copy.deepcopy(BASE)
    op = int(rng.integers(6))
    if op in (0, 1):
        moment = float(10 ** rng.uniform(0, 13))
        depth = float(10 ** rng.uniform(-3, 3))
        data["anomaly"] = {"dipole": [{"north_m": float(rng.uniform(-50, 50)),
                                       "east_m": float(rng.uniform(-50, 50)),
                                       "depth_m": depth, "moment_Am2": moment}]}
        if op == 1:
            data["flight"]["takeoff"]["height_m"] = float(10 ** rng.uniform(-6, 1))
        detail = f"dipole {moment:.3g} A·m² at {depth:.3g} m"
    elif op == 2:
        tl = [0.0] * 18
        tl[int(rng.integers(18))] = float(10 ** rng.uniform(-3, 7)) * rng.choice([-1, 1])
        data["interference"] = {"tl_coefficients": tl,
                                "heading_error_nT": float(rng.uniform(-1000, 1000))}
        detail = f"tl_coefficients {max(tl, key=abs):.3g}"
    elif op == 3:
        eddy = [0.0] * 9
        eddy[int(rng.integers(9))] = float(10 ** rng.uniform(-3, 7))
        data["interference"] = {"vector_eddy_s": eddy}
        detail = f"vector_eddy_s {max(eddy):.3g}"
    elif op == 4:
        data["errors"] = {"preset": ["default", "paper_a", "none"][int(rng.integers(3))],
                          "noise_nT": float(rng.uniform(0, 1000)),
                          "mounting_deg": [float(v) for v in rng.uniform(-180, 180, 3)]}
        detail = f"errors {data['errors']['preset']} noise {data['errors']['noise_nT']:.3g}"
    else:
        data["diurnal"] = {"amplitude_nT": float(rng.uniform(0, 5000)),
                           "pulsation_nT": float(rng.uniform(0, 1000)),
                           "pulsation_period_s": float(10 ** rng.uniform(-3, 4)),
                           "base_station": bool(rng.random() < 0.5)}
        data["site"] = {"lat_deg": float(rng.uniform(-89, 89)),
                        "ground_alt_m": float(rng.uniform(-400, 8000))}
        detail = f"diurnal {data['diurnal']['amplitude_nT']:.3g} nT at lat " \
                 f"{data['site']['lat_deg']:.3g}"
    return _document(data), detail


def _scenario_run(rng):
    """A calibration flight for ``maglog run``: one to four headings, swings from none to
    60°, turbulence, noise: flights that determine the parameters and flights that do
    not, for the run's verdict."""
    import copy
    data = copy.deepcopy(BASE)
    count = int(rng.integers(1, 5))
    cal = {"headings_deg": [float(h) for h in rng.uniform(-180, 180, count)],
           "seconds": float(rng.uniform(4, 20)), "turn_s": float(rng.uniform(1, 4)),
           "roll_deg": float(rng.choice([0.0, 2.0, rng.uniform(0, 60)])),
           "pitch_deg": float(rng.choice([0.0, 2.0, rng.uniform(0, 60)])),
           "yaw_deg": float(rng.choice([0.0, rng.uniform(0, 180)]))}
    data["flight"]["calibration"] = cal
    data["flight"]["dynamics"] = {"turbulence_deg": float(rng.choice([0.0, 0.7, 5.0]))}
    data["errors"] = {"noise_nT": float(rng.choice([0.0, 5.0, 50.0]))}
    del data["faults"]
    detail = (f"{count} headings x {cal['seconds']:.1f} s, roll {cal['roll_deg']:.3g}, "
              f"pitch {cal['pitch_deg']:.3g}, yaw {cal['yaw_deg']:.3g}")
    return _document(data), detail


def _run_argv():
    return ["run", "{work}/scenario.toml", "-o", "{work}/out", "--backend", "model",
            "--quiet", "--quick-papers", "--max-seconds", "120"]


def _simulate_argv(rng):
    argv = ["simulate", "{work}/scenario.toml", "-o", "{work}/out/card.img", "--backend",
            "model", "--quiet", "--max-seconds", MAX_SECONDS]
    return argv


# --- options --------------------------------------------------------------------------------

def _pick(rng, values):
    return values[int(rng.integers(len(values)))]


#: Each option class: its valid argv (options as [name, value] pairs, ``None`` value: a
#: flag), the values to mutate each option with, and how often an input is left valid
#: (each valid hdl input elaborates the logger: seconds).
OPTIONS = {
    "card:format": ([["image", "{work}/card.img"], ["--size", "64MiB"],
                     ["--cluster-size", "512"], ["--label", "MAGLOG"]],
                    {"image": ("{work}/card.img", "{work}/FILE", "{work}", "/proc/maglog.img",
                               "", "{work}/new/card.img", "{work}/full"),
                     "--size": SIZES, "--label": LABELS,
                     "--cluster-size": ("512", "4KiB", "32KiB", "64KiB", "0", "3", "1MiB",
                                        "x", "4096"),
                     "--volume-id": ("0", "1", "4294967295", "4294967296", "-1", "0x10", "x"),
                     "--force": None}, 0.35),
    "hdl:verilog": ([["-o", "{work}/out.v"], ["--frontend", None]],
                    {"--channels": CHANNELS, "--clk-freq": CLOCKS, "--max-frame": FRAMES,
                     "--fifo-depth": FIFOS, "-o": OUTPUTS}, 0.1),
    "hdl:regmap": ([["--format", "c"], ["-o", "{work}/regs.h"]],
                   {"--format": ("markdown", "c", "C", "html", "", "x" * 1000),
                    "-o": OUTPUTS + ("-",)}, 0.1),
    "hdl:build": ([["--board", "de0nano"], ["-o", "{work}/project"], ["--sdram-phase", "-3"]],
                  {"--board": ("de0nano", "logger-ep4ce6", "x", "", "b" * 5000, "DE0NANO"),
                   "--sdram-phase": PHASES, "-o": OUTPUTS, "--force": None}, 0.05),
    "hdl:component": ([["-o", "{work}/component"]],
                      {"--channels": CHANNELS, "--clk-freq": CLOCKS, "--max-frame": FRAMES,
                       "--fifo-depth": FIFOS, "-o": OUTPUTS}, 0.05),
    "replay": ([["scenario", "short"], ["--port", "cesium=loop://"], ["--speed", "1000"]],
               {"scenario": ("short", "{work}/scenario.toml", "missing", "{work}/FILE",
                             "{work}", "survey", "default"),
                "--port": PORTS, "--speed": SPEEDS, "--baud-faults": None}, 0.25),
    # Always a --seconds: without it a recording runs until Ctrl-C.
    "record": ([["-o", "{work}/LOG.TXT"], ["--port", "mag=loop://"], ["--seconds", "0.2"]],
               {"-o": ("{work}/LOG.TXT", "{work}/FILE", "{work}", "/proc/maglog.txt",
                       "{work}/new/LOG.TXT", "{work}/full"),
                "--port": PORTS, "--seconds": SECONDS, "--baud": BAUDS, "--max-frame": FRAMES,
                "--force": None}, 0.3),
}
#: The command words of each option class.
COMMANDS = {"card:format": ["card", "format"], "hdl:verilog": ["hdl", "verilog"],
            "hdl:regmap": ["hdl", "regmap"], "hdl:build": ["hdl", "build"],
            "hdl:component": ["hdl", "component"], "replay": ["replay"], "record": ["record"]}


def _option_case(kind, rng):
    """(argv, detail, judge, files) of an option class: its valid argv with none (now and
    then), one or two options changed, added or repeated."""
    valid, choices, keep = OPTIONS[kind]
    options = [list(pair) for pair in valid]
    changed = []
    if rng.random() >= keep:
        for _ in range(1 if rng.random() < 0.75 else 2):
            name = sorted(choices)[int(rng.integers(len(choices)))]
            values = choices[name]
            value = None if values is None else _pick(rng, values)
            here = [pair for pair in options if pair[0] == name]
            if here and values is not None and rng.random() < 0.85:
                here[0][1] = value
            elif values is None and here:
                options.remove(here[0])
            else:
                options.append([name, value])
            changed.append(f"{name} {value[:30]!r}" if value is not None else name)
    argv = list(COMMANDS[kind])
    for name, value in options:
        if name in ("image", "scenario"):
            argv.append(value)
        elif value is None:
            argv.append(name)
        elif value.startswith("-") and rng.random() < 0.5:
            argv.append(f"{name}={value}")
        else:
            argv += [name, value]
    files = {"FILE": b"a file where a folder should be", "full/keep.txt": b"mine",
             "scenario.toml": _document(BASE).encode()}
    judge = kind.split(":")[-1] if kind.startswith(("hdl:", "card:")) else kind
    judge = "card" if kind == "card:format" else judge
    return argv, "; ".join(changed) or "valid", judge, files


def _known():
    """The issue's own findings on these surfaces, one each: every run starts with them."""
    hour = _document({**BASE, "flight": {**BASE["flight"], "ground": {"seconds": 3600.0}}})
    cases = [
        ("scenario:value", "seed of 5000 digits", _document(BASE, {("scenario", "seed"):
                                                                   "9" * 5000})),
        ("scenario:sensor", "dipole of 1e15 A·m²", _document(
            {**BASE, "anomaly": {"dipole": [{"north_m": 0.0, "east_m": 0.0, "depth_m": 1.0,
                                             "moment_Am2": 1e15}]}})),
        ("scenario:sensor", "1 mm below a 1 µm flight", _document(
            {**BASE, "flight": {**BASE["flight"], "takeoff": {"seconds": 3.0,
                                                             "height_m": 1e-6}},
             "anomaly": {"dipole": [{"north_m": 0.0, "east_m": 0.0, "depth_m": 0.001,
                                     "moment_Am2": 1.0}]}})),
        ("scenario:value", "[flight.ground] seconds = 2**63-1", _document(
            BASE, {("flight.ground", "seconds"): "9223372036854775807"})),
        ("scenario:value", "[flight.landing] seconds = 2**63-1", _document(
            BASE, {("flight.landing", "seconds"): "9223372036854775807"})),
        ("scenario:value", "[flight.survey] legs = 2**63-1", _document(
            BASE, {("flight.survey", "legs"): "9223372036854775807"})),
        ("scenario:value", "height_m = 2**53+1", _document(
            BASE, {("flight.takeoff", "height_m"): "9007199254740993"})),
        ("scenario:value", "ground 1e7 s", _document(
            BASE, {("flight.ground", "seconds"): "1e7"})),
        ("scenario:value", "ground 1e9 s", _document(
            BASE, {("flight.ground", "seconds"): "1e9"})),
        ("scenario:value", "end_after_stop_s = 2**31", _document(
            BASE, {("recording", "end_after_stop_s"): "2147483648"})),
        ("scenario:structure", "an hour on the ground", hour),
        ("scenario:value", "turbulence_deg = 65536", _document(
            BASE, {("flight.dynamics", "turbulence_deg"): "65536"})),
        ("scenario:value", "noise_nT = 9.2e18", _document(
            BASE, {("errors", "noise_nT"): "9.2e18"})),
        ("scenario:value", "a 10,000-character value", _document(
            BASE, {("gps", "talker"): "'" + "x" * 10_000 + "'"})),
    ]
    options = [
        ("replay", "--speed 1e6 into loop://", ["replay", "short", "--port", "mag=loop://",
                                                "--speed", "1e6"], "replay"),
        ("replay", "--speed 1e4 into loop://", ["replay", "short", "--port", "mag=loop://",
                                                "--speed", "1e4"], "replay"),
        ("hdl:build", "-o /proc/x", ["hdl", "build", "--board", "de0nano", "-o", "/proc/x"],
         "build"),
        ("hdl:component", "-o FILE", ["hdl", "component", "-o", "{work}/FILE"], "component"),
        ("hdl:build", "--sdram-phase -inf", ["hdl", "build", "--board", "de0nano", "-o",
                                             "{work}/p", "--sdram-phase", "-inf"], "build"),
        ("card:format", "--label ÄÖÜ", ["card", "format", "{work}/c.img", "--size", "4GB",
                                        "--label", "\u00c4\u00d6\u00dc"], "card"),
    ]
    return cases, options


def make_case(index, seed):
    """Input number ``index`` of the run seeded ``seed``: first the issue's own inputs
    (:func:`_known`), then classes cycling through :data:`CLASSES`."""
    rng = np.random.default_rng([seed, index])
    scenarios, options = _known()
    if index < len(scenarios):
        kind, detail, text = scenarios[index]
        return Case(index, kind, detail, _simulate_argv(rng), "simulate",
                    {"scenario.toml": text.encode("utf-8")})
    if index < len(scenarios) + len(options):
        kind, detail, argv, judge = options[index - len(scenarios)]
        return Case(index, kind, detail, argv, judge, {"FILE": b"mine"})
    kind = CLASSES[index % len(CLASSES)]
    if kind == "scenario:run":
        text, detail = _scenario_run(rng)
        return Case(index, kind, detail, _run_argv(), "run", {"scenario.toml": text.encode()})
    if kind.startswith("scenario:"):
        make = {"scenario:value": _scenario_value, "scenario:structure": _scenario_structure,
                "scenario:sensor": _scenario_sensor}[kind]
        text, detail = make(rng)
        data = text.encode("utf-8", "surrogateescape") if not text.startswith("\xff") \
            else b"\xff\xfe" + text[2:].encode()
        return Case(index, kind, detail, _simulate_argv(rng), "simulate",
                    {"scenario.toml": data})
    argv, detail, judge, files = _option_case(kind, rng)
    return Case(index, kind, detail, argv, judge, files)


# --- running --------------------------------------------------------------------------------

class _Timeout(BaseException):
    """Raised by the alarm: not an Exception, so no handler in the code under test eats it."""


def _alarm(signum, frame):
    raise _Timeout()


def _worker_init(memory_limit=MEMORY_LIMIT):
    import warnings
    warnings.filterwarnings("ignore")
    try:
        import numba
        numba.set_num_threads(1)
    except ImportError:
        pass
    signal.signal(signal.SIGALRM, _alarm)
    if memory_limit:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        limit = memory_limit if hard == resource.RLIM_INFINITY else min(memory_limit, hard)
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))


def _materialise(case, work):
    for name, content in case.files.items():
        path = work / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)


def run_case(case, time_limit=TIME_LIMIT):
    """Run one input through ``maglog.cli.main.main`` in this process; its outcome."""
    from maglog.cli.main import main
    work = Path(tempfile.mkdtemp(prefix=f"surface{case.index}-"))
    here = os.getcwd()
    argv = [a.replace("{work}", str(work)) for a in case.argv]
    out, err = io.StringIO(), io.StringIO()
    result = {"index": case.index, "kind": case.kind, "detail": case.detail}
    start = time.perf_counter()
    try:
        _materialise(case, work)
        os.chdir(work)
        signal.alarm(time_limit)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                status = main(argv)
        except SystemExit as exit_:
            status = exit_.code
        finally:
            signal.alarm(0)
        result.update(_classify(case, status, out.getvalue(), err.getvalue(), work))
    except _Timeout:
        result.update(outcome="hang", reason=f"no answer within {time_limit} s")
    except MemoryError:
        result.update(outcome="oom", reason="MemoryError escaped main")
    except Exception as error:           # what escaped main: the failure counted here
        frames = traceback.extract_tb(error.__traceback__)
        where = frames[-1] if frames else None
        at = f" at {Path(where.filename).name}:{where.lineno}" if where else ""
        result.update(outcome="traceback",
                      reason=f"{type(error).__name__}: {str(error)[:160]}{at}")
    finally:
        signal.alarm(0)
        os.chdir(here)
        shutil.rmtree(work, ignore_errors=True)
    result["seconds"] = round(time.perf_counter() - start, 3)
    return result


def _classify(case, status, out, err, work):
    # The lines that say an error (progress, notes and warnings are other lines).
    lines = [line for line in err.strip().splitlines() if line.startswith("maglog")]
    last = err.strip().splitlines()[-1] if err.strip() else ""
    if "Traceback" in err:
        return {"outcome": "traceback", "reason": "a traceback printed: " + last[:160]}
    if status in (1, 2):
        if "out of memory" in last:
            return {"outcome": "oom", "reason": last[:200]}
        if len(last) > LINE_MAX:
            return {"outcome": "nonsense", "reason": f"an error line of {len(last)} characters: "
                                                     f"{last[:120]!r}"}
        if len(lines) > 1:
            return {"outcome": "nonsense", "reason": f"{len(lines)} error lines: {lines[:2]!r}"}
    if status == 1 and case.judge == "run" and "does not match its scenario's truth" in last:
        return _judge_run(work, failed=True, last=last)
    if status == 1:
        if last.startswith("maglog: error: "):
            return {"outcome": "error", "reason": last[len("maglog: error: "):][:200]}
        return {"outcome": "nonsense", "reason": f"exit 1 without a message: {last[:200]!r}"}
    if status == 2:
        if "error:" in last:
            return {"outcome": "usage", "reason": last[:200]}
        return {"outcome": "nonsense", "reason": f"exit 2 without a message: {last[:200]!r}"}
    if status not in (0, None):
        return {"outcome": "nonsense", "reason": f"exit status {status!r}: {last[:160]!r}"}
    return _judge(case, out, work)


def _strict_json(path):
    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def _judge_run(work, *, failed, last=""):
    """``maglog run``'s summary.json: strict JSON, its verdict the checks', and no
    parameter passed on a z its own sigma made small (not determined by the flight)."""
    try:
        summary = _strict_json(work / "out" / "report" / "summary.json")
    except (OSError, ValueError) as error:
        return {"outcome": "nonsense", "reason": f"summary.json: {error}"[:200]}
    checks = {c["name"]: c for c in summary.get("checks", [])}
    if summary.get("ok") is failed or bool(summary.get("failed")) is not failed:
        return {"outcome": "nonsense", "reason": f"exit status and summary disagree: ok "
                                                 f"{summary.get('ok')}, {last[:100]!r}"}
    tol = summary["tolerances"]
    rows = summary.get("parameters") or {}
    for name, row in rows.items():
        absolute = tol["c_abs_nT"] if name.startswith("c") else tol["k_abs"]
        if row.get("determined") is False and abs(row["difference"]) > absolute \
                and checks.get("parameters", {}).get("status") == "pass":
            return {"outcome": "nonsense", "reason": f"{name} passed, {row['difference']:+.3g} "
                                                     "off and not determined by the flight"}
    verdict = checks.get("parameters", {})
    return {"outcome": "error" if failed else "ok",
            "reason": f"parameters {verdict.get('status')}: {verdict.get('detail', '')}"[:200]}


def _judge(case, out, work):
    """An exit 0: is what the command promises there?"""
    judge = case.judge
    try:
        if judge == "run":
            return _judge_run(work, failed=False)
        if judge == "simulate":
            folder = work / "out"
            truth = _strict_json(folder / "truth.json")
            record = _strict_json(folder / "simulation.json")
            if not (folder / "card.img").stat().st_size:
                raise ValueError("an empty card image")
            kept = sum(c.get("kept", 0) for c in (record.get("counters") or {}).values())
            return {"outcome": "ok", "reason": f"{record['simulated_s']:.1f} s simulated, "
                                               f"{kept} frames kept, truth v{truth['version']}"}
        if judge == "card":
            if "clusters:" not in out:
                raise ValueError("no layout printed")
            return {"outcome": "ok", "reason": out.splitlines()[0][:120]}
        if judge == "verilog":
            target = [Path(a.replace("{work}", str(work))) for a in case.argv
                      if a.startswith("{work}") or a.startswith("/")]
            if target and not target[0].is_file():      # /dev/null: said, not kept
                return {"outcome": "ok", "reason": f"written to {target[0]}"}
            text = target[0].read_text() if target else out
            if "module " not in text:
                raise ValueError("no Verilog module written")
            return {"outcome": "ok", "reason": f"{len(text.splitlines())} lines of Verilog"}
        if judge in ("regmap", "component", "build", "replay", "record"):
            if judge == "build" and not any(work.rglob("build.sh")) and \
                    "Quartus project" not in out:
                raise ValueError("no build.sh written")
            if judge == "component" and "Platform Designer component" not in out:
                raise ValueError("no component said")
            if judge == "replay" and "of scenario at" not in out:
                raise ValueError("no replay table")
            if judge == "record" and "frames," not in out:
                raise ValueError("no recording summary")
            return {"outcome": "ok", "reason": (out.strip().splitlines() or [""])[-1][:120]}
    except (OSError, ValueError, KeyError, TypeError, IndexError) as error:
        return {"outcome": "nonsense", "reason": f"exit 0 but {error}"[:200]}
    return {"outcome": "nonsense", "reason": f"exit 0, no judge for {judge}"}


def run(count, *, seed=10, processes=None, time_limit=TIME_LIMIT, progress=None,
        memory_limit=MEMORY_LIMIT):
    """Generate and run ``count`` inputs; the results (one dict per input) in input order."""
    cases = [make_case(i, seed) for i in range(count)]
    processes = processes or min(2, os.cpu_count() or 1)
    context = multiprocessing.get_context("spawn")
    results = []
    with context.Pool(processes, initializer=_worker_init, initargs=(memory_limit,),
                      maxtasksperchild=50) as pool:
        jobs = [pool.apply_async(run_case, (case, time_limit)) for case in cases]
        for case, job in zip(cases, jobs):
            try:
                result = job.get(timeout=time_limit + 120)
            except multiprocessing.TimeoutError:
                result = {"index": case.index, "kind": case.kind, "detail": case.detail,
                          "outcome": "hang", "reason": "the worker did not answer"}
            results.append(result)
            if progress:
                progress(result)
    return results


def counts(results):
    """Totals by outcome, and by class and outcome."""
    total = Counter(r["outcome"] for r in results)
    by_class = {}
    for r in results:
        by_class.setdefault(r["kind"], Counter())[r["outcome"]] += 1
    return ({o: total.get(o, 0) for o in OUTCOMES},
            {k: {o: c.get(o, 0) for o in OUTCOMES} for k, c in sorted(by_class.items())})


def failures(results):
    return [r for r in results if r["outcome"] in FAILURES]
