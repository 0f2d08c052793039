"""Scenario files: TOML read with :mod:`tomllib`, every key checked against :data:`SCHEMA`.

A scenario file holds tables; every key has a type, a check and a default (the built-in
``default.toml`` spells all of them out). Unknown tables and keys are errors, and every error
names the file, the table and the key::

    scenario.toml: [flight.calibration] seconds must be > 0, not -3

docs/scenarios.md describes every key.
"""

from __future__ import annotations

import datetime as _dt
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

__all__ = ["ScenarioError", "MAX_SCENARIO_S", "SEED_MAX", "shorten", "SurveyScenario",
           "Fault", "Dipole", "SCHEMA", "FAULT_SCHEMA",
           "DIPOLE_SCHEMA", "CHANNEL_NAMES", "FAULT_KINDS", "TL_TERMS",
           "default_scenario_path", "load_scenario", "loads_scenario", "scenario_from_dict",
           "preset_names"]

#: Channel names, in the logger's ``uart_rx`` order (FLIGHT_CHANNELS).
CHANNEL_NAMES = ("mag", "gps", "cesium")
FAULT_KINDS = ("noise_burst", "dropped_bytes", "bad_checksum", "baud_error", "gps_outage",
               "card_busy")
TIMINGS = ("rate", "groups", "stream")
#: How far a baud-error fault may take a line (uart_line.encode's own limit).
MAX_BAUD_ERROR = 0.25
#: Tolles–Lawson terms of ``[interference] tl_coefficients`` (geophysics.TL_TERM_NAMES).
TL_TERMS = 18
#: The longest run (power-up to the run's end, seconds) a scenario may describe: six hours,
#: beyond any multirotor's endurance; the flight's arrays (100 Hz) and frames stay within a
#: few GB. The command line's ``--max-seconds`` (default far lower) refuses long runs first.
MAX_SCENARIO_S = 6 * 3600.0
#: Seeds are 32-bit unsigned integers (as ``maglog --seed``).
SEED_MAX = (1 << 32) - 1
#: Longest text of a value (or key) an error message repeats.
ECHO_CHARS = 60


class ScenarioError(ValueError):
    """A scenario file that cannot be used (the message says where and why, one line)."""


# --- key checks ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Key:
    kind: str                 # float, int, str, bool, datetime, floats, choice, path
    default: object
    check: object = None      # (predicate, "must be ...") or None
    choices: tuple = ()


def _positive():
    return (lambda v: v > 0, "must be > 0")


def _num(x):
    return str(x) if isinstance(x, int) else f"{x:g}"


def _at_least(low):
    return (lambda v: v >= low, f"must be >= {_num(low)}")


def _within(low, high):
    return (lambda v: low <= v <= high, f"must be within {_num(low)}..{_num(high)}")


def _below(limit):
    return (lambda v: v < limit, f"must be < {limit:g}")


def _from(low, high):
    """``low`` to ``high``; said as ``>= low`` below it (the lower bound is the usual
    mistake), ``at most high`` above it."""
    return (lambda v: low <= v <= high,
            lambda v: f"must be >= {_num(low)}" if not v >= low
            else f"must be at most {_num(high)}")


def _up_to(limit):
    """> 0 and at most ``limit``."""
    return (lambda v: 0 < v <= limit,
            lambda v: "must be > 0" if not v > 0 else f"must be at most {_num(limit)}")


#: Any one duration of the flight or the recording.
_SECONDS = _up_to(MAX_SCENARIO_S)


SCHEMA = {
    "scenario": {
        "name": Key("str", "unnamed"),
        "seed": Key("int", 0, _from(0, SEED_MAX)),
        "start": Key("datetime", _dt.datetime(2026, 6, 1, 10, 0, 0, tzinfo=_dt.timezone.utc)),
        "clk_freq_hz": Key("float", 1_843_200.0, _within(1e3, 500e6)),
        "max_frame": Key("int", 128, _within(18, 4096)),
    },
    "site": {
        "lat_deg": Key("float", 47.3769, _within(-89.0, 89.0)),
        "lon_deg": Key("float", 8.5417, _within(-180.0, 180.0)),
        "ground_alt_m": Key("float", 408.0, _within(-400.0, 8000.0)),
    },
    "recording": {
        "start_s": Key("float", 4.7, _SECONDS),
        "stop_after_landing_s": Key("float", 2.0, _from(0.0, 3600.0)),
        "end_after_stop_s": Key("float", 1.0, _up_to(3600.0)),
        "quiet_before_s": Key("float", 0.05, _from(0.0, 10.0)),
        "quiet_after_s": Key("float", 0.25, _from(0.0, 10.0)),
        "hold_s": Key("float", 0.1, _up_to(10.0)),
        "debounce_s": Key("float", 0.01, _up_to(1.0)),
    },
    "flight.ground": {
        "seconds": Key("float", 8.0, _SECONDS),
    },
    "flight.takeoff": {
        "seconds": Key("float", 10.0, _SECONDS),
        "height_m": Key("float", 40.0, _up_to(10_000.0)),
    },
    "flight.calibration": {
        "headings_deg": Key("floats", [0.0, 90.0, 180.0, 270.0]),
        "seconds": Key("float", 20.0, _SECONDS),
        "turn_s": Key("float", 4.0, _from(0.0, 3600.0)),
        "roll_deg": Key("float", 60.0, _within(0.0, 60.0)),
        "pitch_deg": Key("float", 60.0, _within(0.0, 60.0)),
        "yaw_deg": Key("float", 45.0, _within(0.0, 180.0)),
    },
    "flight.survey": {
        "legs": Key("int", 2, _from(0, 10_000)),
        "leg_length_m": Key("float", 150.0, _up_to(100_000.0)),
        "speed_m_s": Key("float", 10.0, _within(0.1, 50.0)),
        "course_deg": Key("float", 30.0, _within(-360.0, 360.0)),
        "spacing_m": Key("float", 20.0, _from(0.0, 10_000.0)),
        "turn_s": Key("float", 6.0, _up_to(3600.0)),
        "drag_per_s": Key("float", 0.1, _from(0.0, 10.0)),
        "tie_lines": Key("int", 0, _from(0, 1000)),
    },
    "flight.landing": {
        "seconds": Key("float", 10.0, _SECONDS),
    },
    "flight.dynamics": {
        "natural_hz": Key("float", 1.2, _within(0.05, 10.0)),
        "damping": Key("float", 0.8, _within(0.1, 2.0)),
        "max_rate_deg_s": Key("float", 120.0, _up_to(3600.0)),
        "max_yaw_rate_deg_s": Key("float", 60.0, _up_to(3600.0)),
        "turbulence_deg": Key("float", 0.7, _from(0.0, 30.0)),
        "turbulence_s": Key("float", 1.0, _within(0.02, 60.0)),
    },
    "gps": {
        "first_s": Key("float", 1.0, _from(0.0, MAX_SCENARIO_S)),
        "offset_s": Key("float", 0.05, _within(0.0, 0.5)),
        "fix_s": Key("float", 6.0, _from(0.0, MAX_SCENARIO_S)),
        "talker": Key("str", "GP"),
        "satellites": Key("int", 10, _within(4, 12)),
        "hdop": Key("float", 0.9, _up_to(99.9)),
        "geoid_m": Key("float", 47.4, _within(-120.0, 120.0)),
        "distractors": Key("bool", True),
    },
    "channels.mag": {
        "baud": Key("int", 115_200, _within(1, 10_000_000)),
        "rate_hz": Key("float", 20.0, _within(10.0, 50.0)),
        "first_s": Key("float", 0.0123, _from(0.0, 10.0)),
        "capture": Key("path", ""),
        "timing": Key("choice", "rate", choices=TIMINGS),
    },
    "channels.gps": {
        "baud": Key("int", 9_600, _within(1, 10_000_000)),
        "capture": Key("path", ""),
        "timing": Key("choice", "groups", choices=TIMINGS),
    },
    "channels.cesium": {
        "baud": Key("int", 9_600, _within(1, 10_000_000)),
        "rate_hz": Key("float", 10.0, _within(1.0, 20.0)),
        "first_s": Key("float", 0.0437, _from(0.0, 10.0)),
        "noise_nT": Key("float", 0.05, _from(0.0, 1000.0)),
        "signal": Key("int", 1250, _within(0, 9999)),
        "capture": Key("path", ""),
        "timing": Key("choice", "rate", choices=TIMINGS),
    },
    "errors": {
        "preset": Key("choice", "paper_a", choices=("default", "paper_a", "none")),
        "noise_nT": Key("float", 5.0, _from(0.0, 1000.0)),
        "mounting_deg": Key("floats", [0.0, 0.0, 0.0]),
    },
    "interference": {
        "tl_coefficients": Key("floats", [0.0] * TL_TERMS),
        "vector_eddy_s": Key("floats", [0.0] * 9),
        "heading_error_nT": Key("float", 0.0, _within(-1000.0, 1000.0)),
    },
    "diurnal": {
        "amplitude_nT": Key("float", 0.0, _from(0.0, 5000.0)),
        "pulsation_nT": Key("float", 0.0, _from(0.0, 1000.0)),
        "pulsation_period_s": Key("float", 600.0, _up_to(86_400.0)),
        "base_station": Key("bool", False),
        "base_rate_hz": Key("float", 1.0, _within(0.01, 100.0)),
        "base_noise_nT": Key("float", 0.01, _from(0.0, 1000.0)),
    },
}

#: Keys of a ``[[anomaly.dipole]]`` table (None: required; NaN: optional, absent = induced).
DIPOLE_SCHEMA = {
    "north_m": Key("float", None, _within(-1e6, 1e6)),
    "east_m": Key("float", None, _within(-1e6, 1e6)),
    "depth_m": Key("float", None, _up_to(100_000.0)),
    "moment_Am2": Key("float", None, _up_to(1e13)),
    "inclination_deg": Key("float", math.nan, _within(-90.0, 90.0)),
    "declination_deg": Key("float", math.nan, _within(-360.0, 360.0)),
}

#: Fault times may reach past the run (a fault over the whole run), within this.
MAX_FAULT_S = 1e6
#: At most this many tables of one fault kind, dipoles, and calibration headings.
MAX_FAULTS = 1000
MAX_DIPOLES = 100
MAX_HEADINGS = 360

#: Keys of each fault kind (``[[faults.<kind>]]`` tables); None: required.
FAULT_SCHEMA = {
    "noise_burst": {"channel": Key("channel", None),
                    "start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                    "end_s": Key("float", None, _up_to(MAX_FAULT_S)),
                    "count": Key("int", 1, _from(1, 1_000_000)),
                    "length": Key("int", 6, _within(1, 64))},
    "dropped_bytes": {"channel": Key("channel", None),
                      "start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                      "end_s": Key("float", None, _up_to(MAX_FAULT_S)),
                      "count": Key("int", 1, _from(1, 1_000_000))},
    "bad_checksum": {"channel": Key("channel", None),
                     "start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                     "end_s": Key("float", None, _up_to(MAX_FAULT_S)),
                     "count": Key("int", 1, _from(1, 1_000_000))},
    "baud_error": {"channel": Key("channel", None),
                   "start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                   "end_s": Key("float", None, _up_to(MAX_FAULT_S)),
                   "error": Key("float", None, _within(-MAX_BAUD_ERROR, MAX_BAUD_ERROR))},
    "gps_outage": {"start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                   "end_s": Key("float", None, _up_to(MAX_FAULT_S))},
    "card_busy": {"start_s": Key("float", None, _from(0.0, MAX_FAULT_S)),
                  "end_s": Key("float", None, _up_to(MAX_FAULT_S)),
                  "busy_s": Key("float", None, _within(1e-6, 10.0))},
}


@dataclass(frozen=True)
class Fault:
    """One ``[[faults.<kind>]]`` table: ``kind``, its index among those of its kind (from
    1), and its keys (``channel`` a name or None, ``start_s``, ``end_s``, ...)."""
    kind: str
    index: int
    channel: str | None
    start_s: float
    end_s: float
    params: dict = field(default_factory=dict)

    @property
    def where(self):
        return f"[[faults.{self.kind}]] #{self.index}"


@dataclass(frozen=True)
class Dipole:
    """One ``[[anomaly.dipole]]`` table (``index`` from 1): position from the site (m),
    depth below its ground (m), moment (A·m²), and the remanent direction (degrees) or
    None for both angles (induced: along the IGRF at the site)."""
    index: int
    north_m: float
    east_m: float
    depth_m: float
    moment_Am2: float
    inclination_deg: float | None = None
    declination_deg: float | None = None


@dataclass
class SurveyScenario:
    """A validated scenario: one namespace per table (``site``, ``recording``, ``gps``,
    ``errors``; ``flight.<phase>``; ``channels[name]``) and the faults.

    :meth:`build` turns it into a :class:`~maglog.sim.stimulus.Stimulus`."""
    source: str
    name: str
    seed: int
    start: _dt.datetime
    clk_freq: float
    max_frame: int
    site: SimpleNamespace
    recording: SimpleNamespace
    flight: SimpleNamespace
    gps: SimpleNamespace
    channels: dict
    errors: SimpleNamespace
    faults: list
    folder: Path | None = None        # where relative capture paths start
    dipoles: list = field(default_factory=list)
    interference: SimpleNamespace = None
    diurnal: SimpleNamespace = None

    @property
    def geophysics_on(self):
        """Whether dipoles, interference or a diurnal field change the sensors' field."""
        inter, di = self.interference, self.diurnal
        return bool(self.dipoles
                    or (inter is not None and (any(inter.tl_coefficients)
                                               or any(inter.vector_eddy_s)
                                               or inter.heading_error_nT))
                    or (di is not None and (di.amplitude_nT or di.pulsation_nT
                                            or di.base_station)))

    @property
    def survey_on(self):
        """Whether the truth gets a ``survey`` part (tie lines or any geophysics)."""
        return self.geophysics_on or (self.flight.survey.tie_lines > 0)

    def build(self):
        """The scenario's sensor streams, button presses, flight and truth (seeded)."""
        from .build import build
        return build(self)

    def error(self, where, message):
        return ScenarioError(f"{self.source}: {where} {message}")

    def flight_parts(self):
        """Seconds of each part of the flight and the recording after it, by the keys
        that set them (power-up to the run's end, before the presses are placed)."""
        from .flight import survey_seconds
        f, rec = self.flight, self.recording
        lines, ties = survey_seconds(f.survey)
        return {"[flight.ground] seconds": f.ground.seconds,
                "[flight.takeoff] seconds": f.takeoff.seconds,
                "[flight.calibration] seconds (per heading)":
                    len(f.calibration.headings_deg) * f.calibration.seconds,
                "[flight.survey] legs, leg_length_m, speed_m_s, turn_s": lines,
                "[flight.survey] tie_lines": ties,
                "[flight.landing] seconds": f.landing.seconds,
                "[recording] stop_after_landing_s": rec.stop_after_landing_s,
                "[recording] end_after_stop_s": rec.end_after_stop_s}

    def run_seconds(self):
        """The run's length (simulated seconds from power-up to its end), estimated from
        the keys before anything is built (the stop press may move a few seconds later to
        find a quiet GPS line)."""
        return float(sum(self.flight_parts().values()))


# --- parsing -------------------------------------------------------------------------------

def shorten(text, limit=ECHO_CHARS):
    """``text`` cut to ``limit`` characters with an ellipsis (error lines stay one short
    line whatever a file holds)."""
    text = str(text)
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _describe(value):
    """``value`` as an error line repeats it: its repr, cut short (an integer too long to
    print as decimal said by its size)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        return f"an integer of {value.bit_length()} bits"
    if isinstance(value, list) and len(value) > 8:
        return shorten(repr(value[:8])[:-1] + f", ... ({len(value)} items)]")
    try:
        text = repr(value)
    except ValueError:                  # a huge number in a nested value
        text = f"a {type(value).__name__}"
    return shorten(text)


def _finite(number):
    """A finite number, also as a float (an integer beyond 1.8e308 is not)."""
    try:
        return math.isfinite(float(number))
    except OverflowError:
        return False


def _convert(source, where, name, key, value):
    """``value`` checked against ``key``; raises ScenarioError naming ``where`` and
    ``name``."""
    original = value

    def fail(what):
        return ScenarioError(f"{source}: {where} {name} {what}, not {_describe(original)}")
    kind = key.kind
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not _finite(value):
            raise fail("must be a finite number")
        value = float(value)
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail("must be an integer")
    elif kind in ("str", "path"):
        if not isinstance(value, str):
            raise fail("must be a string")
    elif kind == "bool":
        if not isinstance(value, bool):
            raise fail("must be true or false")
    elif kind == "datetime":
        if not isinstance(value, _dt.datetime):
            raise fail("must be a TOML date-time (e.g. 2026-06-01T10:00:00Z)")
        if value.tzinfo is None:
            value = value.replace(tzinfo=_dt.timezone.utc)
        value = value.astimezone(_dt.timezone.utc)
    elif kind == "floats":
        if not isinstance(value, list) or not value or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and _finite(v)
                for v in value):
            raise fail("must be a non-empty list of finite numbers")
        value = [float(v) for v in value]
    elif kind == "choice":
        if value not in key.choices:
            raise fail(f"must be one of {', '.join(key.choices)}")
    elif kind == "channel":
        if value not in CHANNEL_NAMES:
            raise fail(f"must be one of {', '.join(CHANNEL_NAMES)}")
    if key.check is not None:
        predicate, text = key.check
        if not predicate(value):
            raise fail(text(value) if callable(text) else text)
    return value


def _table(source, where, schema, given):
    if not isinstance(given, dict):
        raise ScenarioError(f"{source}: {where} must be a table, not {_describe(given)}")
    unknown = sorted(set(given) - set(schema))
    if unknown:
        raise ScenarioError(f"{source}: {where} unknown key {shorten(repr(unknown[0]))} (known: "
                            f"{', '.join(schema)})")
    values = {}
    for name, key in schema.items():
        if name in given:
            values[name] = _convert(source, where, name, key, given[name])
        elif key.default is None:
            raise ScenarioError(f"{source}: {where} {name} is required")
        else:
            values[name] = key.default
    return values


def _split_tables(source, data):
    """The document's tables by dotted name (``flight.takeoff``), and its fault lists."""
    tables, faults = {}, {}
    for top, value in data.items():
        if top == "faults":
            if not isinstance(value, dict):
                raise ScenarioError(f"{source}: [faults] must hold [[faults.<kind>]] tables")
            for kind, entries in value.items():
                if kind not in FAULT_SCHEMA:
                    raise ScenarioError(f"{source}: unknown fault kind [[faults.{shorten(kind)}]] "
                                        f"(known: {', '.join(FAULT_KINDS)})")
                if not isinstance(entries, list):
                    raise ScenarioError(f"{source}: faults.{kind} must be an array of tables "
                                        f"([[faults.{kind}]]), not {_describe(entries)}")
                if len(entries) > MAX_FAULTS:
                    raise ScenarioError(f"{source}: at most {MAX_FAULTS} [[faults.{kind}]] "
                                        f"tables, not {len(entries)}")
                faults[kind] = entries
        elif top == "anomaly":
            if not isinstance(value, dict):
                raise ScenarioError(f"{source}: [anomaly] must hold [[anomaly.dipole]] tables")
            for kind, entries in value.items():
                if kind != "dipole":
                    raise ScenarioError(f"{source}: unknown table [anomaly.{shorten(kind)}] "
                                        "(known: [[anomaly.dipole]])")
                if not isinstance(entries, list):
                    raise ScenarioError(f"{source}: anomaly.dipole must be an array of tables "
                                        f"([[anomaly.dipole]]), not {_describe(entries)}")
                if len(entries) > MAX_DIPOLES:
                    raise ScenarioError(f"{source}: at most {MAX_DIPOLES} [[anomaly.dipole]] "
                                        f"tables, not {len(entries)}")
                faults["anomaly.dipole"] = entries
        elif top in ("flight", "channels"):
            if not isinstance(value, dict):
                raise ScenarioError(f"{source}: [{top}] must be a table")
            for sub, inner in value.items():
                name = f"{top}.{sub}"
                if name not in SCHEMA:
                    known = ", ".join(k for k in SCHEMA if k.startswith(top + "."))
                    raise ScenarioError(f"{source}: unknown table [{shorten(name)}] "
                                        f"(known: {known})")
                tables[name] = inner
        elif top in SCHEMA:
            tables[top] = value
        else:
            known = sorted({k.split(".")[0] for k in SCHEMA} | {"faults", "anomaly"})
            raise ScenarioError(f"{source}: unknown table [{shorten(top)}] (known: "
                               f"{', '.join(known)})")
    return tables, faults


def scenario_from_dict(data, *, source="<scenario>", folder=None):
    """A :class:`SurveyScenario` from a parsed TOML document."""
    tables, fault_lists = _split_tables(source, data)
    values = {name: _table(source, f"[{name}]", schema, tables.get(name, {}))
              for name, schema in SCHEMA.items()}
    faults = []
    for kind in FAULT_KINDS:
        for index, entry in enumerate(fault_lists.get(kind, []), 1):
            where = f"[[faults.{kind}]] #{index}"
            fields = _table(source, where, FAULT_SCHEMA[kind], entry)
            if not fields["end_s"] > fields["start_s"]:
                raise ScenarioError(f"{source}: {where} end_s must be > start_s "
                                    f"({fields['start_s']:g}), not {fields['end_s']!r}")
            channel = fields.pop("channel", "gps" if kind == "gps_outage" else None)
            if kind == "bad_checksum" and channel == "cesium":
                raise ScenarioError(f"{source}: {where} channel must be mag or gps (cesium "
                                    "lines have no checksum), not 'cesium'")
            faults.append(Fault(kind, index, channel, fields.pop("start_s"),
                                fields.pop("end_s"), fields))
    dipoles = []
    for index, entry in enumerate(fault_lists.get("anomaly.dipole", []), 1):
        where = f"[[anomaly.dipole]] #{index}"
        fields = _table(source, where, DIPOLE_SCHEMA, entry)
        angles = [fields[k] for k in ("inclination_deg", "declination_deg")]
        if sum(math.isnan(a) for a in angles) == 1:
            raise ScenarioError(f"{source}: {where} needs both inclination_deg and "
                                "declination_deg (remanent) or neither (induced)")
        if math.isnan(angles[0]):
            fields["inclination_deg"] = fields["declination_deg"] = None
        dipoles.append(Dipole(index=index, **fields))
    inter = values["interference"]
    for name, size in (("tl_coefficients", TL_TERMS), ("vector_eddy_s", 9)):
        if len(inter[name]) != size:
            raise ScenarioError(f"{source}: [interference] {name} must be {size} numbers, "
                                f"not {len(inter[name])}")
    survey = values["flight.survey"]
    if survey["tie_lines"] and (survey["legs"] < 2 or survey["spacing_m"] <= 0):
        raise ScenarioError(f"{source}: [flight.survey] tie_lines needs legs >= 2 and "
                            f"spacing_m > 0 (lines to cross), not {survey['tie_lines']!r}")
    scenario = values["scenario"]
    calibration = values["flight.calibration"]
    if len(calibration["headings_deg"]) > MAX_HEADINGS:
        raise ScenarioError(f"{source}: [flight.calibration] headings_deg must hold at most "
                            f"{MAX_HEADINGS} headings, not {len(calibration['headings_deg'])}")
    if any(not -360.0 <= h <= 360.0 for h in calibration["headings_deg"]):
        raise ScenarioError(f"{source}: [flight.calibration] headings_deg must lie within "
                            f"-360..360, not {_describe(calibration['headings_deg'])}")
    errors = values["errors"]
    if len(errors["mounting_deg"]) != 3:
        raise ScenarioError(f"{source}: [errors] mounting_deg must be three angles (roll, "
                            f"pitch, yaw), not {_describe(errors['mounting_deg'])}")
    talker = values["gps"]["talker"]
    if len(talker) != 2 or not talker.isascii() or not talker.isupper():
        raise ScenarioError(f"{source}: [gps] talker must be two upper-case letters, not "
                            f"{_describe(talker)}")
    flight = SimpleNamespace(**{name.split(".", 1)[1]: SimpleNamespace(**values[name])
                                for name in SCHEMA if name.startswith("flight.")})
    channels = {name: SimpleNamespace(**values[f"channels.{name}"]) for name in CHANNEL_NAMES}
    found = SurveyScenario(
        source=source, name=scenario["name"], seed=scenario["seed"], start=scenario["start"],
        clk_freq=scenario["clk_freq_hz"], max_frame=scenario["max_frame"],
        site=SimpleNamespace(**values["site"]), recording=SimpleNamespace(**values["recording"]),
        flight=flight, gps=SimpleNamespace(**values["gps"]), channels=channels,
        errors=SimpleNamespace(**errors), faults=faults,
        folder=None if folder is None else Path(folder), dipoles=dipoles,
        interference=SimpleNamespace(**inter), diurnal=SimpleNamespace(**values["diurnal"]))
    parts = found.flight_parts()
    total = sum(parts.values())
    if not total <= MAX_SCENARIO_S:
        where, longest = max(parts.items(), key=lambda item: item[1])
        raise ScenarioError(f"{source}: the run lasts {total:,.0f} s, more than a scenario may "
                            f"({MAX_SCENARIO_S:,.0f} s); the longest part: {where} "
                            f"({longest:,.0f} s)")
    return found


def loads_scenario(text, *, source="<scenario>", folder=None):
    """A :class:`SurveyScenario` from TOML text (``source`` names it in errors)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{source}: not valid TOML: {shorten(error, 200)}") from None
    except ValueError as error:         # an integer of more than 4300 digits
        what = ("an integer with too many digits" if "digits" in str(error)
                else shorten(error, 120))
        raise ScenarioError(f"{source}: not a usable TOML file: {what}") from None
    except RecursionError:
        raise ScenarioError(f"{source}: not a usable TOML file: arrays or tables nested too "
                            "deeply") from None
    return scenario_from_dict(data, source=source, folder=folder)


def default_scenario_path():
    """The built-in default scenario, ``sim/stimulus/default.toml``."""
    return Path(__file__).with_name("default.toml")


def preset_names():
    """The built-in scenarios (``sim/stimulus/*.toml``), by name."""
    return sorted(p.stem for p in Path(__file__).parent.glob("*.toml"))


def load_scenario(path=None):
    """Read and check a scenario file (None: the built-in default; a built-in scenario's
    name, e.g. ``"short"``, when no such file exists)."""
    if path is None:
        path = default_scenario_path()
    elif not Path(path).exists() and str(path) in preset_names():
        path = Path(__file__).with_name(f"{path}.toml")
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ScenarioError(f"{path}: cannot read the scenario ({error.strerror or error})") \
            from None
    except UnicodeDecodeError:
        raise ScenarioError(f"{path}: not a UTF-8 text file") from None
    return loads_scenario(text, source=path.name, folder=path.parent)
