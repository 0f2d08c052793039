"""Synthetic survey flights for calibration: attitude, Earth field, the magnetometer error
model, and the log the logger would write.

Error model (DESIGN.md): ``b = C_NO C_SF (I + C_SI) (B_e + B_HI) + b0 + w`` with the body
field ``B_e`` from IGRF (ppigrf) rotated by the attitude (x forward, y right, z down).
"""

import datetime
from dataclasses import dataclass, field

import numpy as np

from . import sentences


__all__ = ["ErrorModel", "DEFAULT_ERRORS", "Flight", "make_flight", "COVERAGES"]

#: Attitude coverage: (roll and pitch half-range in degrees, or None for the full sphere).
COVERAGES = {"full": None, "uav": 30.0, "planar": 5.0}


@dataclass(frozen=True)
class ErrorModel:
    """Non-orthogonality (lower triangular, small), scale factors, soft iron (symmetric),
    hard iron (nT, body frame), bias (nT) and white noise (nT, per axis)."""
    non_orthogonality: tuple = ((1.0, 0.0, 0.0), (0.012, 1.0, 0.0), (-0.008, 0.015, 1.0))
    scale: tuple = (1.04, 0.97, 1.02)
    soft_iron: tuple = ((0.02, 0.01, -0.005), (0.01, -0.015, 0.008), (-0.005, 0.008, 0.01))
    hard_iron: tuple = (250.0, -180.0, 320.0)
    bias: tuple = (40.0, -25.0, 15.0)
    noise: float = 5.0

    def matrix(self):
        return (np.array(self.non_orthogonality) @ np.diag(self.scale)
                @ (np.eye(3) + np.array(self.soft_iron)))

    def apply(self, b_earth, rng):
        m = self.matrix()
        clean = (b_earth + np.array(self.hard_iron)) @ m.T + np.array(self.bias)
        return clean + rng.normal(scale=self.noise, size=clean.shape)

    def truth(self):
        """The scalar model's K (upper triangular, positive diagonal) and c."""
        m = self.matrix()
        # b = M (B + h) + b0  =>  B = M^-1 b - (h + M^-1 b0) = Q R b - o
        q, r = np.linalg.qr(np.linalg.inv(m))
        signs = np.sign(np.diag(r))
        k = r * signs[:, None]
        offset = np.array(self.hard_iron) + np.linalg.inv(m) @ np.array(self.bias)
        return k, (q * signs).T @ offset


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

    def log(self, *, mag_rate=20.0, cesium_rate=10.0, cesium_noise=0.05, seed=0):
        """The log file the logger would write: PMAG1, cesium and GGA/ZDA lines in time
        order (CR LF)."""
        rng = np.random.default_rng(seed)
        events = []
        for k, (t, b) in enumerate(zip(self.t, self.b_meas)):
            events.append((t, 1, sentences.pmag1(k, *b)))
        ces_t = np.arange(0, self.t[-1], 1 / cesium_rate)
        ces = np.interp(ces_t, self.t, self.total) + rng.normal(scale=cesium_noise,
                                                                size=ces_t.size)
        for t, f in zip(ces_t, ces):
            events.append((t, 2, sentences.cesium(f, 1500)))
        seconds0 = (self.start - self.start.replace(hour=0, minute=0, second=0,
                                                    microsecond=0)).total_seconds()
        for s in range(int(self.t[-1]) + 1):
            events.append((float(s), 0, sentences.gga(seconds0 + s, self.lat, self.lon,
                                                      altitude_m=self.altitude_m)))
            events.append((float(s), 0, sentences.zda(self.start
                                                      + datetime.timedelta(seconds=s))))
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
