"""A multirotor survey flight: phases, commanded attitude, attitude dynamics, position and the
Earth field along the track.

Phases (seconds from power-up, t = 0): ``ground`` (engines off; the GPS acquires its fix),
``takeoff`` (vertical climb to ``height_m``), ``calibration`` (hovering: on each of the
headings, a turn onto it, then rolls, pitches and yaws, each for a third of what is left),
``survey`` (a turn onto the first line, then ``legs`` straight lines flown back and forth,
each joined to the next by a hovering turn and a sideways step of ``spacing_m``), ``tie``
(with ``tie_lines`` > 0: tie lines perpendicular to the lines, evenly spaced along them at
``(j + 1/2) / tie_lines`` of their length, each crossing all lines with ``spacing_m`` of
overrun on each side, flown back and forth, heading along the tie line; a min-jerk move at
the same peak speed, heading already on the tie line, from the last line's end to the first
tie line and from each tie line's end to the next), ``landing`` (vertical descent) and
``ground`` again. :attr:`Track.lines` lists each line's straight part (the move along it).

Position: the commanded path, minimum-jerk on each move (climb, line, step, descent), so
velocity and acceleration are smooth. The calibration manoeuvres are flown in place (the
drift that tilting would cause is not modelled).

Attitude: a multirotor tilts to accelerate. The commanded roll and pitch are the tilt that
gives the path's horizontal acceleration plus a linear drag (``drag_per_s`` times the
airspeed, no wind): ``pitch = -atan(a_forward / g)``, ``roll = atan(a_right / g)``, with the
calibration swings added on top; the commanded heading is the line's course (or the
calibration heading). Each axis follows its command through a second-order response
(``natural_hz``, ``damping``) with a rate limit, integrated at 100 Hz; turbulence
(band-limited noise of ``turbulence_deg`` standard deviation and ``turbulence_s``
correlation) is added while airborne (half of it on the heading).

Earth field: IGRF (ppigrf) at the position and altitude once a second, on the scenario's
date, interpolated to the magnetometer samples and rotated into the body frame. With
dipoles, interference or a diurnal field (:mod:`.geophysics`) the field is
:class:`~.geophysics.SurveyField`'s, the anomaly evaluated at each sample's own position.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from .scenario import Flight, _field_ned, _rotation, _smooth_noise

__all__ = ["Track", "make_flight", "survey_seconds", "DT", "GRAVITY"]

#: Integration step of the attitude dynamics, seconds.
DT = 0.01
GRAVITY = 9.81
METRES_PER_DEGREE = 111_320.0
#: Height above which the aircraft counts as airborne (turbulence), metres.
AIRBORNE_M = 0.3


@dataclass
class Track:
    """The dense (100 Hz) path and the phases; ``until`` the end of the arrays."""
    t: np.ndarray
    north: np.ndarray
    east: np.ndarray
    up: np.ndarray
    v_north: np.ndarray
    v_east: np.ndarray
    phases: list                 # [(name, start_s, end_s)]
    flight_end: float            # touch-down after the landing
    takeoff: float
    lat: float
    lon: float
    ground_alt: float
    field_t: np.ndarray          # the IGRF grid (1 Hz)
    field_ned: np.ndarray        # (n, 3) nT
    lines: list = field(default_factory=list)   # [(kind "line"|"tie", index, start, end)]
    attitude: np.ndarray | None = None          # (n, 3) roll, pitch, heading (radians)
    geo: object = None           # geophysics.SurveyField when the field has survey parts

    def at(self, t, values):
        return np.interp(t, self.t, values)

    def position(self, t):
        """Latitude, longitude (degrees) and altitude (m) at ``t``."""
        north, east, up = (self.at(t, v) for v in (self.north, self.east, self.up))
        lat = self.lat + north / METRES_PER_DEGREE
        lon = self.lon + east / (METRES_PER_DEGREE * np.cos(np.radians(self.lat)))
        return lat, lon, self.ground_alt + up

    def total(self, t):
        """|B_earth| at ``t`` (nT): what the cesium magnetometer reads."""
        return np.interp(t, self.field_t, np.linalg.norm(self.field_ned, axis=1))


def _min_jerk(x):
    x = np.clip(x, 0.0, 1.0)
    return x ** 3 * (10 - 15 * x + 6 * x ** 2)


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


class _Plan:
    """Piecewise commands on the dense grid, phase by phase."""

    def __init__(self, t, heading0):
        self.t = t
        n = t.size
        self.north = np.zeros(n)
        self.east = np.zeros(n)
        self.up = np.zeros(n)
        self.heading = np.full(n, heading0)
        self.roll_extra = np.zeros(n)
        self.pitch_extra = np.zeros(n)
        self.phases = []
        self.lines = []
        self.now = 0.0
        self.pos = np.zeros(3)          # north, east, up at `now`
        self.head = heading0            # unwrapped

    def _span(self, seconds):
        sel = (self.t >= self.now) & (self.t < self.now + seconds)
        return sel, (self.t[sel] - self.now) / seconds

    def _hold_after(self):
        sel = self.t >= self.now
        self.north[sel], self.east[sel], self.up[sel] = self.pos
        self.heading[sel] = self.head

    def turn_to(self, heading):
        self.head = self.head + _wrap(heading - self.head)
        return self.head

    def move(self, seconds, delta, heading=None):
        """Move by ``delta`` (north, east, up) with a minimum-jerk profile; the heading
        command steps to ``heading`` at the start."""
        if heading is not None:
            self.turn_to(heading)
        sel, x = self._span(seconds)
        s = _min_jerk(x)
        for axis, arr in enumerate((self.north, self.east, self.up)):
            arr[sel] = self.pos[axis] + delta[axis] * s
        self.heading[sel] = self.head
        self.pos = self.pos + np.asarray(delta, float)
        self.now += seconds
        self._hold_after()

    def manoeuvre(self, seconds, heading, turn_s, roll, pitch, yaw):
        """Hover on ``heading``: turn onto it, then rolls, pitches and yaws."""
        self.turn_to(heading)
        if turn_s > 0:
            self.move(turn_s, (0.0, 0.0, 0.0))
        third = (seconds - turn_s) / 3
        for extra, amplitude in ((self.roll_extra, roll), (self.pitch_extra, pitch)):
            sel, x = self._span(third)
            extra[sel] = amplitude * np.sin(2 * np.pi * 2 * x)       # two full swings
            self.now += third
        sel, x = self._span(third)
        self.heading[sel] = self.head + yaw * np.sin(2 * np.pi * x)   # one swing
        self.now += third
        self._hold_after()


def _tie_moves(survey):
    """The tie lines' moves from the last line's end, in the lines' frame (along the first
    line's course, to its right): [(seconds, (d_along, d_side), heading offset (radians
    from the course), tie index or None for a move between tie lines)]."""
    length, spacing, speed = survey.leg_length_m, survey.spacing_m, survey.speed_m_s
    width = (survey.legs - 1) * spacing
    along, side = (length if survey.legs % 2 else 0.0), width
    moves = []
    for j in range(survey.tie_lines):
        towards = -1.0 if j % 2 == 0 else 1.0             # first tie back across the lines
        start = (length * (j + 0.5) / survey.tie_lines,
                 width + spacing if towards < 0 else -spacing)
        delta = (start[0] - along, start[1] - side)
        seconds = max(survey.turn_s, 1.875 * float(np.hypot(*delta)) / speed)
        moves.append((seconds, delta, towards * np.pi / 2, None))
        tie = towards * (width + 2 * spacing)
        moves.append((1.875 * abs(tie) / speed, (0.0, tie), towards * np.pi / 2, j))
        along, side = start[0], start[1] + tie
    return moves


def survey_seconds(survey):
    """The survey phase's and the tie phase's seconds (0 for none)."""
    if not survey.legs:
        return 0.0, 0.0
    leg_s = 1.875 * survey.leg_length_m / survey.speed_m_s
    lines = survey.turn_s * survey.legs + leg_s * survey.legs
    ties = sum(m[0] for m in _tie_moves(survey)) if survey.tie_lines else 0.0
    return lines, ties


def make_flight(scenario, errors, rng, horizon):
    """The flight of ``scenario`` from t = 0 to ``horizon`` s: (:class:`Flight` sampled at
    the magnetometer's rate, :class:`Track`). ``rng`` draws the turbulence and the sensor
    noise."""
    f = scenario.flight
    cal, survey, dyn = f.calibration, f.survey, f.dynamics
    mag = scenario.channels["mag"]
    t = np.arange(0.0, horizon + DT, DT)
    headings = np.radians(cal.headings_deg)
    plan = _Plan(t, headings[0])

    def phase(name, body):
        start = plan.now
        body()
        plan.phases.append((name, start, plan.now))

    phase("ground", lambda: plan.move(f.ground.seconds, (0.0, 0.0, 0.0)))
    takeoff = plan.now
    phase("takeoff", lambda: plan.move(f.takeoff.seconds, (0.0, 0.0, f.takeoff.height_m)))

    def calibration():
        for h in headings:
            plan.manoeuvre(cal.seconds, h, min(cal.turn_s, cal.seconds / 2),
                           np.radians(cal.roll_deg), np.radians(cal.pitch_deg),
                           np.radians(cal.yaw_deg))
    phase("calibration", calibration)

    def lines():
        course = np.radians(survey.course_deg)
        leg_s = 1.875 * survey.leg_length_m / survey.speed_m_s    # min-jerk peak speed
        plan.move(survey.turn_s, (0.0, 0.0, 0.0), heading=course)
        for leg in range(survey.legs):
            c = course + np.pi * (leg % 2)
            start = plan.now
            plan.move(leg_s, (survey.leg_length_m * np.cos(c),
                              survey.leg_length_m * np.sin(c), 0.0), heading=c)
            plan.lines.append(("line", leg, start, plan.now))
            if leg + 1 < survey.legs:
                side = course + np.pi / 2
                plan.move(survey.turn_s, (survey.spacing_m * np.cos(side),
                                          survey.spacing_m * np.sin(side), 0.0),
                          heading=c + np.pi)
    if survey.legs:
        phase("survey", lines)

    def ties():
        course = np.radians(survey.course_deg)
        for seconds, (d_along, d_side), offset, index in _tie_moves(survey):
            start = plan.now
            plan.move(seconds, (d_along * np.cos(course) - d_side * np.sin(course),
                                d_along * np.sin(course) + d_side * np.cos(course), 0.0),
                      heading=course + offset)
            if index is not None:
                plan.lines.append(("tie", index, start, plan.now))
    if survey.legs and survey.tie_lines:
        phase("tie", ties)
    phase("landing", lambda: plan.move(f.landing.seconds, (0.0, 0.0, -f.takeoff.height_m)))
    flight_end = plan.now
    if flight_end >= horizon:
        raise ValueError("the flight does not fit its horizon")
    plan.phases.append(("ground", flight_end, horizon))

    # Commanded tilt from the path's acceleration and drag, in the commanded heading's frame.
    v_n, v_e = np.gradient(plan.north, DT), np.gradient(plan.east, DT)
    a_n, a_e = np.gradient(v_n, DT), np.gradient(v_e, DT)
    ch, sh = np.cos(plan.heading), np.sin(plan.heading)
    a_fwd = a_n * ch + a_e * sh + survey.drag_per_s * (v_n * ch + v_e * sh)
    a_right = -a_n * sh + a_e * ch + survey.drag_per_s * (-v_n * sh + v_e * ch)
    commands = np.column_stack([np.arctan2(a_right, GRAVITY) + plan.roll_extra,
                                -np.arctan2(a_fwd, GRAVITY) + plan.pitch_extra,
                                plan.heading])
    attitude = _respond(commands, dyn)
    airborne = np.convolve((plan.up > AIRBORNE_M).astype(float),
                           np.ones(50) / 50, mode="same")
    width = max(1, int(round(dyn.turbulence_s / DT)))
    scale = np.radians(dyn.turbulence_deg)
    for axis, share in ((0, 1.0), (1, 1.0), (2, 0.5)):
        attitude[:, axis] += airborne * _smooth_noise(rng, t.size, width, share * scale)

    # The Earth field once a second along the track, then at the magnetometer's samples.
    field_t = np.arange(0.0, horizon + 1.0, 1.0)
    north_s, east_s, up_s = (np.interp(field_t, t, v) for v in (plan.north, plan.east, plan.up))
    site = scenario.site
    lat_s = site.lat_deg + north_s / METRES_PER_DEGREE
    lon_s = site.lon_deg + east_s / (METRES_PER_DEGREE * np.cos(np.radians(site.lat_deg)))
    when = scenario.start.replace(tzinfo=None)
    field_ned = _field_ned(lat_s, lon_s, (site.ground_alt_m + up_s), when)
    track = Track(t=t, north=plan.north, east=plan.east, up=plan.up, v_north=v_n, v_east=v_e,
                  phases=plan.phases, flight_end=flight_end, takeoff=takeoff,
                  lat=site.lat_deg, lon=site.lon_deg, ground_alt=site.ground_alt_m,
                  field_t=field_t, field_ned=field_ned, lines=plan.lines, attitude=attitude)

    ts = np.arange(mag.first_s, horizon, 1.0 / mag.rate_hz)
    roll, pitch, heading = (np.interp(ts, t, attitude[:, k]) for k in range(3))
    if scenario.geophysics_on:
        from .geophysics import SurveyField, survey_truth
        track.geo = SurveyField(survey_truth(scenario, plan.lines), track, attitude, DT)
        body, total = track.geo.body(ts, roll, pitch, heading)
        sensed = body + track.geo.vector_eddy(ts)
    else:
        ned = np.column_stack([np.interp(ts, field_t, field_ned[:, k]) for k in range(3)])
        body = np.einsum("nji,nj->ni", _rotation(heading, pitch, roll), ned)
        total = np.linalg.norm(ned, axis=1)
        sensed = body
    vn, ve = np.interp(ts, t, v_n), np.interp(ts, t, v_e)
    flight = Flight(t=ts, roll=roll, pitch=pitch, heading=heading, b_earth=body,
                    b_meas=errors.apply(sensed, rng), total=total,
                    lat=site.lat_deg, lon=site.lon_deg, altitude_m=site.ground_alt_m,
                    start=when, errors=errors,
                    north_m=np.interp(ts, t, plan.north), east_m=np.interp(ts, t, plan.east),
                    course=np.arctan2(ve, vn), speed=np.hypot(vn, ve))
    return flight, track


def _respond(commands, dyn):
    """Each axis of ``commands`` (n, 3: roll, pitch, heading; radians) through a
    second-order response with a rate limit (semi-implicit Euler at :data:`DT`)."""
    omega = 2 * np.pi * dyn.natural_hz
    limit = np.radians([dyn.max_rate_deg_s, dyn.max_rate_deg_s, dyn.max_yaw_rate_deg_s])
    return _second_order(np.ascontiguousarray(commands, dtype=np.float64),
                         omega * omega * DT, 2 * dyn.damping * omega * DT, limit, DT)


@numba.njit(cache=True)
def _second_order(commands, k1, k2, limit, dt):
    out = np.empty_like(commands)
    for axis in range(commands.shape[1]):
        x = commands[0, axis]
        v = 0.0
        for i in range(commands.shape[0]):
            v = min(max(v + k1 * (commands[i, axis] - x) - k2 * v, -limit[axis]), limit[axis])
            x += v * dt
            out[i, axis] = x
    return out
