"""Synthetic flights of the kind met on real aeromagnetic data, for the calibration tests.

A fluxgate in a fixed-wing aircraft against a scalar (total-field) magnetometer mounted
elsewhere on it: the aircraft flies survey lines and turns between them, so the field's
direction in the fluxgate's frame sweeps mostly about the vertical axis (headings change,
bank only in the turns, a little pitch). The errors are of the size seen on such data: K's
diagonal 1.048-1.065, offsets up to 710 nT, and interference the model cannot remove
(the aircraft's own field, the two sensors' different places), about 18 nT RMS.

Everything here is plain numpy, written independently of ``maglog.calib``: the field is
rotated into the sensor's frame, the sensor's errors applied in the paper's forward form
(``b = K^-1 (B + c)``), and the biases of the reference made as a user's data would have
them (a first-order lag filter, a constant reference over crustal anomalies).

The figures the flights reproduce (issue 24) are measured in ``test_realkind.py``.
"""

from dataclasses import dataclass

import numpy as np

FIELD_NT = 50_000.0
INCLINATION_DEG = 65.0
DECLINATION_DEG = 3.0
#: The fluxgate's errors in the fitted form (K upper triangular with a positive diagonal,
#: calibrated = K b - c): diagonal 1.048-1.065, offsets up to 710 nT.
K_TRUE = np.array([[1.048, 0.012, -0.018],
                   [0.0, 1.065, 0.009],
                   [0.0, 0.0, 1.056]])
C_TRUE = np.array([710.0, -420.0, 380.0])
SPEED_M_S = 60.0


@dataclass
class Flight:
    t: np.ndarray          # seconds
    b: np.ndarray          # fluxgate (N, 3), nT
    r: np.ndarray          # reference total field (N,), nT
    field: np.ndarray      # true total field at the fluxgate (N,), nT
    east: np.ndarray       # position, m
    north: np.ndarray
    K: np.ndarray
    c: np.ndarray

    @property
    def rate(self):
        return 1.0 / float(np.median(np.diff(self.t)))

    def log(self, *, lat0=-31.0, lon0=116.0, start_seconds_of_day=3600.0):
        """The flight as a maglog log file (PMAG1 and cesium lines per sample, GGA and ZDA
        each second), written with the simulator's sentence writers."""
        import datetime

        from maglog.sim.stimulus import sentences
        events = []
        for k, (t, b, r) in enumerate(zip(self.t, self.b, self.r)):
            events.append((t, 1, sentences.pmag1(k, *b)))
            events.append((t, 2, sentences.cesium(float(r), 1500)))
        start = datetime.datetime(2024, 5, 1, tzinfo=datetime.timezone.utc) + \
            datetime.timedelta(seconds=start_seconds_of_day)
        metres_per_deg = 111_320.0
        for s in range(int(self.t[-1]) + 1):
            k = min(int(np.searchsorted(self.t, s)), len(self.t) - 1)
            lat = lat0 + self.north[k] / metres_per_deg
            lon = lon0 + self.east[k] / (metres_per_deg * np.cos(np.radians(lat0)))
            events.append((float(s), 0, sentences.gga(start_seconds_of_day + s, lat, lon,
                                                      altitude_m=300.0)))
            events.append((float(s), 0, sentences.zda(start + datetime.timedelta(seconds=s))))
        events.sort(key=lambda e: (e[0], e[1]))
        return b"".join(e[2] for e in events)


def _rotation(heading, pitch, roll):
    """Body -> north-east-down per sample (N, 3, 3), angles in radians."""
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    out = np.empty((len(heading), 3, 3))
    out[:, 0, 0] = ch * cp
    out[:, 0, 1] = ch * sp * sr - sh * cr
    out[:, 0, 2] = ch * sp * cr + sh * sr
    out[:, 1, 0] = sh * cp
    out[:, 1, 1] = sh * sp * sr + ch * cr
    out[:, 1, 2] = sh * sp * cr - ch * sr
    out[:, 2, 0] = -sp
    out[:, 2, 1] = cp * sr
    out[:, 2, 2] = cp * cr
    return out


def _smooth_noise(rng, n, sigma, samples):
    """Gaussian noise low-passed over about ``samples`` samples, of RMS ``sigma``."""
    white = rng.normal(size=n + 4 * samples)
    kernel = np.exp(-0.5 * (np.arange(-2 * samples, 2 * samples + 1) / samples) ** 2)
    out = np.convolve(white, kernel, mode="valid")[:n]
    return sigma * out / np.std(out)


def attitude(n, rate, rng, *, bank_deg=25.0, pitch_deg=2.0, turn_rate_deg_s=3.0,
             leg_s=20.0):
    """A fixed-wing pattern: straight legs of ``leg_s`` seconds joined by turns at
    ``turn_rate_deg_s`` banked ``bank_deg``, the direction of each turn and its length
    (90-270 degrees) drawn at random; pitch wanders by ``pitch_deg``, roll by half a degree
    on the legs. Returns (t, heading, pitch, roll) in seconds and radians."""
    t = np.arange(n) / rate
    turning = np.zeros(n)
    i = 0
    while i < n:
        i += int(leg_s * rate * rng.uniform(0.6, 1.4))
        if i >= n:
            break
        angle = np.radians(rng.uniform(90, 270))
        steps = int(angle / np.radians(turn_rate_deg_s) * rate)
        turning[i:i + steps] = rng.choice([-1.0, 1.0])
        i += steps
    # The bank follows the turn smoothly (about 2 s to roll in).
    kernel = np.hanning(int(2 * rate) | 1)
    turning = np.convolve(turning, kernel / kernel.sum(), mode="same")
    # The heading turns at the (smoothed) turn rate: no step in the rate of any angle.
    heading = rng.uniform(0, 2 * np.pi) + np.cumsum(np.radians(turn_rate_deg_s) * turning) / rate
    roll = np.radians(bank_deg) * turning
    roll += np.radians(0.5) * _smooth_noise(rng, n, 1.0, max(int(rate), 1))
    pitch = np.radians(pitch_deg) * _smooth_noise(rng, n, 1.0, max(int(3 * rate), 1))
    return t, heading, pitch, roll


def _anomalies(east, north, rng, amplitude, widths=(300.0, 1500.0)):
    """Crustal anomalies along the track: a sum of Gaussian bodies ``widths`` m across,
    scaled to peak at +-``amplitude`` nT over the flown track."""
    span = max(np.ptp(east), np.ptp(north), 1.0)
    field = np.zeros(len(east))
    for _ in range(12):
        x0 = rng.uniform(east.min() - 0.1 * span, east.max() + 0.1 * span)
        y0 = rng.uniform(north.min() - 0.1 * span, north.max() + 0.1 * span)
        width = rng.uniform(*widths)
        field += rng.normal() * np.exp(-((east - x0) ** 2 + (north - y0) ** 2)
                                       / (2 * width ** 2))
    field -= np.mean(field)
    return amplitude * field / max(np.max(np.abs(field)), 1e-12)


def first_order_lag(x, rate, tau_s, oversample=16):
    """``x`` through a first-order low-pass of time constant ``tau_s``, as a sensor's
    filter acts on the continuous field before the samples are taken: ``x`` is
    interpolated by a cubic spline ``oversample`` times finer, filtered exactly for an
    input linear between those points, and taken back at the samples; the filter starts
    at rest on the first value."""
    from scipy.interpolate import CubicSpline
    x = np.asarray(x, float)
    if tau_s <= 0:
        return x.copy()
    t = np.arange(len(x)) / rate
    fine = np.arange((len(x) - 1) * oversample + 1) / (rate * oversample)
    xf = CubicSpline(t, x)(fine)
    h = 1.0 / (rate * oversample)
    a = np.exp(-h / tau_s)
    b0 = 1.0 - (tau_s / h) * (1.0 - a)
    b1 = (tau_s / h) * (1.0 - a) - a
    from scipy.signal import lfilter
    # y_i = a y_(i-1) + b0 x_i + b1 x_(i-1), started at rest on x_0.
    out, _ = lfilter([b0, b1], [1.0, -a], xf, zi=[xf[0] * (1 - b0)])
    return out[::oversample]


def flight(*, n=1000, rate=10.0, seed=0, noise_nT=18.0, smooth_nT=0.0, bank_deg=25.0,
           pitch_deg=2.0, turn_rate_deg_s=3.0, leg_s=20.0, K=K_TRUE, c=C_TRUE,
           anomaly_nT=0.0, constant_reference=False, lag_s=0.0, lag_on="reference",
           reference_noise_nT=0.05, aircraft_field_nT=(0.0, 0.0, 0.0),
           inclination_deg=INCLINATION_DEG, vertical_axis=2, aircraft_induced=None,
           axis_noise_nT=0.0, mount=None, manoeuvres=False,
           anomaly_width_m=(300.0, 1500.0)):
    """A real-kind flight.

    ``noise_nT``: white interference on the total field (what no calibration removes);
    ``smooth_nT``: interference that varies over about ten seconds (the aircraft's field
    changing with its state). ``anomaly_nT``: crustal anomalies of that peak along the
    track (bodies ``anomaly_width_m`` across), seen by both sensors; with ``constant_reference`` the reference is the regional
    field alone (a user's constant). ``lag_s``: a first-order filter of that time constant
    on the reference (``lag_on="reference"``) or on the fluxgate's three axes
    (``"magnetometer"``).
    """
    rng = np.random.default_rng(seed)
    t, heading, pitch, roll = attitude(n, rate, rng, bank_deg=bank_deg, pitch_deg=pitch_deg,
                                       turn_rate_deg_s=turn_rate_deg_s, leg_s=leg_s)
    if manoeuvres:
        roll = roll + np.radians(10) * np.sin(2 * np.pi * t / 4.0)
        pitch = pitch + np.radians(5) * np.sin(2 * np.pi * t / 6.0 + 1.0)
        heading = heading + np.radians(5) * np.sin(2 * np.pi * t / 5.0 + 2.0)
    east = np.cumsum(SPEED_M_S * np.sin(heading)) / rate
    north = np.cumsum(SPEED_M_S * np.cos(heading)) / rate
    inc, dec = np.radians(inclination_deg), np.radians(DECLINATION_DEG)
    direction = np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])
    anomaly = (_anomalies(east, north, rng, anomaly_nT, anomaly_width_m) if anomaly_nT
               else np.zeros(n))
    # A slow regional change (diurnal and the IGRF gradient over the track), a few nT.
    regional = FIELD_NT + 3.0 * np.sin(2 * np.pi * t / max(t[-1], 1.0))
    total = regional + anomaly
    interference = rng.normal(scale=noise_nT, size=n)
    if smooth_nT:
        interference += _smooth_noise(rng, n, smooth_nT, int(10 * rate))
    sensed = total + interference
    rot = _rotation(heading, pitch, roll)
    body = np.einsum("nji,j->ni", rot, direction) * sensed[:, None]
    body = np.roll(body, vertical_axis - 2, axis=1)
    if mount is not None:
        body = body @ np.asarray(mount, float).T
    b = np.linalg.solve(K, (body + c).T).T
    if axis_noise_nT:
        b = b + rng.normal(scale=axis_noise_nT, size=b.shape)
    r = (regional.copy() if constant_reference else total.copy())
    if constant_reference:
        r = np.full(n, float(np.median(regional)))
    r = r + rng.normal(scale=reference_noise_nT, size=n)
    if np.any(aircraft_field_nT):
        r = r + np.einsum("nij,j,i->n", rot, np.asarray(aircraft_field_nT, float), direction)
    if aircraft_induced is not None:
        body_field = np.einsum("nji,j->ni", rot, direction) * total[:, None]
        induced = body_field @ np.asarray(aircraft_induced, float).T
        r = r + np.einsum("nij,nj,i->n", rot, induced, direction)
    if lag_s:
        if lag_on == "reference":
            r = first_order_lag(r, rate, lag_s)
        else:
            b = np.column_stack([first_order_lag(b[:, i], rate, lag_s) for i in range(3)])
    return Flight(t=t, b=b, r=r, field=total, east=east, north=north, K=np.array(K, float),
                  c=np.array(c, float))


def isotropic_rms(b, r):
    """The best isotropic fit: |s b - c| against r (four parameters), by least squares;
    its RMS residual (nT)."""
    from scipy.optimize import least_squares
    s0 = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))

    def residual(p):
        return np.linalg.norm(p[0] * b - p[1:], axis=1) - r
    fit = least_squares(residual, np.r_[s0, 0.0, 0.0, 0.0], x_scale=np.r_[1e-3, 100, 100, 100])
    return float(np.sqrt(np.mean(fit.fun ** 2)))


def truth_rms(fl):
    """RMS of |K b - c| - r with the true parameters (what a perfect fit leaves)."""
    u = fl.b @ fl.K.T - fl.c
    return float(np.sqrt(np.mean((np.linalg.norm(u, axis=1) - fl.r) ** 2)))
