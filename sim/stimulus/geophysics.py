"""What a survey scenario adds to the Earth field and to the sensors: magnetic sources
(point dipoles), the diurnal variation (with a base station's record), and the platform's
interference (Tolles–Lawson terms on the cesium, eddy currents on the vector sensor, a
heading error).

The truth of a survey scenario (``truth["survey"]``, :func:`survey_truth`) holds everything
the public functions here need, so tests and reports evaluate the true map and the diurnal
field from ``truth.json`` alone::

    anomaly_total(truth["survey"], north_m, east_m, up_m)   # |F + b| - |F|, nT
    diurnal_nT(truth["survey"], t)                           # D(t), nT; t from power-up

Frames and units: local metres ``north``, ``east`` from the site (flat earth, as
:mod:`.flight`), ``up`` the height above the site's ground; the dipoles sit ``depth_m``
below that ground. Field vectors are north, east, down (NED) in nT, moments in A·m².
Body frame: x forward, y right, z down (:func:`.scenario._rotation`).

The sensors, with ``F_total = F_igrf(position) + b(position) + D(t) F̂_igrf`` (b the
dipoles' field at the sample's own position, D the diurnal field along the IGRF direction),
``B = Rᵀ F_total`` in the body frame, ``T = |B|``, ``u = B / T`` and ``u' = du/dt``
(from the 100 Hz attitude):

- cesium: ``T + TL(u, T, u') + heading_error_nT · u3 + noise``, TL the 18 Tolles–Lawson
  terms (:data:`TL_TERM_NAMES`: permanent ``u1 u2 u3``; induced ``T u_i u_j`` for the six
  i <= j; eddy ``T u_i u_j'`` for the nine i, j, row-major) times ``tl_coefficients``;
- vector magnetometer: ``B + E dB/dt`` (E the 3 × 3 ``vector_eddy_s``, seconds) through the
  error model.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from .scenario import _field_ned, _rotation

__all__ = ["TL_TERM_NAMES", "tl_features", "dipole_moment_ned", "anomaly_vector",
           "anomaly_total", "diurnal_nT", "survey_truth", "SurveyField", "base_station_csv",
           "BASE_CSV", "DIURNAL_PEAK_SOLAR_H"]

#: The 18 Tolles–Lawson terms in the order of ``tl_coefficients`` (u' = du/dt).
TL_TERM_NAMES = (
    "u1", "u2", "u3",
    "T*u1*u1", "T*u1*u2", "T*u1*u3", "T*u2*u2", "T*u2*u3", "T*u3*u3",
    "T*u1*u1'", "T*u1*u2'", "T*u1*u3'", "T*u2*u1'", "T*u2*u2'", "T*u2*u3'",
    "T*u3*u1'", "T*u3*u2'", "T*u3*u3'")
#: The base station's file, beside truth.json.
BASE_CSV = "base.csv"
#: Local solar time of the daily variation's maximum, hours.
DIURNAL_PEAK_SOLAR_H = 13.0
_DAY_S = 86_400.0
_INDUCED_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def tl_features(u, total, du):
    """The 18 Tolles–Lawson terms (n, 18) of unit directions ``u`` (n, 3), totals ``total``
    (n, nT) and derivatives ``du`` (n, 3, 1/s), in the order of :data:`TL_TERM_NAMES`."""
    u, du = np.atleast_2d(u), np.atleast_2d(du)
    total = np.asarray(total, float).reshape(-1, 1)
    induced = np.column_stack([u[:, i] * u[:, j] for i, j in _INDUCED_PAIRS])
    eddy = (u[:, :, None] * du[:, None, :]).reshape(len(u), 9)
    return np.hstack([u, total * induced, total * eddy])


def dipole_moment_ned(moment, inclination_deg, declination_deg, field_ned):
    """A dipole's moment vector (NED, A·m²): along (inclination, declination) for a remanent
    one, along ``field_ned`` (the IGRF at the site) for an induced one (angles None)."""
    if inclination_deg is None:
        direction = np.asarray(field_ned, float) / np.linalg.norm(field_ned)
    else:
        inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
        direction = np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec),
                              np.sin(inc)])
    return moment * direction


def anomaly_vector(dipoles, north_m, east_m, up_m):
    """The dipoles' field (..., 3: north, east, down; nT) at the points, by
    ``harmonica.dipole_magnetic``; ``dipoles`` as in ``truth["survey"]["dipoles"]``."""
    import harmonica
    north, east, up = np.broadcast_arrays(*(np.asarray(v, float) for v in
                                            (north_m, east_m, up_m)))
    shape = north.shape
    if not dipoles:
        return np.zeros(shape + (3,))
    moments = np.array([d["moment_ned_Am2"] for d in dipoles], float)
    sources = (np.array([d["east_m"] for d in dipoles], float),
               np.array([d["north_m"] for d in dipoles], float),
               -np.array([d["depth_m"] for d in dipoles], float))
    b_e, b_n, b_u = harmonica.dipole_magnetic(
        (east.ravel(), north.ravel(), up.ravel()), sources,
        (moments[:, 1], moments[:, 0], -moments[:, 2]), field="b", parallel=False)
    return np.stack([b_n, b_e, -b_u], axis=-1).reshape(shape + (3,))


def anomaly_total(truth_survey, north_m, east_m, up_m):
    """The total-field anomaly ``|F + b| - |F|`` (nT) of the survey's dipoles at the points
    (local metres; ``up_m`` above the site's ground), F the site's IGRF vector
    (``truth_survey["igrf_site_ned_nT"]``). Arrays broadcast; a float for scalars."""
    f = np.asarray(truth_survey["igrf_site_ned_nT"], float)
    b = anomaly_vector(truth_survey["dipoles"], north_m, east_m, up_m)
    value = np.linalg.norm(f + b, axis=-1) - np.linalg.norm(f)
    return float(value) if value.ndim == 0 else value


def diurnal_nT(truth_survey, t):
    """The diurnal field D (nT) at ``t`` seconds from power-up (UTC): the daily sinusoid
    (24 h period, maximum at 13:00 local solar time at the site's longitude) plus the
    pulsation ``pulsation_nT · sin(2π t / pulsation_period_s)``."""
    d = truth_survey["diurnal"]
    t = np.asarray(t, float)
    solar_s = d["start_seconds_of_day"] + t + d["lon_deg"] * 240.0
    value = (d["amplitude_nT"]
             * np.cos(2 * np.pi * (solar_s - DIURNAL_PEAK_SOLAR_H * 3600.0) / _DAY_S)
             + d["pulsation_nT"] * np.sin(2 * np.pi * t / d["pulsation_period_s"]))
    return float(value) if value.ndim == 0 else value


def _seconds_of_day(when):
    return (when - when.replace(hour=0, minute=0, second=0, microsecond=0)).total_seconds()


def survey_truth(scenario, lines):
    """``truth["survey"]`` of a scenario with survey features: origin, time base, lines (a
    list of (kind, index, start_s, end_s)), the site's IGRF, the dipoles with their moment
    vectors, the interference and the diurnal parameters."""
    site = scenario.site
    height = scenario.flight.takeoff.height_m
    when = scenario.start.replace(tzinfo=None)
    igrf = _field_ned(np.array([site.lat_deg]), np.array([site.lon_deg]),
                      np.array([site.ground_alt_m + height]), when)[0]
    ground = _field_ned(np.array([site.lat_deg]), np.array([site.lon_deg]),
                        np.array([site.ground_alt_m]), when)[0]
    dipoles = []
    for d in scenario.dipoles:
        moment = dipole_moment_ned(d.moment_Am2, d.inclination_deg, d.declination_deg, igrf)
        dipoles.append({"north_m": d.north_m, "east_m": d.east_m, "depth_m": d.depth_m,
                        "moment_Am2": d.moment_Am2,
                        "kind": "induced" if d.inclination_deg is None else "remanent",
                        "inclination_deg": d.inclination_deg,
                        "declination_deg": d.declination_deg,
                        "moment_ned_Am2": [float(x) for x in moment]})
    inter, di = scenario.interference, scenario.diurnal
    seconds0 = _seconds_of_day(scenario.start)
    return {
        "origin": {"lat_deg": site.lat_deg, "lon_deg": site.lon_deg,
                   "ground_alt_m": site.ground_alt_m, "flight_height_m": height},
        "time": {"timestamp": scenario.start.isoformat(), "start_seconds_of_day": seconds0,
                 "t_log": "t_log = start_seconds_of_day + t: the log's time base (seconds "
                          "since 00:00 UTC of the timestamp's date) from the times here "
                          "(seconds from power-up, like the phases)"},
        "lines": [{"kind": kind, "index": index, "start_s": round(float(start), 6),
                   "end_s": round(float(end), 6)} for kind, index, start, end in lines],
        "igrf_site_ned_nT": [float(x) for x in igrf],
        "igrf_site_note": "IGRF at the site's latitude and longitude, ground altitude + "
                          "flight height, on the start date (the F of anomaly_total)",
        "dipoles": dipoles,
        "interference": {"tl_coefficients": list(inter.tl_coefficients),
                         "tl_names": list(TL_TERM_NAMES),
                         "vector_eddy_s": np.reshape(inter.vector_eddy_s, (3, 3)).tolist(),
                         "heading_error_nT": inter.heading_error_nT},
        "diurnal": {"amplitude_nT": di.amplitude_nT, "pulsation_nT": di.pulsation_nT,
                    "pulsation_period_s": di.pulsation_period_s,
                    "peak_local_solar_h": DIURNAL_PEAK_SOLAR_H, "lon_deg": site.lon_deg,
                    "start_seconds_of_day": seconds0,
                    "base_station": BASE_CSV if di.base_station else None,
                    "base_rate_hz": di.base_rate_hz, "base_noise_nT": di.base_noise_nT,
                    "base_igrf_total_nT": float(np.linalg.norm(ground))},
    }


class SurveyField:
    """The total field and the sensors' readings along a flight (module docstring).

    ``track`` the dense :class:`~.flight.Track` (its 1 Hz IGRF grid and positions),
    ``attitude`` the dense (roll, pitch, heading) array, ``truth_survey`` from
    :func:`survey_truth`."""

    def __init__(self, truth_survey, track, attitude, dt):
        self.survey = truth_survey
        self.track = track
        self.attitude = attitude
        inter = truth_survey["interference"]
        self.coefficients = np.asarray(inter["tl_coefficients"], float)
        self.eddy = np.asarray(inter["vector_eddy_s"], float)
        self.heading_error = float(inter["heading_error_nT"])
        body = self._body(track.t, attitude[:, 0], attitude[:, 1], attitude[:, 2],
                          self.field_ned(track.t))
        total = np.linalg.norm(body, axis=1, keepdims=True)
        self.t = track.t
        self.d_body = np.gradient(body, dt, axis=0)
        self.d_u = np.gradient(body / total, dt, axis=0)

    def field_ned(self, t):
        """F_total (n, 3, NED nT) at times ``t``, the anomaly at the positions at ``t``."""
        tr = self.track
        igrf = np.column_stack([np.interp(t, tr.field_t, tr.field_ned[:, k]) for k in range(3)])
        north, east, up = (np.interp(t, tr.t, v) for v in (tr.north, tr.east, tr.up))
        b = anomaly_vector(self.survey["dipoles"], north, east, up)
        unit = igrf / np.linalg.norm(igrf, axis=1, keepdims=True)
        return igrf + b + diurnal_nT(self.survey, t)[:, None] * unit

    @staticmethod
    def _body(t, roll, pitch, heading, ned):
        return np.einsum("nji,nj->ni", _rotation(heading, pitch, roll), ned)

    def body(self, t, roll, pitch, heading):
        """(B in the body frame, |F_total|) at times ``t`` with the given attitude."""
        ned = self.field_ned(t)
        return self._body(t, roll, pitch, heading, ned), np.linalg.norm(ned, axis=1)

    def vector_eddy(self, t):
        """E dB/dt (n, 3, nT) at ``t``: what the vector sensor adds to B."""
        d_body = np.column_stack([np.interp(t, self.t, self.d_body[:, k]) for k in range(3)])
        return d_body @ self.eddy.T

    def cesium(self, t):
        """The cesium's reading without noise at ``t``: ``T + TL + heading error``."""
        roll, pitch, heading = (np.interp(t, self.t, self.attitude[:, k]) for k in range(3))
        body, _ = self.body(t, roll, pitch, heading)
        total = np.linalg.norm(body, axis=1)
        u = body / total[:, None]
        du = np.column_stack([np.interp(t, self.t, self.d_u[:, k]) for k in range(3)])
        return (total + tl_features(u, total, du) @ self.coefficients
                + self.heading_error * u[:, 2])


def base_station_csv(truth_survey, start, until_s, rng):
    """The base station's record (bytes): ``time_utc,total_nT`` from 60 s before power-up to
    60 s after ``until_s``, at ``base_rate_hz``; the site's ground IGRF total + D(t) + noise."""
    d = truth_survey["diurnal"]
    t = np.arange(-60.0, until_s + 60.0 + 1e-9, 1.0 / d["base_rate_hz"])
    value = (d["base_igrf_total_nT"] + diurnal_nT(truth_survey, t)
             + rng.normal(scale=d["base_noise_nT"], size=t.size))
    start = start.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    rows = ["time_utc,total_nT"]
    for tk, v in zip(t, value):
        when = start + _dt.timedelta(milliseconds=round(tk * 1000))
        rows.append(f"{when.isoformat(timespec='milliseconds')}Z,{v:.3f}")
    return ("\n".join(rows) + "\n").encode("ascii")
