"""The scenario's truth (``truth.json``, version 1; schema in /work/spec12.md).

Frame counts are over the whole run from power-up, from the reference filter
(:mod:`maglog.sim.reference`) fed with what each channel's receiver reports
(:meth:`maglog.sim.stimulus.system.SystemScenario.received`: the bytes as sent, or, for
bytes sent at an off-nominal rate, :func:`maglog.sim.stimulus.uart_line.decode` of their line
at the gateware's nominal bit time). The recorded log is
:meth:`~maglog.sim.stimulus.system.SystemScenario.recorded_frames`.

Noise floor: the RMS residual ``|K b - c| - F_cs`` a perfect calibration leaves against the
cesium reference interpolated to the magnetometer's samples. With ``u_i`` the unit field
direction in the calibrated frame, ``K w`` the sensor noise seen through K, and the
reference's own noise interpolated linearly between samples (a weight λ uniform in [0, 1]
gives ``E[(1-λ)² + λ²] = 2/3``)::

    noise_floor² = mean_i |Kᵀ u_i|² (σ_w² + q_m²/12) + (2/3) σ_cs² + q_cs²/12

with σ_w the magnetometer's white noise per axis, q_m = 0.1 nT its ``$PMAG1`` resolution,
σ_cs the cesium noise and q_cs = 0.001 nT its resolution.
"""

from __future__ import annotations

import hashlib
import numpy as np

from ..reference import COUNTER_NAMES, Kind, reference_filter
from . import errors as _errors
from .config import CHANNEL_NAMES

__all__ = ["make_truth", "channel_counts", "noise_floor", "TRUTH_VERSION",
           "PMAG_RESOLUTION_NT", "CESIUM_RESOLUTION_NT"]

TRUTH_VERSION = 1
PMAG_RESOLUTION_NT = 0.1
CESIUM_RESOLUTION_NT = 0.001
_KIND_NAMES = ("pmag", "nmea", "cesium")


def channel_counts(system, channel):
    """The reference filter's counters over a channel's whole run, with ``flushes`` and
    ``sent_bytes``."""
    result = system.received_filter(channel)
    counts = {"sent_bytes": len(system.channel_bytes(channel))}
    counts.update({name: result.counters[name] for name in COUNTER_NAMES})
    counts["flushes"] = len(result.flushes)
    return counts


def noise_floor(k, q, body, noise, cesium_noise):
    """The residual RMS a perfect calibration leaves (module docstring), nT; ``q`` the
    rotation the scalar model cannot see (``K b - c = qᵀ B_body``)."""
    u = body @ q / np.linalg.norm(body, axis=1, keepdims=True)
    gain = float(np.mean(np.sum((u @ k) ** 2, axis=1)))       # |K^T u|^2
    return float(np.sqrt(gain * (noise ** 2 + PMAG_RESOLUTION_NT ** 2 / 12)
                         + 2 / 3 * cesium_noise ** 2 + CESIUM_RESOLUTION_NT ** 2 / 12))


def _matrix(m):
    return [[float(x) for x in row] for row in np.asarray(m)]


def make_truth(stim, fault_records, withheld, errors):
    scenario, system, flight = stim.scenario, stim.system, stim.flight
    frames = {name: channel_counts(system, k) for k, name in enumerate(CHANNEL_NAMES)}
    recorded = system.recorded_frames()
    p0, p1 = system.presses[0], system.presses[1]
    per_channel = {name: sum(1 for t, _ in system.kept_frames(k) if p0 <= t < p1)
                   for k, name in enumerate(CHANNEL_NAMES)}
    log = b"".join(recorded)

    faults = []
    for record in fault_records:
        record = dict(record)
        index = record.pop("index")
        if record["kind"] == "baud_error":
            k = CHANNEL_NAMES.index(record["channel"])
            # The same channel with this fault's bytes received as sent.
            events = []
            for i, burst in enumerate(system.bursts):
                if burst.channel == k:
                    events.append((burst.start, [(x, False) for x in burst.data]
                                   if stim.placed[i] == index else system.burst_events(burst)))
            events = [e for _, part in sorted(events, key=lambda e: e[0]) for e in part]
            without = reference_filter(Kind(system.channels[k].kind.value), events,
                                       max_frame=system.max_frame).counters
            with_fault = channel_counts(system, k)
            record["count"] = sum(1 for i, b in enumerate(system.bursts)
                                  if stim.placed[i] == index)
            record["expect"] = {"cause": "uart_error",
                                "frames": with_fault["uart_error"] - without["uart_error"]}
            record["kept_delta"] = with_fault["kept"] - without["kept"]
        faults.append(record)

    k, c, q = errors.truth_with_rotation()
    a, b = _errors.forward(errors)
    cesium = scenario.channels["cesium"]
    mag = scenario.channels["mag"]
    return {
        "version": TRUTH_VERSION,
        "scenario": scenario.name,
        "seed": scenario.seed,
        "clk_freq": system.clk_freq,
        "timestamp": scenario.start.isoformat(),
        "presses_s": [float(p) for p in system.presses[:2]],
        "until_s": float(system.until),
        "channels": [{"name": name, "kind": _KIND_NAMES[i], "baud": ch.baud,
                      "baud_actual": _actual_baud(system, i)}
                     for i, (name, ch) in enumerate(zip(CHANNEL_NAMES, system.channels))],
        "frames": frames,
        "recorded": {"frames": len(recorded), "per_channel": per_channel,
                     "sha256": hashlib.sha256(log).hexdigest(), "bytes": len(log)},
        "withheld": withheld,
        "faults": faults,
        "errors": {"preset": scenario.errors.preset, "K": _matrix(k),
                   "c": [float(x) for x in c], "A": _matrix(a), "b": [float(x) for x in b],
                   "noise_nT": float(errors.noise),
                   "mounting_deg": [float(x) for x in errors.mounting]},
        "reference": {"cesium_noise_nT": cesium.noise_nT,
                      "igrf_total_nT_mean": float(np.mean(flight.total))},
        "noise_floor_nT": noise_floor(k, q, flight.b_earth, errors.noise, cesium.noise_nT),
        "flight": {"phases": [{"name": n, "start_s": round(float(s), 6),
                               "end_s": round(float(min(e, system.until)), 6)}
                              for n, s, e in stim.track.phases if s < system.until],
                   "samples": int(flight.t.size), "mag_rate_hz": mag.rate_hz,
                   "cesium_rate_hz": cesium.rate_hz, "attitude_csv": "attitude.csv"},
    }


def _actual_baud(system, channel):
    """The channel's line rate: the nominal one, or that of its off-nominal bytes (the most
    common if several)."""
    nominal = system.channels[channel].baud
    sizes = {}
    for burst in system.channel_bursts(channel):
        rate = burst.baud or nominal
        sizes[rate] = sizes.get(rate, 0) + len(burst.data)
    return float(max(sizes, key=sizes.get))
