"""From a :class:`~maglog.sim.stimulus.config.SurveyScenario` to the logger's inputs and the
truth: the sensor frames per channel, the button presses, the faults, their places on the
lines (:class:`~maglog.sim.stimulus.system.Timeline`) and the :class:`Stimulus` that holds them.

Order of work (each step seeded from the scenario's seed, one generator per purpose):

1. the flight (:mod:`.flight`) and the error model (:mod:`.errors`);
2. the frames each instrument sends, at their request times: ``$PMAG1`` per magnetometer
   sample, a cesium line at its rate, a GPS group once a second (RMC, VTG, GGA, GSA, GSV,
   ZDA; GGA fix quality 0 before ``[gps] fix_s``); a capture replaces a channel's frames;
   a GPS outage removes the groups of its interval;
3. the presses: each moved forward (1 ms steps) until no GPS group is on the line within
   ``quiet_before_s`` before and ``quiet_after_s`` after it; magnetometer and cesium frames
   that would be on their lines in that window are withheld (not sent), so that the log's
   content is the frames that end between the presses whatever the firmware's reaction time;
4. the frame faults (noise bursts, dropped bytes, bad checksums) on frames the filter would
   otherwise keep, chosen with the fault generator among those of the interval;
5. the frames placed on their lines in time order (:class:`~maglog.sim.stimulus.system.Timeline`:
   no two kept frames of different channels end within MIN_END_GAP_S); a frame with bytes
   inside a baud-error window is split there, the bytes inside sent at the line's actual
   rate, with two nominal bit times of idle after them;
6. the truth (:mod:`.truth`); with survey features, ``truth["survey"]``
   (:func:`.geophysics.survey_truth`) and the base station's record (``base.csv``, its
   noise from a generator of its own: the four above draw as without it).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...hw.frame_filter import ChannelKind
from ...hw.frontend import ChannelConfig, divisor_for
from ...hw.arch.units import hertz
from . import sentences
from .captures import load_capture, shared_data_dir
from .system import UART_FRAME_BITS, SystemScenario, Timeline
from . import errors as _errors
from .config import CHANNEL_NAMES, shorten
from .flight import make_flight, survey_seconds

__all__ = ["Stimulus", "Item", "build", "NOISE_BYTES", "KEEPABLE"]

_KINDS = {"mag": ChannelKind.PMAG, "gps": ChannelKind.NMEA, "cesium": ChannelKind.CESIUM}
_MS_TO_KNOTS = 3600.0 / 1852.0
#: Bytes of a noise burst: everything outside printable ASCII but CR and LF (which would
#: end a frame rather than spoil it).
NOISE_BYTES = bytes(b for b in range(256) if (b < 0x20 or b > 0x7E) and b not in (0x0D, 0x0A))
#: Frame types the filter keeps when intact.
KEEPABLE = frozenset({"pmag", "cesium", "GGA", "ZDA", "VTG"})
#: Slack around a frame's nominal line time when testing it against a press's quiet window
#: (Timeline may move a frame later by a few MIN_END_GAP_S steps).
_QUIET_SLACK_S = 0.02
#: How far a press may move to find a quiet GPS line.
_PRESS_SEARCH_S = 5.0
_PRESS_STEP_S = 0.001
#: Idle after bytes sent at an off-nominal rate, in nominal bit times.
_IDLE_AFTER_OFF_BITS = 2
#: The seconds after the stop press the flight arrays reach beyond the run's end.
_HORIZON_MARGIN_S = 3.0 + _PRESS_SEARCH_S
#: A baud error up to this size leaves every character intact (centre sampling at 16x).
SAFE_BAUD_ERROR = 0.02
#: Second entropy word of the survey's own generators (beside the seed).
_SURVEY_ENTROPY = 0x5355_5256


@dataclass
class Item:
    """A frame an instrument sends: when it asks for the line, on which channel, the bytes,
    its type (``pmag``, ``cesium``, ``GGA``, ..., ``capture``) and the faults it carries."""
    t: float
    channel: int
    data: bytes
    type: str
    seq: int = 0
    faults: list = field(default_factory=list)

    def duration(self, baud):
        return len(self.data) * UART_FRAME_BITS / baud


@dataclass
class Stimulus:
    """What a scenario gives the system runner and the reports (see /work/spec12.md)."""
    scenario: object
    system: SystemScenario
    flight: object
    truth: dict
    card: dict
    track: object = None
    items: list = field(default_factory=list)      # the frames as sent (after faults)
    placed: list = field(default_factory=list)     # per burst: index of its baud fault or None
    files: dict = field(default_factory=dict)      # more files beside truth.json: name -> bytes

    def write_truth(self, folder):
        """Write ``truth.json`` and ``attitude.csv`` (and ``base.csv`` when the scenario has
        a base station) into ``folder`` (created if needed); returns the truth file's path."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / self.truth["flight"]["attitude_csv"]).write_bytes(self.flight.attitude_csv())
        for name, data in self.files.items():
            (folder / name).write_bytes(data)
        path = folder / "truth.json"
        path.write_text(json.dumps(self.truth, indent=1) + "\n", encoding="utf-8")
        return path


# --- frames --------------------------------------------------------------------------------

def _capture_bytes(scenario, name):
    text = scenario.channels[name].capture
    where = f"[channels.{name}] capture"
    if text.startswith("shared:"):
        data = shared_data_dir()
        if data is None:
            raise scenario.error(where, "needs the shared data folder, absent "
                                        f"({shorten(repr(text))})")
        path = data / text.removeprefix("shared:")
    else:
        path = Path(text)
        if not path.is_absolute() and scenario.folder is not None:
            path = scenario.folder / path
    try:
        if not path.is_file():
            raise scenario.error(where, f"must name a readable file, not {shorten(repr(text))}")
        data = load_capture(path)
    except OSError as error:             # a name too long, a file that cannot be read
        raise scenario.error(where, f"must name a readable file, not {shorten(repr(text))} "
                                    f"({error.strerror or type(error).__name__})") from None
    lines = [line for line in data.splitlines(keepends=True) if line]
    if not lines:
        raise scenario.error(where, f"holds no data after its header ({shorten(repr(text))})")
    return lines


def _capture_items(scenario, name, channel, until):
    """A capture's lines on ``channel`` with the channel's ``timing``."""
    cfg = scenario.channels[name]
    lines = _capture_bytes(scenario, name)
    baud = cfg.baud
    items = []
    if cfg.timing == "stream":
        t = getattr(cfg, "first_s", scenario.gps.first_s)
        for line in lines:
            items.append(Item(t, channel, line, "capture"))
            t += len(line) * UART_FRAME_BITS / baud
    elif cfg.timing == "rate":
        if not hasattr(cfg, "rate_hz"):
            raise scenario.error(f"[channels.{name}] timing", "must be groups or stream for "
                                 "the GPS (it has no rate_hz), not 'rate'")
        for k, line in enumerate(lines):
            items.append(Item(cfg.first_s + k / cfg.rate_hz, channel, line, "capture"))
    else:                                           # groups: a new one at each GGA (or RMC)
        anchor = next((tag for tag in (b"GGA,", b"RMC,")
                       if any(line[3:7] == tag and line[:1] == b"$" for line in lines)), None)
        if anchor is None:
            raise scenario.error(f"[channels.{name}] timing", "'groups' needs GGA or RMC "
                                 "sentences in the capture; use 'stream' or 'rate'")
        second = -1
        for line in lines:
            if line[:1] == b"$" and line[3:7] == anchor or second < 0:
                second += 1
            items.append(Item(scenario.gps.first_s + scenario.gps.offset_s + second, channel,
                              line, "capture", seq=second))
    return [item for item in items if item.t < until]


def _gps_items(scenario, track, rng, horizon, outages):
    gps = scenario.gps
    sky = [(prn, int(rng.integers(5, 86)), int(rng.integers(0, 360)), int(rng.integers(25, 49)))
           for prn in (2, 5, 12, 13, 15, 18, 20, 24, 25, 29, 31, 10)[:gps.satellites]]
    items = []
    n = 0
    while gps.first_s + n + gps.offset_s < horizon:
        epoch = gps.first_s + n
        t = epoch + gps.offset_s
        n += 1
        if any(start <= t < end for start, end in outages):
            continue
        when = scenario.start + _dt.timedelta(seconds=epoch)
        lat, lon, alt = (float(v) for v in track.position(epoch))
        vn, ve = float(track.at(epoch, track.v_north)), float(track.at(epoch, track.v_east))
        course = math.degrees(math.atan2(ve, vn)) % 360
        knots = math.hypot(vn, ve) * _MS_TO_KNOTS
        group = sentences.gps_epoch(when, lat, lon, course_deg=course, speed_knots=knots,
                                    sky=sky, fix=epoch >= gps.fix_s, hdop=gps.hdop,
                                    altitude_m=alt, geoid_m=gps.geoid_m,
                                    distractors=gps.distractors, talker=gps.talker)
        items += [Item(t, 1, data, kind, seq=n - 1) for kind, data in group]
    return items


def _field_causes(scenario, track, t, extra=None):
    """What adds to the Earth field at the sensor at time ``t``: {the scenario's key that
    sets it: nT}, largest first (``extra``: more causes measured by the caller)."""
    causes = dict(extra or {})
    geo = track.geo
    if geo is not None:
        north, east, up = (float(np.interp(t, track.t, v))
                           for v in (track.north, track.east, track.up))
        from .geophysics import anomaly_vector, diurnal_nT
        for index, dipole in enumerate(geo.survey["dipoles"], 1):
            b = anomaly_vector([dipole], north, east, up)
            causes[f"[[anomaly.dipole]] #{index} (moment_Am2 "
                   f"{dipole['moment_Am2']:g} A·m², {up + dipole['depth_m']:.3g} m below the "
                   "sensor)"] = float(np.linalg.norm(b))
        causes["[interference] vector_eddy_s"] = float(np.linalg.norm(geo.vector_eddy([t])))
        causes["[diurnal]"] = abs(float(diurnal_nT(geo.survey, t)))
    return sorted(causes.items(), key=lambda item: -item[1])


def _check_sensor_range(scenario, track, what, t, value, limit, extra):
    """A :class:`ScenarioError` naming the largest cause when ``value`` (a reading at
    ``t``) does not fit the sensor's format; ``limit`` says the format's range."""
    causes = _field_causes(scenario, track, t, extra)
    cause = ("; the largest cause: " + f"{causes[0][0]} ({causes[0][1]:.3g} nT)"
             if causes and causes[0][1] > 0 else "")
    from .config import ScenarioError
    return ScenarioError(f"{scenario.source}: the {what} would read {value:.6g} nT at t = "
                         f"{t:.2f} s, outside its format's {limit}{cause}")


def _mag_in_range(scenario, flight, track, sensed):
    """Every magnetometer sample fits ``$PMAG1``'s ±XXXXX.X, or a ScenarioError."""
    b = np.asarray(flight.b_meas, float)
    bad = ~(np.abs(b) < sentences.PMAG_FIELD_LIMIT_NT).all(axis=1)
    if not bad.any():
        return
    i = int(np.argmax(bad))
    axis = int(np.argmax(~(np.abs(b[i]) < sentences.PMAG_FIELD_LIMIT_NT)))
    err = scenario.errors
    extra = {f"[errors] preset {err.preset!r} and noise_nT {err.noise_nT:g} (the "
             "magnetometer's own errors)": float(np.linalg.norm(b[i] - sensed[i]))}
    raise _check_sensor_range(scenario, track, f"magnetometer's {'xyz'[axis]} axis",
                              float(flight.t[i]), float(b[i, axis]),
                              f"±{sentences.PMAG_FIELD_LIMIT_NT} nT (PMAG1)", extra)


def _mag_items(flight):
    return [Item(float(t), 0, sentences.pmag1(k % 100_000, *map(float, b)), "pmag", seq=k)
            for k, (t, b) in enumerate(zip(flight.t, flight.b_meas))]


def _cesium_items(scenario, track, rng, horizon):
    cfg = scenario.channels["cesium"]
    t = np.arange(cfg.first_s, horizon, 1.0 / cfg.rate_hz)
    clean = track.total(t) if track.geo is None else track.geo.cesium(t)
    field_nt = clean + rng.normal(scale=cfg.noise_nT, size=t.size)
    limit = sentences._CESIUM_FIELD_LIMIT_NT
    bad = ~((field_nt >= 0) & (field_nt < limit - 0.001))
    if bad.any():
        i = int(np.argmax(bad))
        extra = {f"[channels.cesium] noise_nT {cfg.noise_nT:g}": abs(field_nt[i] - clean[i])}
        if track.geo is not None:
            extra["[interference] tl_coefficients, heading_error_nT"] = abs(
                float(clean[i]) - float(track.geo.body(t[i:i + 1], *(
                    np.interp(t[i:i + 1], track.t, track.attitude[:, k])
                    for k in range(3)))[1][0]))
        raise _check_sensor_range(scenario, track, "cesium", float(t[i]), float(field_nt[i]),
                                  f"0..{limit:g} nT", extra)
    signal = np.clip(cfg.signal + rng.integers(-20, 21, size=t.size), 0, 9999)
    return [Item(float(tk), 2, sentences.cesium(float(f), int(s)), "cesium", seq=k)
            for k, (tk, f, s) in enumerate(zip(t, field_nt, signal))]


# --- presses -------------------------------------------------------------------------------

def _place_press(requested, busy, before, after):
    """The first instant from ``requested`` (1 ms steps) whose window is free of ``busy``
    intervals, or None."""
    steps = int(_PRESS_SEARCH_S / _PRESS_STEP_S)
    for k in range(steps + 1):
        p = round(requested + k * _PRESS_STEP_S, 6)
        if not any(s < p + after and p - before < e for s, e in busy):
            return p
    return None


def _gps_busy(items, baud):
    """The GPS line's busy intervals: each group from its first frame's request to the end
    of its bytes sent back to back (plus slack)."""
    groups = {}
    for item in items:
        start, size = groups.get(item.seq, (item.t, 0))
        groups[item.seq] = (min(start, item.t), size + len(item.data))
    return [(s, s + size * UART_FRAME_BITS / baud + _QUIET_SLACK_S)
            for s, size in groups.values()]


# --- faults on frames ----------------------------------------------------------------------

def _choose(scenario, fault, candidates, rng):
    if len(candidates) < fault.params["count"]:
        raise scenario.error(fault.where, f"count must be at most the {len(candidates)} "
                             f"{fault.channel} frames the filter would keep in "
                             f"{fault.start_s:g}-{fault.end_s:g} s, not "
                             f"{fault.params['count']}")
    picks = rng.choice(len(candidates), size=fault.params["count"], replace=False)
    return [candidates[i] for i in sorted(picks)]


def _header_end(data):
    """Index of the first byte after the sentence's header (``$TTSSS,`` or ``$PMAG1,``)."""
    return data.index(b",") + 1


def _apply_frame_fault(fault, item, rng):
    data = item.data
    if fault.kind == "noise_burst":
        # Inside the frame, after its `$`: non-printable bytes drop it (bad_byte).
        star = data.find(b"*")
        last = (star if star > 0 else len(data) - 2)
        at = int(rng.integers(2, last))
        burst = bytes(rng.choice(np.frombuffer(NOISE_BYTES, np.uint8),
                                 size=fault.params["length"]).tolist())
        item.data = data[:at] + burst + data[at:]
        return "bad_byte"
    if fault.kind == "dropped_bytes":
        if item.type == "cesium":
            at = int(rng.integers(2, 15))            # a digit, `.` or `,`: the form breaks
            item.data = data[:at] + data[at + 1:]
            return "not_whitelisted"
        at = int(rng.integers(_header_end(data), data.index(b"*")))
        item.data = data[:at] + data[at + 1:]       # the body changes: its checksum fails
        return "checksum"
    # bad_checksum
    star = data.index(b"*")
    body = data[1:star]
    wrong = sentences.nmea_checksum(body) ^ int(rng.integers(1, 256))
    item.data = sentences.nmea_sentence(body.decode("ascii"), checksum=wrong,
                                        eol=data[star + 3:])
    return "checksum"


# --- placing -------------------------------------------------------------------------------

def _windows(faults, channel_name, nominal):
    return [(f.start_s, f.end_s, nominal * (1 + f.params["error"]), i)
            for i, f in enumerate(faults)
            if f.kind == "baud_error" and f.channel == channel_name]


def _pieces(start, data, nominal, windows):
    """Split a frame sent from ``start`` at the nominal rate where its bytes enter and leave
    baud-error windows: ``[(data, baud or None, fault index or None)]``."""
    per_byte = UART_FRAME_BITS / nominal
    last = start + (len(data) - 1) * per_byte             # the last byte's start
    touching = [w for w in windows if w[0] <= last and start < w[1]]
    if not touching:
        return [(data, None, None)]
    ws, we, baud, fault = touching[0]
    if len(touching) == 1 and ws <= start and last < we:
        return [(data, baud, fault)]
    pieces = []
    for i in range(len(data)):
        t = start + i * per_byte
        hit = next(((baud, f) for ws, we, baud, f in windows if ws <= t < we), (None, None))
        if pieces and pieces[-1][1:] == hit:
            pieces[-1][0].append(data[i])
        else:
            pieces.append(([data[i]], *hit))
    return [(bytes(p), baud, f) for p, baud, f in pieces]


def _place(channels, items, faults):
    line = Timeline(channels)
    placed = []
    not_before = [0.0] * len(channels)
    windows = {k: _windows(faults, CHANNEL_NAMES[k], channels[k].baud)
               for k in range(len(channels))}
    for item in sorted(items, key=lambda it: (it.t, it.channel, it.seq)):
        k = item.channel
        nominal = channels[k].baud
        start = max(item.t, not_before[k])
        for data, baud, fault in _pieces(start, item.data, nominal, windows[k]):
            end = line.add(k, start, data, baud)
            placed.append(fault)
            start = end
            if baud is not None:
                start += _IDLE_AFTER_OFF_BITS / nominal
        not_before[k] = start
    return line.bursts, placed


# --- the whole build -----------------------------------------------------------------------

def build(scenario):
    from .truth import make_truth
    # One generator per purpose: a change to one leaves the others' draws alone.
    rng_flight, rng_cesium, rng_faults, rng_sky = (
        np.random.default_rng(s) for s in np.random.SeedSequence(scenario.seed).spawn(4))
    err = scenario.errors
    errors = _errors.preset(err.preset, noise=err.noise_nT, mounting=err.mounting_deg)
    rec = scenario.recording
    f = scenario.flight
    if rec.start_s >= f.ground.seconds:
        raise scenario.error("[recording] start_s", f"must be before take-off at "
                             f"{f.ground.seconds:g} s ([flight.ground] seconds), not "
                             f"{rec.start_s!r}")
    channels = tuple(ChannelConfig(_KINDS[name], scenario.channels[name].baud)
                     for name in CHANNEL_NAMES)
    for name, channel in zip(CHANNEL_NAMES, channels):
        try:
            divisor_for(scenario.clk_freq, channel.baud)
        except ValueError as error:
            raise scenario.error(f"[channels.{name}] baud", f"must be reachable from the "
                                 f"{hertz(scenario.clk_freq)} clock: {error}") from None
    # A first pass gives the flight's length; the arrays reach past the stop press.
    survey = f.survey
    leg_s = 1.875 * survey.leg_length_m / survey.speed_m_s
    flight_s = (f.ground.seconds + f.takeoff.seconds
                + len(f.calibration.headings_deg) * f.calibration.seconds
                + (survey.turn_s * survey.legs + leg_s * survey.legs if survey.legs else 0.0)
                + f.landing.seconds)
    if survey.legs and survey.tie_lines:
        flight_s += survey_seconds(survey)[1]
    horizon = flight_s + rec.stop_after_landing_s + rec.end_after_stop_s + _HORIZON_MARGIN_S
    flight, track = make_flight(scenario, errors, rng_flight, horizon)
    _mag_in_range(scenario, flight, track, flight.b_earth if track.geo is None else
                  flight.b_earth + track.geo.vector_eddy(flight.t))

    outages = [(x.start_s, x.end_s) for x in scenario.faults if x.kind == "gps_outage"]
    items = {}
    items["gps"] = (_capture_items(scenario, "gps", 1, horizon)
                    if scenario.channels["gps"].capture
                    else _gps_items(scenario, track, rng_sky, horizon, outages))
    if scenario.channels["gps"].capture and outages:
        items["gps"] = [it for it in items["gps"]
                        if not any(s <= it.t < e for s, e in outages)]
    items["mag"] = (_capture_items(scenario, "mag", 0, horizon)
                    if scenario.channels["mag"].capture else _mag_items(flight))
    items["cesium"] = (_capture_items(scenario, "cesium", 2, horizon)
                       if scenario.channels["cesium"].capture
                       else _cesium_items(scenario, track, rng_cesium, horizon))

    # Presses, in GPS-quiet moments; the other lines' frames in their windows withheld.
    gps_baud = channels[1].baud
    busy = (_gps_busy(items["gps"], gps_baud) if scenario.channels["gps"].timing != "stream"
            or not scenario.channels["gps"].capture else [])
    presses = []
    for what, requested in (("start_s", rec.start_s),
                            ("stop_after_landing_s", track.flight_end + rec.stop_after_landing_s)):
        press = _place_press(requested, busy, rec.quiet_before_s, rec.quiet_after_s)
        if press is None:
            raise scenario.error(f"[recording] {what}", f"leaves no quiet GPS line within "
                                 f"{_PRESS_SEARCH_S:g} s of {requested:g} s")
        presses.append(press)
    until = presses[1] + rec.end_after_stop_s
    withheld = {name: 0 for name in CHANNEL_NAMES}
    for k, name in enumerate(CHANNEL_NAMES):
        baud = channels[k].baud
        kept = []
        for item in items[name]:
            a, b = item.t - _QUIET_SLACK_S, item.t + item.duration(baud) + _QUIET_SLACK_S
            if b > until - _QUIET_SLACK_S:
                continue                            # would not end before the run does
            if any(p - rec.quiet_before_s < b and a < p + rec.quiet_after_s for p in presses):
                withheld[name] += 1
                continue
            kept.append(item)
        items[name] = kept

    # Frame faults, on frames the filter would otherwise keep.
    big_windows = [(x.channel, x.start_s, x.end_s) for x in scenario.faults
                   if x.kind == "baud_error" and abs(x.params["error"]) > SAFE_BAUD_ERROR]
    fault_records = []
    for index, fault in enumerate(scenario.faults):
        record = {"kind": fault.kind, "channel": fault.channel, "start_s": fault.start_s,
                  "end_s": fault.end_s, "count": 1, "expect": None, "index": index}
        if fault.kind in ("noise_burst", "dropped_bytes", "bad_checksum"):
            baud = channels[CHANNEL_NAMES.index(fault.channel)].baud
            candidates = [it for it in items[fault.channel]
                          if it.type in KEEPABLE and not it.faults
                          and fault.start_s <= it.t < fault.end_s
                          and not any(ch == fault.channel and it.t - 1 < we
                                      and ws < it.t + it.duration(baud) + 1
                                      for ch, ws, we in big_windows)]
            chosen = _choose(scenario, fault, candidates, rng_faults)
            causes = {_apply_frame_fault(fault, it, rng_faults) for it in chosen}
            for it in chosen:
                it.faults.append(index)
            record["count"] = len(chosen)
            record["expect"] = {"cause": causes.pop(), "frames": len(chosen)}
            record["kept_delta"] = -len(chosen)
        elif fault.kind == "card_busy":
            record["busy_s"] = fault.params["busy_s"]
        elif fault.kind == "baud_error":
            record["error"] = fault.params["error"]
        elif fault.kind == "gps_outage":
            gps = scenario.gps
            epochs = gps.first_s + gps.offset_s + np.arange(int(horizon) + 1)
            record["count"] = int(np.count_nonzero((epochs >= fault.start_s)
                                                   & (epochs < fault.end_s)
                                                   & (epochs < until)))
            record["kept_delta"] = None
        fault_records.append(record)

    all_items = [it for name in CHANNEL_NAMES for it in items[name]]
    bursts, placed = _place(channels, all_items, scenario.faults)
    system = SystemScenario(channels=channels, clk_freq=scenario.clk_freq, bursts=bursts,
                            presses=presses, until=until, hold=rec.hold_s,
                            debounce_s=rec.debounce_s, max_frame=scenario.max_frame,
                            timestamp=scenario.start)
    _check_quiet(scenario, system)
    card = {"busy_spikes": [[x.start_s, x.end_s, x.params["busy_s"]]
                            for x in scenario.faults if x.kind == "card_busy"]}
    keep = flight.t < until
    flight = replace(flight, **{name: getattr(flight, name)[keep]
                                for name in ("t", "roll", "pitch", "heading", "b_earth",
                                             "b_meas", "total", "north_m", "east_m", "course",
                                             "speed")})
    stim = Stimulus(scenario=scenario, system=system, flight=flight, truth={}, card=card,
                    track=track, items=all_items, placed=placed)
    stim.truth = make_truth(stim, fault_records, withheld, errors)
    if scenario.survey_on:
        _add_survey(stim)
    return stim


def _add_survey(stim):
    """``truth["survey"]`` and, with a base station, ``base.csv`` (its own generator)."""
    from .geophysics import base_station_csv, survey_truth
    scenario, track = stim.scenario, stim.track
    lines = [line for line in track.lines if line[2] < stim.system.until]
    survey = (dict(track.geo.survey, lines=survey_truth(scenario, lines)["lines"])
              if track.geo is not None else survey_truth(scenario, lines))
    stim.truth["survey"] = survey
    if scenario.diurnal.base_station:
        # Not from the scenario's four generators: their draws stay as without the survey.
        rng_base, = (np.random.default_rng(s) for s in
                     np.random.SeedSequence([scenario.seed, _SURVEY_ENTROPY]).spawn(1))
        stim.files[survey["diurnal"]["base_station"]] = base_station_csv(
            survey, scenario.start, stim.system.until, rng_base)


def _check_quiet(scenario, system):
    rec = scenario.recording
    for press in system.presses:
        for k, channel in enumerate(system.channels):
            for burst in system.channel_bursts(k):
                if (burst.start < press + rec.quiet_after_s
                        and press - rec.quiet_before_s < burst.end(channel.baud)):
                    raise scenario.error("[recording]", f"channel {CHANNEL_NAMES[k]} is busy "
                                         f"at {burst.start:.4f} s, within the quiet window "
                                         f"of the press at {press:g} s")
