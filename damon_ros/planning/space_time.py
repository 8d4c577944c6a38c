"""Space-time certification: a *timed* trajectory against where each mover will be.

The path checks (`GraphPlanner`) certify a route against the obstacles now and swept along
their velocity over a fixed horizon (0.3 s in the bench, 1 s in the node): a static
picture. A trajectory lasting 2 s was certified against where a sphere could be in the next
0.3 s, so a sphere that reaches the path's far end after 1.5 s was never looked at. Here the
arm's state at trajectory time ``t`` is checked against each moving obstacle's predicted
region at ``t``.

Prediction model (`Prediction`): an obstacle reported with position ``p`` and velocity
``v``, its data ``age`` s old when planning starts, is at trajectory time ``t`` (horizon
``tau = age + t``) inside its shape translated by ``v * tau`` and grown by

    rho(tau) = sigma_p + (sigma_v + kappa * |v|) * tau + 0.5 * a_max * tau**2

``sigma_p`` the position error of a report, ``sigma_v`` an absolute and ``kappa`` a relative
velocity error, ``a_max`` a bound on unmodelled acceleration (0: constant velocity). A
state keeps more than ``margin + rho(tau) + step_m / 2`` from that region (the exact
distance to the translated shape, less the growth: a Minkowski sum with a ball, not a
bigger primitive).

Time resolution: between two checked instants no joint moves more than the planner's
``resolution`` rad (the rule every segment check follows) and no obstacle's region moves or
grows by more than ``step_m``; the half step in the margin then covers the region at every
instant between two checks (each lies within half an interval of a checked one). So the
instants are dense where the arm or an obstacle is fast and sparse where both are slow.

Static obstacles (reported slower than ``moving_speed_m_s``, the jitter of a tracked box)
are not checked here: the path checks certify them, at the cost they always had. No rclpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from damon_ros.core import sphere_kernels
from damon_ros.core.shapes import Shape
from damon_ros.planning.trajectory import braking_kernel


@dataclass(frozen=True)
class Prediction:
    """The obstacle prediction model and the check's time resolution (SI units)."""

    position_sigma_m: float = 0.005  # error of a reported position (ideal: noise, rounding)
    velocity_sigma_m_s: float = 0.05  # absolute error of a reported velocity
    velocity_sigma_rel: float = 0.1  # relative error of a reported velocity
    acceleration_m_s2: float = 0.0  # unmodelled acceleration bound (0 = constant velocity)
    min_age_s: float = 0.033  # data is at least this old (one camera frame) unless told
    step_m: float = 0.01  # most an obstacle's region changes between checked instants
    moving_speed_m_s: float = 0.05  # slower reports are static (a tracked box's jitter)

    def growth(self, speed: float, tau: float) -> float:
        """rho(tau): how far the region has grown ``tau`` s after the report."""
        return (self.position_sigma_m + (self.velocity_sigma_m_s + self.velocity_sigma_rel
                                         * speed) * tau + 0.5 * self.acceleration_m_s2 * tau * tau)

    def rate(self, speed: float, tau: float) -> float:
        """Upper bound on how fast the region moves or grows (m/s) up to ``tau``."""
        return (speed + self.velocity_sigma_m_s + self.velocity_sigma_rel * speed
                + self.acceleration_m_s2 * tau)


def movers(obstacles: Sequence[tuple[Shape, np.ndarray]],
           prediction: Prediction) -> tuple[tuple[Shape, np.ndarray], ...]:
    """The (shape, velocity) pairs the space-time check looks at: the moving ones."""
    return tuple((s, np.asarray(v, float)) for s, v in obstacles
                 if float(np.linalg.norm(v)) >= prediction.moving_speed_m_s)


@dataclass(frozen=True)
class Contact:
    """Where a timed trajectory meets a mover's predicted region."""

    time_s: float  # trajectory time of the first refused instant
    obstacle: int  # index into the movers
    q: np.ndarray  # the arm's state then
    region: Shape  # the mover's shape where it is predicted then (not grown)
    growth_m: float  # rho at that instant

    def describe(self) -> str:
        name = self.region.name or f"obstacle {self.obstacle}"
        return (f"{name} is predicted on the trajectory {self.time_s:.2f} s into it "
                f"(region grown by {self.growth_m:.3f} m)")


def check_instants(times: np.ndarray, positions: np.ndarray, resolution: float,
                   rate: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, states) to check: the trajectory's samples, subdivided (linearly) where a
    joint moves more than ``resolution`` or the region more than ``step`` between two, then
    thinned to the fewest that keep both bounds between consecutive instants."""
    return _instants(np.asarray(times, float), np.ascontiguousarray(positions, float),
                     resolution, rate, step)


@njit(cache=True)
def _instants(times, positions, resolution, rate, step):
    """`check_instants`, compiled (the certified-stop check asks it for every stop)."""
    pieces = np.empty(times.shape[0] - 1, np.int64)
    for i in range(pieces.shape[0]):
        dq = 0.0
        for a in range(positions.shape[1]):
            dq = max(dq, abs(positions[i + 1, a] - positions[i, a]))
        dt = times[i + 1] - times[i]
        pieces[i] = int(max(1.0, max(math.ceil(dq / resolution), math.ceil(dt * rate / step))))
    t, q = _subdivided(times, positions, pieces)
    return _thinned(t, q, resolution, rate, step)


@njit(cache=True)
def _subdivided(times, positions, pieces):
    n = int(pieces.sum()) + 1
    t_out = np.empty(n)
    q_out = np.empty((n, positions.shape[1]))
    m = 0
    for i in range(pieces.shape[0]):
        for k in range(pieces[i]):
            f = k / pieces[i]
            t_out[m] = times[i] + f * (times[i + 1] - times[i])
            q_out[m] = positions[i] + f * (positions[i + 1] - positions[i])
            m += 1
    t_out[m] = times[-1]
    q_out[m] = positions[-1]
    return t_out, q_out


@njit(cache=True)
def _thinned(times, positions, resolution, rate, step):
    keep = np.zeros(times.shape[0], np.bool_)
    keep[0] = keep[-1] = True
    last = 0
    for j in range(1, times.shape[0]):
        gap_q = np.max(np.abs(positions[j] - positions[last]))
        if gap_q > resolution or (times[j] - times[last]) * rate > step:
            keep[j - 1] = True  # the previous state is still within both bounds
            last = j - 1
    return times[keep], positions[keep]


@njit(cache=True)
def _scratch(jr, pos, hull):
    """The arrays a distance query over moved movers writes into: the arm's frames, the
    best pair, and the movers' moved positions and hull rows."""
    return (np.empty((jr.shape[0] + 1, 3, 3)), np.empty((jr.shape[0] + 1, 3)),
            np.empty(2, np.int64), pos.copy(), hull.copy())


@njit(cache=True)
def _translate(tau, velocity, kind, pos, params, hull, moved_pos, moved_hull):
    """Each packed mover translated by its velocity times ``tau`` into ``moved_pos`` and
    ``moved_hull``: its position, and a hull's face rows (corners and plane offset)."""
    for k in range(kind.shape[0]):
        dx, dy, dz = velocity[k, 0] * tau, velocity[k, 1] * tau, velocity[k, 2] * tau
        moved_pos[k, 0], moved_pos[k, 1], moved_pos[k, 2] = (pos[k, 0] + dx, pos[k, 1] + dy,
                                                            pos[k, 2] + dz)
        if kind[k] == sphere_kernels.HULL:
            for r in range(int(params[k, 1]), int(params[k, 2])):
                for c in range(3):
                    moved_hull[r, 3 * c] = hull[r, 3 * c] + dx
                    moved_hull[r, 3 * c + 1] = hull[r, 3 * c + 1] + dy
                    moved_hull[r, 3 * c + 2] = hull[r, 3 * c + 2] + dz
                moved_hull[r, 12] = hull[r, 12] - (hull[r, 9] * dx + hull[r, 10] * dy
                                                   + hull[r, 11] * dz)


@njit(cache=True)
def _first_refused(times, Q, tau0, required0, grow_lin, grow_quad, velocity, robot_args,
                   kind, pos, rot, params, hull):
    """Index of the first instant at which some mover part comes within its required
    distance (margin + rho(tau) + half step), or -1. Each part is translated by v * tau:
    its position, and a hull's face rows (corners and plane offset). One distance query an
    instant for all movers, each less its own required distance (the query's ``offset``:
    ``d - need <= 0`` exactly when ``d <= need``): the arm's pose and its bounds once."""
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot_args
    fr, fp, where, moved_pos, moved_hull = _scratch(jr, pos, hull)
    need = np.empty(kind.shape[0])
    for n in range(times.shape[0]):
        tau = tau0 + times[n]
        _translate(tau, velocity, kind, pos, params, hull, moved_pos, moved_hull)
        for k in range(kind.shape[0]):
            need[k] = required0 + grow_lin[k] * tau + grow_quad * tau * tau
        if sphere_kernels._distance_below(Q[n], 1e-12, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr,
                                          jb, kind, moved_pos, rot, params, moved_hull, fr, fp,
                                          where, 0.0, 0, need) <= 0.0:
            return n
    return -1


def first_contact(robot, times: np.ndarray, positions: np.ndarray,
                  moving: Sequence[tuple[Shape, np.ndarray]], margin: float, resolution: float,
                  prediction: Prediction, age_s: float = 0.0) -> Contact | None:
    """The first instant of the timed trajectory (``times``, ``positions``) at which the arm
    comes within ``margin`` of a mover's predicted region (module docstring), or None when
    it never does. ``robot``: the planner's robot model; the fast (sphere) model runs one
    compiled loop, the exact meshes one query per instant and mover."""
    if not moving:
        return None
    if getattr(robot, "collision", "") == "fast":
        found = _first_instant(robot, times, positions, moving, margin, resolution,
                               prediction, age_s)
        return None if found is None else _contact(*found, moving, prediction, robot)
    tau0 = max(age_s, prediction.min_age_s)
    speeds = [float(np.linalg.norm(v)) for _, v in moving]
    rate = max(prediction.rate(s, tau0 + float(times[-1])) for s in speeds)
    t, Q = check_instants(times, positions, resolution, rate, prediction.step_m)
    for ti, q in zip(t, Q, strict=True):
        for k, (shape, v) in enumerate(moving):
            tau = tau0 + ti
            need = margin + prediction.growth(speeds[k], tau) + 0.5 * prediction.step_m
            if robot.distances(q[None], [shape.moved_to(shape.position + v * tau)])[0] <= need:
                return Contact(float(ti), k, q, shape.moved_to(shape.position + v * tau),
                               prediction.growth(speeds[k], tau))
    return None


HINT_WINDOW_S = 0.25
"""`refused_at` asks the instants this close to its hint first."""


def refused_at(robot, times: np.ndarray, positions: np.ndarray,
               moving: Sequence[tuple[Shape, np.ndarray]], margin: float, resolution: float,
               prediction: Prediction, age_s: float = 0.0,
               hint_s: float | None = None) -> float | None:
    """The time of an instant that `first_contact` refuses (not necessarily the first), or
    None when it refuses none, without describing the contact (on the fast model the
    nearest mover's region there costs a distance query per mover, more than the check):
    for the questions whose answer is yes or no (a delayed start, an escape's rest). The
    instants within HINT_WINDOW_S of ``hint_s`` go first — where the same route, started
    earlier, was refused: the same instants are asked, so the same answer comes, sooner."""
    if not moving:
        return None
    if getattr(robot, "collision", "") != "fast":
        contact = first_contact(robot, times, positions, moving, margin, resolution,
                                prediction, age_s)
        return None if contact is None else contact.time_s
    m = _Movers.of(moving, prediction)
    tau0 = max(age_s, prediction.min_age_s)
    t, Q = check_instants(times, positions, resolution,
                          m.rate(prediction, tau0 + float(times[-1])), prediction.step_m)
    required0 = margin + prediction.position_sigma_m + 0.5 * prediction.step_m
    parts = [(0, len(t))]
    if hint_s is not None:
        a, b = (int(i) for i in np.searchsorted(t, [hint_s - HINT_WINDOW_S,
                                                    hint_s + HINT_WINDOW_S]))
        parts = [(a, b), (0, a), (b, len(t))]
    for a, b in parts:
        n = int(_first_refused(t[a:b], Q[a:b], tau0, required0, m.grow_lin,
                               0.5 * prediction.acceleration_m_s2, m.velocity,
                               tuple(robot.spheres.kernel_args), *m.packed))
        if n >= 0:
            return float(t[a + n])
    return None


class _Movers:
    """The movers in the kernels' arrays: packed shapes, velocities, speeds and growth rates,
    kept for the same (immutable) tuple, which a re-plan asks about dozens of times (the
    trajectory, each delayed start, each certified stop)."""

    _last: tuple | None = None

    def __init__(self, moving, prediction: Prediction) -> None:
        self.speeds = np.array([float(np.linalg.norm(v)) for _, v in moving])
        self.velocity = np.array([v for _, v in moving], float).reshape(-1, 3)
        self.grow_lin = np.array([prediction.velocity_sigma_m_s
                                  + prediction.velocity_sigma_rel * s for s in self.speeds])
        self.packed = sphere_kernels.pack_obstacles(tuple(s for s, _ in moving))

    @classmethod
    def of(cls, moving, prediction: Prediction) -> _Movers:
        last = cls._last
        if last is None or last[0] is not moving or last[1] is not prediction:
            if not isinstance(moving, tuple):  # a list may change in place: never kept
                return cls(moving, prediction)
            last = cls._last = (moving, prediction, cls(moving, prediction))
        return last[2]

    def rate(self, prediction: Prediction, horizon: float) -> float:
        """`Prediction.rate` of the fastest mover up to ``horizon``."""
        return max(prediction.rate(float(s), horizon) for s in self.speeds)


def _first_instant(robot, times, positions, moving, margin, resolution, prediction, age_s):
    """(time, state, tau0) of the first refused instant on the fast model, or None."""
    m = _Movers.of(moving, prediction)
    tau0 = max(age_s, prediction.min_age_s)
    t, Q = check_instants(times, positions, resolution,
                          m.rate(prediction, tau0 + float(times[-1])), prediction.step_m)
    required0 = margin + prediction.position_sigma_m + 0.5 * prediction.step_m
    n = int(_first_refused(t, Q, tau0, required0, m.grow_lin,
                           0.5 * prediction.acceleration_m_s2, m.velocity,
                           tuple(robot.spheres.kernel_args), *m.packed))
    return None if n < 0 else (t[n], Q[n], tau0)


def least_distance(robot, times: np.ndarray, positions: np.ndarray,
                   moving: Sequence[tuple[Shape, np.ndarray]], prediction: Prediction,
                   age_s: float = 0.0, floor: float = -math.inf) -> float:
    """Least signed distance of the states ``positions`` at ``times`` from the movers where
    they nominally are then (translated by ``v * tau``, ``tau`` as in `first_contact`; not
    grown): how close following a trajectory comes to them. Once an instant is at or
    below ``floor`` that instant's distance is returned (the question is then answered).
    On the fast model one compiled loop (a Python query per instant and mover cost a
    re-route ~10-25 ms before its search began: `GraphPlanner.follow_on_safer`)."""
    if not moving:
        return math.inf
    tau0 = max(age_s, prediction.min_age_s)
    if getattr(robot, "collision", "") == "fast":
        m = _Movers.of(moving, prediction)
        return float(_least_distance(np.asarray(times, float),
                                     np.ascontiguousarray(positions, float), tau0, floor,
                                     m.velocity, tuple(robot.spheres.kernel_args), *m.packed))
    best = math.inf
    for t, q in zip(times, positions, strict=True):
        moved = [s.moved_to(s.position + np.asarray(v, float) * (tau0 + t)) for s, v in moving]
        best = min(best, float(robot.distances(np.asarray(q, float)[None], moved)[0]))
        if best <= floor:
            break
    return best


@njit(cache=True)
def _least_distance(times, Q, tau0, floor, velocity, robot_args, kind, pos, rot, params,
                    hull):
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot_args
    fr, fp, where, moved_pos, moved_hull = _scratch(jr, pos, hull)
    best = np.inf
    for n in range(times.shape[0]):
        _translate(tau0 + times[n], velocity, kind, pos, params, hull, moved_pos, moved_hull)
        best = sphere_kernels._distance_below(Q[n], best, jr, jp, sj, sc, sr, gj, gs, ge, gc,
                                              gr, jb, kind, moved_pos, rot, params,
                                              moved_hull, fr, fp, where, floor)
        if best <= floor:
            return best
    return best


def stops_screen(robot, trajectory, stops: np.ndarray, first: int,
                 moving: Sequence[tuple[Shape, np.ndarray]], margin: float, resolution: float,
                 prediction: Prediction, tau0: float, limits, coast_s: float,
                 statics: Sequence[Shape]) -> tuple[int, int]:
    """The certified-stop check of `GraphPlanner._stop_contact` for the stops from the
    trajectory's states ``stops[first:]``, compiled on the fast model: from each, the
    braking states (`trajectory.braking_kernel`), their instants (`check_instants`, at the
    stop's own age ``tau0 + t``) against the movers with ``margin``, then the braking line
    against the ``statics`` on the fast model (margin 0). Returns (j, 1) when stop ``j``
    meets a mover, (j, 2) when the fast model refuses its line, (-1, 0) when none does: the
    caller re-asks that one stop in Python (the contact to report; the meshes for a line
    the fast model refuses), where before every stop cost ~0.5 ms of Python."""
    m = _Movers.of(moving, prediction)
    packed = robot.spheres.packed(tuple(statics)) if statics else m.packed
    j, what = _stops_screen(
        trajectory.times, trajectory.positions, trajectory.velocities,
        np.asarray(stops, np.int64), first, limits.velocity, limits.acceleration, limits.jerk,
        limits.lower, limits.upper, coast_s, tau0, prediction.min_age_s, resolution,
        m.speeds, prediction.velocity_sigma_m_s, prediction.velocity_sigma_rel,
        prediction.acceleration_m_s2, prediction.step_m,
        margin + prediction.position_sigma_m + 0.5 * prediction.step_m, m.grow_lin,
        0.5 * prediction.acceleration_m_s2, m.velocity, tuple(robot.spheres.kernel_args),
        m.packed, packed, bool(statics))
    return int(j), int(what)


@njit(cache=True)
def _stops_screen(times, positions, velocities, stops, first, vmax, amax, jmax, lower, upper,
                  coast_s, tau0, min_age, resolution, speeds, sigma_v, sigma_rel, accel, step,
                  required0, grow_lin, grow_quad, velocity, robot_args, movers, statics,
                  check_statics):
    kind, pos, rot, params, hull = movers
    s_kind, s_pos, s_rot, s_params, s_hull = statics
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot_args
    for j in range(first, stops.shape[0]):
        i = stops[j]
        bt, bq = braking_kernel(positions[i], velocities[i], vmax, amax, jmax, lower, upper,
                                coast_s, 4)
        age = max(tau0 + times[i], min_age)
        horizon = age + bt[-1]
        rate = -np.inf
        for s in speeds:  # Prediction.rate, term for term
            rate = max(rate, s + sigma_v + sigma_rel * s + accel * horizon)
        t, Q = _instants(bt, bq, resolution, rate, step)
        if _first_refused(t, Q, age, required0, grow_lin, grow_quad, velocity, robot_args,
                          kind, pos, rot, params, hull) >= 0:
            return j, 1
        if check_statics:
            end = bq[bq.shape[0] - 1].copy()
            start = positions[i].copy()
            steps = max(1, sphere_kernels.motion_steps(start, end, resolution))
            if not sphere_kernels.segment_clear(start, end, steps, 0.0, jr, jp, sj, sc, sr, gj,
                                                gs, ge, gc, gr, jb, s_kind, s_pos, s_rot,
                                                s_params, s_hull):
                return j, 2
    return -1, 0


def _contact(t: float, q: np.ndarray, tau0: float, moving, prediction: Prediction,
             robot) -> Contact:
    """The contact at instant ``t`` (fast model): the mover nearest its own region's edge
    there, found in one compiled query (`_nearest_mover`); a query per mover, each packing
    its moved shape, cost ~0.7 ms, a twentieth of a holding arm's slowest retries."""
    tau = tau0 + t
    m = _Movers.of(moving, prediction)
    k = int(_nearest_mover(np.ascontiguousarray(q, float), tau, m.grow_lin, m.velocity,
                           tuple(robot.spheres.kernel_args), *m.packed))
    shape, v = moving[k]
    return Contact(float(t), k, q, shape.moved_to(shape.position + v * tau),
                   prediction.growth(float(m.speeds[k]), tau))


@njit(cache=True)
def _nearest_mover(q, tau, grow_lin, velocity, robot_args, kind, pos, rot, params, hull):
    """Index of the mover with the least distance less its growth at ``tau`` (the terms of
    rho that all movers share leave the order as it is)."""
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot_args
    fr, fp, where, moved_pos, moved_hull = _scratch(jr, pos, hull)
    _translate(tau, velocity, kind, pos, params, hull, moved_pos, moved_hull)
    sphere_kernels._distance_below(q, np.inf, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb,
                                   kind, moved_pos, rot, params, moved_hull, fr, fp, where,
                                   -np.inf, 0, grow_lin * tau)
    return max(where[1], 0)


def predicted_region(contact: Contact, extra_m: float = 0.0) -> Shape:
    """The mover's predicted region at the contact, as one obstacle shape for a re-route
    around where it will be: a sphere, box or cylinder grown by rho (+ ``extra_m``); a
    point set as is (the margin then has to carry it)."""
    s, g = contact.region, contact.growth_m + extra_m
    if s.kind == "sphere":
        return Shape("sphere", (s.size[0] + g,), s.position, s.orientation, name=s.name)
    if s.kind == "box":
        return Shape("box", tuple(np.asarray(s.size) + 2 * g), s.position, s.orientation,
                     name=s.name)
    if s.kind == "cylinder":
        return Shape("cylinder", (s.size[0] + g, s.size[1] + 2 * g), s.position,
                     s.orientation, name=s.name)
    return s


def warm_up(robot) -> None:
    """Compile the kernels (or load them from the disk cache) before the first real plan."""
    if getattr(robot, "collision", "") != "fast":
        return
    q = np.zeros((2, 7))
    q[1, 0] = 0.1
    for where in ([2.0, 2.0, 2.0], [0.0, 0.0, 0.3]):  # a miss, then a contact at the base
        probe = ((Shape("sphere", (0.05,), np.array(where)), np.array([0.1, 0.0, 0.0])),
                 (Shape("points", (), np.array(where), points=np.eye(3) * 0.05),
                  np.array([0.0, 0.1, 0.0])))
        first_contact(robot, np.array([0.0, 0.5]), q, probe, 0.01, 0.02, Prediction())
        refused_at(robot, np.array([0.0, 0.5]), q, probe, 0.01, 0.02, Prediction(),
                   hint_s=0.2)
        least_distance(robot, np.array([0.0, 0.5]), q, probe, Prediction(), floor=0.0)
        if hasattr(robot, "limits"):  # a moving state's stop, against movers and a static
            from damon_ros.planning.trajectory import Trajectory

            rates = np.array([[0.0] * 7, [0.2] + [0.0] * 6])
            stops_screen(robot, Trajectory(np.array([0.0, 0.5]), q, rates, np.zeros((2, 7))),
                         np.array([1]), 0, probe, 0.01, 0.02, Prediction(), 0.033,
                         robot.limits, 0.03, (probe[0][0],))
