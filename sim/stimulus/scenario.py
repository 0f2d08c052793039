"""Synthetic survey flights for calibration: attitude, Earth field, the magnetometer error
model, and the log the logger would write.

Error model (DESIGN.md): ``b = C_NO C_SF (I + C_SI) (R_m^T B_e + B_HI) + b0 + w`` with the
body field ``B_e`` from IGRF (ppigrf) rotated by the attitude (x forward, y right, z down)
and ``R_m`` the sensor's mounting rotation in the airframe (identity by default).

Two flight patterns: :func:`make_flight`, a calibration manoeuvre at one place (turns with
roll and pitch swings, or tumbling over the full sphere), and :func:`make_survey`, that
manoeuvre followed by straight, level survey lines flown back and forth in a wind, with a
moving GPS position and VTG course over ground.
"""

import datetime
from dataclasses import dataclass, field

import numpy as np

from . import sentences


__all__ = ["ErrorModel", "DEFAULT_ERRORS", "Flight", "make_flight", "make_survey",
           "COVERAGES"]

#: Attitude coverage: (roll and pitch half-range in degrees, or None for the full sphere).
COVERAGES = {"full": None, "uav": 30.0, "planar": 5.0}

_METRES_PER_DEGREE = 111_320.0          # of latitude (spherical Earth: enough for a survey)
_KNOT_M_S = 1852.0 / 3600.0
_GRAVITY = 9.81


@dataclass(frozen=True)
class ErrorModel:
    """Non-orthogonality (lower triangular, small), scale factors, soft iron (symmetric),
    hard iron (nT, sensor frame), bias (nT), white noise (nT, per axis), and the sensor's
    mounting in the airframe as roll, pitch and yaw (degrees; sensor to body).

    These are this project's own representative values, not the paper's Table 1 (whose
    figures are not reproduced here); pass your own to model a particular installation."""
    non_orthogonality: tuple = ((1.0, 0.0, 0.0), (0.012, 1.0, 0.0), (-0.008, 0.015, 1.0))
    scale: tuple = (1.04, 0.97, 1.02)
    soft_iron: tuple = ((0.02, 0.01, -0.005), (0.01, -0.015, 0.008), (-0.005, 0.008, 0.01))
    hard_iron: tuple = (250.0, -180.0, 320.0)
    bias: tuple = (40.0, -25.0, 15.0)
    noise: float = 5.0
    mounting: tuple = (0.0, 0.0, 0.0)

    def matrix(self):
        """The sensor's error matrix M (sensor frame): ``b = M (B_s + h) + b0``."""
        return (np.array(self.non_orthogonality) @ np.diag(self.scale)
                @ (np.eye(3) + np.array(self.soft_iron)))

    def mounting_rotation(self):
        """R_m, sensor frame to body frame: ``B_body = R_m B_s``."""
        roll, pitch, yaw = np.radians(self.mounting)
        return _rotation(np.array([yaw]), np.array([pitch]), np.array([roll]))[0]

    def apply(self, b_earth, rng):
        m = self.matrix()
        sensor = b_earth @ self.mounting_rotation()             # R_m^T B per row
        clean = (sensor + np.array(self.hard_iron)) @ m.T + np.array(self.bias)
        return clean + rng.normal(scale=self.noise, size=clean.shape)

    def truth(self):
        """The scalar model's K (upper triangular, positive diagonal) and c, and the
        rotation ``Q`` that the scalar model cannot see: ``K b - c = Q^T B_body``."""
        k, c, _ = self.truth_with_rotation()
        return k, c

    def truth_with_rotation(self):
        m = self.matrix()
        mount = self.mounting_rotation()
        # b = M (R^T B + h) + b0  =>  B = R M^-1 b - R (h + M^-1 b0) = Q K b - o
        q, r = np.linalg.qr(mount @ np.linalg.inv(m))
        signs = np.sign(np.diag(r))
        k = r * signs[:, None]
        q = q * signs
        offset = mount @ (np.array(self.hard_iron) + np.linalg.inv(m) @ np.array(self.bias))
        return k, q.T @ offset, q


DEFAULT_ERRORS = ErrorModel()


@dataclass
class Flight:
    t: np.ndarray               # seconds from the start (magnetometer samples)
    roll: np.ndarray            # radians
    pitch: np.ndarray
    heading: np.ndarray
    b_earth: np.ndarray         # body-frame Earth field, nT
    b_meas: np.ndarray          # magnetometer output, nT
    total: np.ndarray           # |B_e|, nT (what the cesium magnetometer sees)
    lat: float
    lon: float
    altitude_m: float
    start: datetime.datetime
    errors: ErrorModel = field(default_factory=ErrorModel)
    # A moving flight (make_survey): position from the start point, course over ground
    # (radians from true north) and ground speed (m/s) per sample; None when stationary.
    north_m: np.ndarray | None = None
    east_m: np.ndarray | None = None
    course: np.ndarray | None = None
    speed: np.ndarray | None = None

    @property
    def start_seconds_of_day(self):
        midnight = self.start.replace(hour=0, minute=0, second=0, microsecond=0)
        return (self.start - midnight).total_seconds()

    def position(self, t):
        """Latitude and longitude (degrees) at flight time ``t`` (s)."""
        if self.north_m is None:
            return self.lat, self.lon
        north = float(np.interp(t, self.t, self.north_m))
        east = float(np.interp(t, self.t, self.east_m))
        return (self.lat + north / _METRES_PER_DEGREE,
                self.lon + east / (_METRES_PER_DEGREE * np.cos(np.radians(self.lat))))

    def attitude_csv(self):
        """The attitude as ``maglog calibrate --attitude`` reads it: ``t`` in seconds since
        00:00 UTC of the flight's date (the log's time base), roll, pitch and true heading
        in degrees."""
        def deg(angle):
            # Rounded first, then +0.0: an angle of -1e-17 rad (one rounding of a level
            # attitude) is written "0.0000", not "-0.0000", whatever the CPU's trig path.
            return f"{round(float(np.degrees(angle)), 4) + 0.0:.4f}"

        rows = ["t,roll_deg,pitch_deg,heading_deg"]
        rows += [f"{self.start_seconds_of_day + t:.3f},{deg(r)},{deg(p)},"
                 f"{round(float(np.degrees(h) % 360), 4) % 360 + 0.0:.4f}"
                 for t, r, p, h in zip(self.t, self.roll, self.pitch, self.heading)]
        return ("\n".join(rows) + "\n").encode()

    def log(self, *, mag_rate=20.0, cesium_rate=10.0, cesium_noise=0.05, seed=0):
        """The log file the logger would write: PMAG1, cesium and GGA/ZDA lines (and VTG
        for a moving flight) in time order (CR LF)."""
        rng = np.random.default_rng(seed)
        events = []
        for k, (t, b) in enumerate(zip(self.t, self.b_meas)):
            events.append((t, 1, sentences.pmag1(k, *b)))
        ces_t = np.arange(0, self.t[-1], 1 / cesium_rate)
        ces = np.interp(ces_t, self.t, self.total) + rng.normal(scale=cesium_noise,
                                                                size=ces_t.size)
        for t, f in zip(ces_t, ces):
            events.append((t, 2, sentences.cesium(f, 1500)))
        seconds0 = self.start_seconds_of_day
        for s in range(int(self.t[-1]) + 1):
            lat, lon = self.position(float(s))
            events.append((float(s), 0, sentences.gga(seconds0 + s, lat, lon,
                                                      altitude_m=self.altitude_m)))
            events.append((float(s), 0, sentences.zda(self.start
                                                      + datetime.timedelta(seconds=s))))
            if self.course is not None:
                k = min(int(np.searchsorted(self.t, s)), len(self.t) - 1)
                events.append((float(s), 0, sentences.vtg(np.degrees(self.course[k]) % 360,
                                                          self.speed[k] / _KNOT_M_S)))
        events.sort(key=lambda e: (e[0], e[1]))
        return b"".join(e[2] for e in events)


def _rotation(heading, pitch, roll):
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    rz = np.array([[ch, -sh, np.zeros_like(ch)], [sh, ch, np.zeros_like(ch)],
                   [np.zeros_like(ch), np.zeros_like(ch), np.ones_like(ch)]])
    ry = np.array([[cp, np.zeros_like(cp), sp], [np.zeros_like(cp), np.ones_like(cp),
                                                 np.zeros_like(cp)], [-sp, np.zeros_like(cp), cp]])
    rx = np.array([[np.ones_like(cr), np.zeros_like(cr), np.zeros_like(cr)],
                   [np.zeros_like(cr), cr, -sr], [np.zeros_like(cr), sr, cr]])
    return np.einsum("ijn,jkn,kln->nil", rz, ry, rx)       # body -> NED, per sample


def make_flight(*, coverage="uav", seconds=120.0, rate=20.0, errors=DEFAULT_ERRORS, seed=1,
                lat=47.5, lon=8.5, altitude_m=500.0,
                start=datetime.datetime(2026, 6, 1, 10, 0, 0)):
    """A calibration flight: heading turning through all directions, roll and pitch
    swinging within the coverage's range (or tumbling over the full sphere)."""
    import ppigrf
    if coverage not in COVERAGES:
        raise ValueError(f"Coverage must be one of {', '.join(COVERAGES)}, not {coverage!r}")
    rng = np.random.default_rng(seed)
    t = np.arange(0, seconds, 1 / rate)
    n = t.size
    if COVERAGES[coverage] is None:
        heading = rng.uniform(0, 2 * np.pi, n)
        pitch = np.arcsin(rng.uniform(-1, 1, n))
        roll = rng.uniform(-np.pi, np.pi, n)
    else:
        limit = np.radians(COVERAGES[coverage])
        heading = 2 * np.pi * t / (seconds / 4)                 # four full turns
        pitch = limit * np.sin(2 * np.pi * t / 7.3 + rng.uniform(0, 6))
        roll = limit * np.sin(2 * np.pi * t / 5.1 + rng.uniform(0, 6))
    east, north, up = ppigrf.igrf(lon, lat, altitude_m / 1000, start)
    field_ned = np.array([float(np.ravel(north)[0]), float(np.ravel(east)[0]),
                          -float(np.ravel(up)[0])])
    body = np.einsum("nji,j->ni", _rotation(heading, pitch, roll), field_ned)
    return Flight(t=t, roll=roll, pitch=pitch, heading=heading, b_earth=body,
                  b_meas=errors.apply(body, rng), total=np.linalg.norm(body, axis=1),
                  lat=lat, lon=lon, altitude_m=altitude_m, start=start, errors=errors)


def _field_ned(lat, lon, altitude_m, when):
    """IGRF north, east, down (nT) at each position (arrays)."""
    import ppigrf
    east, north, up = ppigrf.igrf(lon, lat, altitude_m / 1000, when)
    return np.column_stack([np.ravel(north), np.ravel(east), -np.ravel(up)])


def _smooth_noise(rng, n, width, scale):
    """Band-limited noise: white noise averaged over ``width`` samples, scaled to ``scale``
    standard deviation (zero when ``scale`` is 0)."""
    if scale == 0 or n == 0:
        return np.zeros(n)
    white = rng.normal(size=n + width)
    smooth = np.convolve(white, np.ones(width) / width, mode="valid")[:n]
    return scale * smooth / smooth.std()


def make_survey(*, calibration_seconds=120.0, coverage="uav", legs=6, leg_seconds=60.0,
                turn_seconds=15.0, line_course_deg=30.0, airspeed=15.0, wind=(4.0, -3.0),
                cruise_pitch_deg=0.0, turbulence_deg=1.0, rate=20.0, errors=DEFAULT_ERRORS,
                seed=1, lat=47.5, lon=8.5, altitude_m=500.0,
                start=datetime.datetime(2026, 6, 1, 10, 0, 0)):
    """A survey flight: the calibration manoeuvre of :func:`make_flight` at the start point
    (hovering: no ground speed), a turn onto the first line, then ``legs`` straight, level lines on ``line_course_deg``
    and its reciprocal, joined by banked 180° turns, flown at ``airspeed`` (m/s) in a
    ``wind`` (north, east, m/s; the aircraft crabs into it, so its heading differs from its
    course over ground). Roll and pitch on the lines are ``cruise_pitch_deg`` plus
    turbulence of ``turbulence_deg`` (standard deviation, ~2 s correlation)."""
    if legs < 1 or leg_seconds <= 0 or turn_seconds <= 0 or airspeed <= 0:
        raise ValueError("Need at least one leg, and positive leg and turn times and airspeed")
    wind_n, wind_e = wind
    if np.hypot(wind_n, wind_e) >= airspeed:
        raise ValueError(f"Wind {np.hypot(wind_n, wind_e):.1f} m/s must be below the "
                         f"airspeed {airspeed} m/s")
    calib = make_flight(coverage=coverage, seconds=calibration_seconds, rate=rate,
                        errors=errors, seed=seed, lat=lat, lon=lon, altitude_m=altitude_m,
                        start=start)
    rng = np.random.default_rng(seed + 1_000_003)
    # Plan the lines: the course over ground, and the heading that holds it in the wind.
    tracks = np.radians(line_course_deg + 180.0 * (np.arange(legs) % 2))
    crabs = np.arcsin((wind_n * np.sin(tracks) - wind_e * np.cos(tracks)) / airspeed)
    headings = tracks + crabs
    dt = 1 / rate
    per_leg = int(round(leg_seconds * rate))
    per_turn = int(round(turn_seconds * rate))
    # From the manoeuvre's last attitude onto the first line (no jump in the attitude).
    step = np.arange(1, per_turn + 1) / per_turn
    entry = (headings[0] - calib.heading[-1] + np.pi) % (2 * np.pi) - np.pi
    pieces = [(calib.heading[-1] + entry * step, calib.roll[-1] * (1 - step))]
    entry_pitch = calib.pitch[-1] + (np.radians(cruise_pitch_deg) - calib.pitch[-1]) * step
    for i in range(legs):
        pieces.append((np.full(per_leg, headings[i]), np.zeros(per_leg)))
        if i + 1 < legs:
            turn = (headings[i + 1] - headings[i]) % (2 * np.pi)
            if i % 2:                                           # alternate: right, left
                turn -= 2 * np.pi
            omega = turn / turn_seconds
            bank = np.arctan(airspeed * omega / _GRAVITY)
            pieces.append((headings[i] + turn * step, np.full(per_turn, bank)))
    heading = np.concatenate([p[0] for p in pieces])
    n = heading.size
    # Roll into and out of the turns over a second rather than at once.
    bank = np.concatenate([p[1] for p in pieces])
    ramp = max(1, int(rate))
    bank[per_turn:] = np.convolve(np.concatenate([np.zeros(ramp - 1), bank[per_turn:]]),
                                  np.ones(ramp) / ramp, mode="valid")
    roll = bank + _smooth_noise(rng, n, int(2 * rate), np.radians(turbulence_deg))
    pitch = np.radians(cruise_pitch_deg) + _smooth_noise(rng, n, int(2 * rate),
                                                         np.radians(turbulence_deg))
    pitch[:per_turn] += entry_pitch - np.radians(cruise_pitch_deg)
    v_north = airspeed * np.cos(heading) + wind_n
    v_east = airspeed * np.sin(heading) + wind_e
    north = np.cumsum(v_north) * dt
    east = np.cumsum(v_east) * dt
    t = calib.t[-1] + dt + np.arange(n) * dt
    # The field along the track (IGRF every second, interpolated).
    seconds = np.arange(0.0, t[-1] - t[0] + 1.0, 1.0)
    lat_s = lat + np.interp(seconds, t - t[0], north) / _METRES_PER_DEGREE
    lon_s = lon + np.interp(seconds, t - t[0], east) / (_METRES_PER_DEGREE
                                                        * np.cos(np.radians(lat)))
    ned_s = _field_ned(lat_s, lon_s, altitude_m, start)
    field_ned = np.column_stack([np.interp(t - t[0], seconds, ned_s[:, k]) for k in range(3)])
    body = np.einsum("nji,nj->ni", _rotation(heading, pitch, roll), field_ned)
    stationary = calib.t.size
    return Flight(
        t=np.concatenate([calib.t, t]),
        roll=np.concatenate([calib.roll, roll]),
        pitch=np.concatenate([calib.pitch, pitch]),
        heading=np.concatenate([calib.heading, heading]),
        b_earth=np.vstack([calib.b_earth, body]),
        b_meas=np.vstack([calib.b_meas, errors.apply(body, rng)]),
        total=np.concatenate([calib.total, np.linalg.norm(body, axis=1)]),
        lat=lat, lon=lon, altitude_m=altitude_m, start=start, errors=errors,
        north_m=np.concatenate([np.zeros(stationary), north]),
        east_m=np.concatenate([np.zeros(stationary), east]),
        course=np.concatenate([calib.heading, np.arctan2(v_east, v_north)]),
        speed=np.concatenate([np.zeros(stationary), np.hypot(v_north, v_east)]))
