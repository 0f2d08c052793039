"""Short synthetic sensor streams for demos and tests.

:func:`demo_streams` gives a few seconds of a flight's serial bytes per channel: the
magnetometer's ``$PMAG1`` at 20 Hz, the GPS receiver's NMEA at 1 Hz (GGA with a fix, ZDA,
VTG, and the distractors RMC, GSA, GSV), and the cesium magnetometer at 10 Hz, with a few
deliberate faults at seeded places. Its sentences come from :mod:`.sentences` as the
scenarios' do, a GPS second from the same :func:`~.sentences.gps_epoch`; what is the
demo's own is the straight, level track and the slowly varying fields. The faults:

- one ``$PMAG1`` with a bad checksum;
- one epoch without a fix (its GGA has quality 0: kept, but raises no flush event);
- a burst of non-printable bytes inside one cesium frame;
- one GGA or VTG cut short (no ``*hh``, no line end), so the next ``$`` drops it.

The same seed always gives the same bytes (``numpy.random.default_rng``).
"""

from __future__ import annotations

import datetime as _dt
import math

import numpy as np

from . import sentences

__all__ = ["demo_streams", "MAG_RATE_HZ", "GPS_RATE_HZ", "CESIUM_RATE_HZ"]

MAG_RATE_HZ = 20.0
GPS_RATE_HZ = 1.0
CESIUM_RATE_HZ = 10.0

#: Mean field at the magnetometer, nT (x, y, z).
MAG_BASE_NT = (20_000.0, -3_000.0, 45_000.0)
#: Slow variation (heading changes, gradients) per axis, nT, and its period.
MAG_VARIATION_NT = (60.0, 40.0, 25.0)
MAG_VARIATION_PERIOD_S = 30.0
MAG_NOISE_NT = 0.8

CESIUM_BASE_NT = 49_895.0
CESIUM_VARIATION_NT = 3.0
CESIUM_VARIATION_PERIOD_S = 45.0
CESIUM_NOISE_NT = 0.01
CESIUM_SIGNAL = 1250
CESIUM_SIGNAL_SPREAD = 20

FLIGHT_START = _dt.datetime(2024, 6, 1, 10, 0, 0, tzinfo=_dt.timezone.utc)
START_LAT_DEG = 47.3769
START_LON_DEG = 8.5417
GROUND_SPEED_MS = 15.0
COURSE_DEG = 90.0
ALTITUDE_M = 120.0
GEOID_M = 47.4
SATELLITES_USED = (2, 5, 12, 13, 15, 18, 20, 24, 25, 29)
_METRES_PER_DEGREE_LAT = 111_320.0
_MS_TO_KNOTS = 1.0 / 0.514444
_SNR_RANGE_DB = (25, 48)
_ELEVATION_RANGE_DEG = (5, 85)
_AZIMUTH_RANGE_DEG = (0, 359)

#: Non-printable bytes for noise bursts (not CR, LF: they would be a different fault).
_NOISE_BYTES = np.array(
    [b for b in range(0x100) if (b < 0x20 or b > 0x7E) and b not in (0x0D, 0x0A)], dtype=np.uint8
)
NOISE_BURST_LENGTH = (3, 6)
#: A cesium noise burst goes between these frame positions (inside the field digits).
_CESIUM_BURST_POSITIONS = (3, 14)
#: A truncated GPS sentence keeps at least its header and loses at least its ``*hh``.
_TRUNCATE_MIN_KEEP = 7
_TRUNCATE_MIN_LOSS = 5
_CHECKSUM_MAX = 0xFF


def _count(seconds: float, rate_hz: float) -> int:
    return max(1, math.floor(seconds * rate_hz + 0.5))


def _mag_stream(rng: np.random.Generator, seconds: float) -> bytes:
    count = _count(seconds, MAG_RATE_HZ)
    t = np.arange(count) / MAG_RATE_HZ
    phases = rng.uniform(0, 2 * math.pi, size=3)
    fields = (
        np.array(MAG_BASE_NT)[None, :]
        + np.array(MAG_VARIATION_NT)[None, :]
        * np.sin(2 * math.pi * t[:, None] / MAG_VARIATION_PERIOD_S + phases[None, :])
        + rng.normal(0.0, MAG_NOISE_NT, size=(count, 3))
    )
    first_seq = int(rng.integers(0, 100_000))
    bad = int(rng.integers(count))
    out = bytearray()
    for index, (x, y, z) in enumerate(fields):
        frame = sentences.pmag1(first_seq + index, float(x), float(y), float(z))
        if index == bad:
            body = frame[1 : frame.index(b"*")].decode("ascii")
            wrong = sentences.nmea_checksum(body) ^ int(rng.integers(1, _CHECKSUM_MAX + 1))
            frame = sentences.nmea_sentence(body, checksum=wrong)
        out += frame
    return bytes(out)


def _cesium_stream(rng: np.random.Generator, seconds: float) -> bytes:
    count = _count(seconds, CESIUM_RATE_HZ)
    t = np.arange(count) / CESIUM_RATE_HZ
    phase = rng.uniform(0, 2 * math.pi)
    field = (
        CESIUM_BASE_NT
        + CESIUM_VARIATION_NT * np.sin(2 * math.pi * t / CESIUM_VARIATION_PERIOD_S + phase)
        + rng.normal(0.0, CESIUM_NOISE_NT, size=count)
    )
    signal = CESIUM_SIGNAL + rng.integers(-CESIUM_SIGNAL_SPREAD, CESIUM_SIGNAL_SPREAD + 1, size=count)
    noisy = int(rng.integers(count))
    out = bytearray()
    for index in range(count):
        frame = sentences.cesium(float(field[index]), int(signal[index]))
        if index == noisy:
            at = int(rng.integers(*_CESIUM_BURST_POSITIONS))
            length = int(rng.integers(NOISE_BURST_LENGTH[0], NOISE_BURST_LENGTH[1] + 1))
            burst = bytes(rng.choice(_NOISE_BYTES, size=length).tolist())
            frame = frame[:at] + burst + frame[at:]
        out += frame
    return bytes(out)


def _gps_stream(rng: np.random.Generator, seconds: float) -> bytes:
    count = _count(seconds, GPS_RATE_HZ)
    no_fix = int(rng.integers(count))
    satellites = [
        (
            prn,
            int(rng.integers(_ELEVATION_RANGE_DEG[0], _ELEVATION_RANGE_DEG[1] + 1)),
            int(rng.integers(_AZIMUTH_RANGE_DEG[0], _AZIMUTH_RANGE_DEG[1] + 1)),
            int(rng.integers(_SNR_RANGE_DB[0], _SNR_RANGE_DB[1] + 1)),
        )
        for prn in SATELLITES_USED
    ]
    epochs: list[list[tuple[str, bytes]]] = []
    metres_per_degree_lon = _METRES_PER_DEGREE_LAT * math.cos(math.radians(START_LAT_DEG))
    east_ms = GROUND_SPEED_MS * math.sin(math.radians(COURSE_DEG))
    north_ms = GROUND_SPEED_MS * math.cos(math.radians(COURSE_DEG))
    knots = GROUND_SPEED_MS * _MS_TO_KNOTS
    for index in range(count):
        elapsed = index / GPS_RATE_HZ
        when = FLIGHT_START + _dt.timedelta(seconds=elapsed)
        lat = START_LAT_DEG + north_ms * elapsed / _METRES_PER_DEGREE_LAT
        lon = START_LON_DEG + east_ms * elapsed / metres_per_degree_lon
        epochs.append(sentences.gps_epoch(when, lat, lon, course_deg=COURSE_DEG,
                                          speed_knots=knots, sky=satellites,
                                          fix=index != no_fix, altitude_m=ALTITUDE_M,
                                          geoid_m=GEOID_M))
    # Cut one GGA (with a fix) or VTG short; both are always followed by another sentence.
    choices = [
        (epoch, position)
        for epoch in range(count)
        for position, (name, _) in enumerate(epochs[epoch])
        if name == "VTG" or (name == "GGA" and epoch != no_fix)
    ]
    epoch, position = choices[int(rng.integers(len(choices)))]
    name, frame = epochs[epoch][position]
    keep = int(rng.integers(_TRUNCATE_MIN_KEEP, len(frame) - _TRUNCATE_MIN_LOSS + 1))
    epochs[epoch][position] = (name, frame[:keep])
    return b"".join(frame for epoch in epochs for _, frame in epoch)


def demo_streams(seconds: float = 2.0, seed: int = 1) -> dict[str, bytes]:
    """Serial bytes per channel (``"mag"``, ``"gps"``, ``"cesium"``) of a short flight."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 < seconds < math.inf:
        raise ValueError(f"Duration must be a positive number of seconds, not {seconds!r}")
    # One independent generator per channel: a change to one channel leaves the others alone.
    children = np.random.SeedSequence(seed).spawn(3)
    mag_rng, gps_rng, cesium_rng = (np.random.default_rng(child) for child in children)
    return {
        "mag": _mag_stream(mag_rng, seconds),
        "gps": _gps_stream(gps_rng, seconds),
        "cesium": _cesium_stream(cesium_rng, seconds),
    }
