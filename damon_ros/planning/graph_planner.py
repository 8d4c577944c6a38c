"""The certified DAMON planner: latent-graph routing, proven free by exact geometry.

``plan`` and ``replan`` route over the two-layer latent graph (module 2 of the paper) and
certify every edge they return against *all* current obstacles with the conservative fast
collision model at ≤ ``resolution`` rad steps (lazy evaluation: an edge is checked only
when a shortest path uses it; an invalid edge is removed and the search repeated). The
search starts in the subgraph of the obstacle node nearest the obstacle point closest to
the arm (the paper's top-layer lookup) and widens to more subgraphs only when no safe
route exists there. Nothing unchecked is ever returned: when no certified route exists the
result says so and the caller holds position.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from damon_ros.core.limits import IK_LIMIT_MARGIN, READY, START_LIMIT_TOLERANCE, JointLimits
from damon_ros.core.shapes import Shape
from damon_ros.learning.graph import LatentGraph
from damon_ros.planning.graph_search import GraphSearch
from damon_ros.planning.space_time import (
    HINT_WINDOW_S,
    Contact,
    Prediction,
    first_contact,
    least_distance,
    predicted_region,
    refused_at,
    stops_screen,
)


@dataclass(frozen=True)
class PoseGoal:
    """A TCP (``panda_hand_tcp``) target in the base frame; quaternion ``[x, y, z, w]``."""

    position: np.ndarray
    orientation: np.ndarray
    position_tolerance: float = 0.01
    orientation_tolerance: float = 0.05


@dataclass(frozen=True)
class Scene:
    """Obstacles now, and the same obstacles swept over the prediction horizon.

    The first segment of a path (it leaves the arm's current state) is certified against
    ``now`` with a margin that lets the arm move away from an obstacle that has already come
    close; every later segment is certified against ``ahead``. ``moving`` (shape, velocity)
    pairs, reported ``age_s`` ago, are where the timed trajectory is checked in space and
    time (`space_time`): none for a scene of bare shapes."""

    now: tuple[Shape, ...]
    ahead: tuple[Shape, ...]
    moving: tuple[tuple[Shape, np.ndarray], ...] = ()
    age_s: float = 0.0

    @classmethod
    def of(cls, obstacles) -> Scene:
        if isinstance(obstacles, Scene):
            return obstacles
        shapes = tuple(obstacles)
        return cls(shapes, shapes)

    def statics(self) -> Scene:
        """The scene without its movers (``now[i]`` swept into ``ahead[i]``): what the
        path checks still look at when the movers are checked in space and time. Made once
        a scene: the same tuples each time are the same packed arrays for the kernels
        (`SphereModel.packed`), where a re-plan asks for them a few hundred times."""
        if not self.moving or len(self.now) != len(self.ahead):
            return self
        kept = self.__dict__.get("_statics")
        if kept is None:
            ids = {id(s) for s, _ in self.moving}
            keep = [i for i, s in enumerate(self.now) if id(s) not in ids]
            kept = Scene(tuple(self.now[i] for i in keep), tuple(self.ahead[i] for i in keep))
            object.__setattr__(self, "_statics", kept)  # frozen: not a field, not compared
        return kept


@dataclass(frozen=True)
class PlannerConfig:
    """Explicit planner settings (the planner node exposes each as a parameter)."""

    margin: float = 0.01  # λ, m of clearance required on top of the conservative fast model
    resolution: float = 0.02  # rad, max joint step between checked states on an edge
    k_attach: int = 10  # graph vertices the start and the goal are each tied to
    widen: tuple[int, ...] = (1, 8, 0)  # obstacle nodes searched per attempt (0 = all)
    max_lazy_iterations: int = 300
    shortcut: bool = True
    velocity_scale: float = 0.9
    acceleration_scale: float = 0.8  # leaves the PID room to correct (tracking < 0.02 rad)
    jerk_scale: float = 0.8
    trajectory_dt: float = 0.01
    ik_seeds: int = 16
    time_budget_s: float = 0.25  # a route search gives up (and says so) after this long
    fallback_budget_s: float = 0.1  # RRT-Connect when the graph has no route (0 = none);
    # doubled on each further failure toward the same goal, up to 8x
    experience_routes: int = 32  # certified fallback routes kept for reuse
    handover_s: float = 0.005  # with a fallback, the graph's lazy search hands over after this
    exact_goal_margin: float = 0.002  # m on the exact meshes for a goal close to an object
    prediction: Prediction = Prediction()  # where movers will be (space-time certification)
    space_time_reroutes: int = 1  # re-routes around a mover's predicted region, then refuse

    def graph_budget(self) -> float:
        """s the graph's lazy search may take: the whole time budget without a fallback;
        with one, at most ``handover_s`` — where the graph has no quick route (clutter it was
        not built for: MotionBenchMaker), its lazy iterations only delay the search that
        finds one (a plan there took 0.25 s of graph and 0.05 s of RRT-Connect)."""
        if self.fallback_budget_s > 0.0:
            return min(self.time_budget_s, self.handover_s)
        return self.time_budget_s


APPROACH_RAD = (0.1, 0.2, 0.4)
"""Perturbation scales searched for an approach state into a goal only the meshes accept."""
QUICK_HANDOVER_SHARE = 0.2
"""The share of its budget the graph gets when its last search toward the same goal found
no route (1 ms of the node's 5 ms handover): its lazy iterations there only delayed the
search that finds one (stress bench: re-route p99 per band 20.2/16.0/15.4/12.7 ->
17.3/14.6/11.9/10.0 ms, the same outcomes)."""
EXPERIENCE_REACH_RAD = 1.0
"""A stored route is tried for a query whose start and goal are this close to it."""
MOVING_RAD_S = 0.05
"""Joint speed above which a new route starts where the arm will stop (`_route_moving`)."""
START_DELAYS_S = (0.2, 0.4, 0.7, 1.0, 1.4)
"""Waits tried before a trajectory a mover would cross (`GraphPlanner._delayed`); below the
runtime's stall time (1.5 s), after which a still arm is re-planned."""
BRAKE_LATENCY_S = 0.03
"""Coasting before braking starts: planning, DDS and a controller tick (measured 10-30 ms)."""
STOP_EVERY_RAD = 0.1
"""A published trajectory's certified stop is checked from states this far apart (and at
most `STOP_EVERY_S`): between two, the brakes start within a few centimetres of a checked
one, which the braking check's extra `STOP_MARGIN_M` covers."""
STOP_EVERY_S = 0.1
STOP_MARGIN_M = 0.01
RECHECK_SLACK_M = 0.005
"""m less margin when the running trajectory is re-checked against the movers than when it
was certified (never below 0): one perception noise sigma. Without it a trajectory certified
by a millimetre was refused at the next frame when the mover's reported position jittered,
and the arm re-routed 3x as often as with the swept check (stress bench, slow movers)."""
REST_HORIZON_S = 1.0
"""An arm at rest (holding, or at the end of a stop or an escape) is checked this long
against the movers' predictions: longer than the hold's retry and a re-route's latency."""
SWERVE_CANDIDATES = 8
"""An escape's swerve (`GraphPlanner._swerve`) is tried toward this many of the clearest
candidates at most: each costs ~1-3 ms (its states' chords certified), and it runs while a
fast arm closes on a mover."""
SWERVE_BRANCH_S = BRAKE_LATENCY_S
"""A swerve follows the stop already sent at least this long before it turns: its coast, the
time a command is allowed to reach the controller (later where the computation takes
longer: `SWERVE_LATE_FACTOR`). Turning after 0.03 or
0.04 s: 650 of 650 generated G scenes (seeds 2607-2609, ideal perception) without contact;
after 0.06 s, 649 (G-s2608-298 touched: no turn from that late cleared the ball)."""
SWERVE_LATE_FACTOR = 1.5
"""A swerve turns no sooner than this many times the computation's time so far after the
measured state (`GraphPlanner._swerve_branch`): the rest of the computation (the swerve's
own candidates) takes a fraction of what came before it."""
SWERVE_CHORD_S = 0.02
"""A swerve's states are certified as the chords between samples this far apart: at the
Panda's 15 rad/s^2 a chord leaves the curve by under 1e-3 rad."""
PULL_ROUNDS = 10
"""Rounds of the pull toward the neighbours' midpoints that shortens a graph route."""
CLEARANCES_KEPT = 8
"""(state, obstacle tuple) pairs whose clearance `GraphPlanner.clearance` keeps."""
KEPT_START_RAD = 1e-3
"""A search starting this close to where the last route found started (an arm at rest
there) tries that route first (`GraphPlanner._kept`)."""
RETRY_AROUND_S = 0.005
"""A holding arm's retry may leave work to the next retry (`GraphPlanner._may_defer`): it
searches around the predicted region of a mover that refused its route only when it has
taken less than this so far, and then on the graph alone. Those second searches, with
RRT-Connect where the graph had no route, were most of the retries over 10 ms."""
RETRY_DEFERRALS = 3
"""Retries in a row that may leave work to the next: then one searches in full, so a route
that needs the full search is still found (after at most this many retries' wait)."""
RETRY_SHORTEN_S = 0.004
"""A holding arm's retry that may defer and has taken longer than this when RRT-Connect
returns a route leaves the route's shortening (and its certification) to the next retry,
which takes it up where this one stopped (`GraphPlanner._pending_route`): sampling and
shortening in one retry were most of the retries still over 10 ms (2-11 ms each)."""
RETRY_GRAPH_S = 0.002
"""A holding arm's retry that may defer and whose graph search found no route after longer
than this leaves RRT-Connect to the next retry, whose graph then hands over after
QUICK_HANDOVER_SHARE of its budget: a graph miss and a sampling search in one retry took
8-13 ms."""


@dataclass
class PlanResult:
    """What a plan or re-plan produced. ``path`` rows are certified straight-line waypoints;
    when ``success`` is False, ``reason`` says why and nothing should be executed."""

    success: bool
    reason: str
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    trajectory: object | None = None
    goal_q: np.ndarray | None = None
    subgraph: int = -1
    searched_nodes: int = 0
    lazy_iterations: int = 0
    edges_checked: int = 0
    edges_rejected: int = 0
    timing_ms: dict[str, float] = field(default_factory=dict)
    source: str = "graph"  # graph | experience | rrtconnect | escape | last resort (`escape`)

    @property
    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.path, axis=0), axis=1).sum())


class _Query:
    """One routing problem: start, goal, obstacles, and the edge-validity cache."""

    START = -1
    GOAL = -2

    def __init__(self, planner: GraphPlanner, q_start, q_goal, scene: Scene,
                 prior: _Query | None = None):
        self.p = planner
        self.q_start = q_start
        self.q_goal = q_goal
        self.scene = scene
        self.start_margin = planner._start_margin(q_start, scene.ahead)
        # the relaxed start margin is for what is already close; the rest keeps λ
        self.start_near, self.start_far = scene.ahead, ()
        self.split = self.start_margin < planner.config.margin and len(scene.ahead) > 1
        if self.split:
            self.start_near, self.start_far = planner._split_near(q_start, scene.ahead)
        self.valid: dict[tuple[int, int], bool] = {}
        self.search = GraphSearch(*planner.csr) if planner.graph is not None else None
        self.checked = 0
        self.rejected = 0
        self.iterations = 0
        self.deadline = time.perf_counter() + planner.config.graph_budget()
        self.order: np.ndarray | None = None  # obstacle nodes nearest first (`_node_order`)
        self.added: tuple[Shape, ...] = ()  # obstacles beyond the prior query's
        self.free_before: set[tuple[int, int]] = set()  # certified by the prior query
        if prior is not None and self._extends(prior):
            self._inherit(prior)

    def _extends(self, prior: _Query) -> bool:
        """The same start and goal, the same obstacles now, and the prior query's swept
        obstacles followed by more: a search around a mover's predicted region."""
        n = len(prior.scene.ahead)
        return (prior.p is self.p and prior.scene.now is self.scene.now
                and len(self.scene.ahead) >= n
                and all(a is b for a, b in zip(prior.scene.ahead, self.scene.ahead[:n],
                                               strict=False))
                and np.array_equal(prior.q_start, self.q_start)
                and np.array_equal(prior.q_goal, self.q_goal))

    def _inherit(self, prior: _Query) -> None:
        """What the prior query decided and still holds with more obstacles: a refused
        segment stays refused (blocked graph edges included); a certified one only needs
        the added obstacles (`_added_certified`); its obstacle-node order (the start and the
        obstacles now are the same). A link of the start is taken over only when the start
        margin's rules are the same (the added region can lower the start margin or split
        the obstacles into near and far). Without this the search around a mover's region
        re-checked every edge of the first search: the second search cost as much as the
        first (family D, 1-7 ms)."""
        self.order = prior.order
        self.added = self.scene.ahead[len(prior.scene.ahead):]
        same_start = self.start_margin == prior.start_margin and self.split == prior.split
        for key, ok in prior.valid.items():
            if self.START in key and not same_start:
                continue
            if ok:
                self.free_before.add(key)
            else:
                self.valid[key] = False
        if self.search is not None and prior.search is not None:
            self.search.blocked[:] = prior.search.blocked

    def config(self, v: int) -> np.ndarray:
        if v == self.START:
            return self.q_start
        if v == self.GOAL:
            return self.q_goal
        return self.p.graph.q[v]

    def edge_free(self, u: int, v: int) -> bool:
        key = (u, v) if u < v else (v, u)
        known = self.valid.get(key)
        if known is None:
            q0, q1 = self.config(u), self.config(v)
            if key in self.free_before:  # self-collision too was checked then
                known = self._added_certified(q0, q1, first=self.START in key,
                                              last=self.GOAL in key)
            else:
                # graph edges on the fast model alone (``band`` off): a refused edge is
                # cheap and the search has others; the band's mesh queries (up to 64 a
                # segment) had doubled the lazy search's time on the public scenes. The
                # goal's own segment still goes to the meshes when only they accept it.
                known = self.segment_certified(q0, q1, first=self.START in key,
                                               last=self.GOAL in key, band=False)
                if known and key[0] < 0:  # not a graph edge: self-collision not verified
                    known = self.p.robot.segment_self_collision_free(q0, q1)
            self.valid[key] = known
            self.checked += 1
            self.rejected += not known
            if not known and key[0] >= 0:
                self.search.block(*key)
        return known

    def _added_certified(self, q0: np.ndarray, q1: np.ndarray, first: bool,
                         last: bool) -> bool:
        """`segment_certified` (graph-edge rules: fast model, no band) of a segment the
        prior query certified against its obstacles: the added obstacles alone, each with
        the margin `segment_certified` gives it (the fast model's answer for a set of
        obstacles is its answer for each). A goal segment it refuses goes to the meshes
        against every obstacle, as there."""
        margin = self.start_margin if first else self.p.config.margin
        groups = [(self.added, margin)]
        if first and self.start_far:
            near = {id(o) for o in self.start_near}
            groups = [(tuple(o for o in self.added if id(o) in near), margin),
                      (tuple(o for o in self.added if id(o) not in near),
                       self.p.config.margin)]
        free = all(not group or self.p.segment_free(q0, q1, group, m, False)
                   for group, m in groups)
        if not free and last and self.p.goal_exact:
            free = self.p.exact.segment_free(q0, q1, self.scene.ahead,
                                             margin=self.p.config.exact_goal_margin,
                                             resolution=self.p.config.resolution)
        return free

    def link_weight(self, u: int, v: int, w: float) -> float:
        """``w`` for a start or goal link not known to be blocked; inf for one that is."""
        return math.inf if self.valid.get((u, v) if u < v else (v, u)) is False else w

    def segment_certified(self, q0: np.ndarray, q1: np.ndarray, first: bool,
                          last: bool = False, exact: bool = True, band: bool = True) -> bool:
        """Obstacle check of one segment: a first segment against the obstacles now with the
        start margin, any other against the swept obstacles with the full margin. A last
        segment into a goal that only the exact meshes accept (a grasp pose close to an
        object) is certified on the exact meshes when the conservative model refuses it."""
        margin = self.start_margin if first else self.p.config.margin
        # first: the swept obstacles too, something falling onto the first segment counts
        if first and self.start_far:
            free = self.p.segment_free(q0, q1, self.start_near, margin, exact and band) and \
                self.p.segment_free(q0, q1, self.start_far, self.p.config.margin,
                                    exact and band)
        else:
            free = self.p.segment_free(q0, q1, self.scene.ahead, margin, exact and band)
        if not free and exact and last and self.p.goal_exact:
            free = self.p.exact.segment_free(q0, q1, self.scene.ahead,
                                             margin=self.p.config.exact_goal_margin,
                                             resolution=self.p.config.resolution)
        return free


class GraphPlanner:
    """Plans and re-plans Panda motions over a :class:`LatentGraph`.

    ``robot`` is a fast (conservative) :class:`damon_ros.core.robot.Robot`; ``risk`` is an optional
    callable ``(q, obstacles) -> p(collision)`` (the GMR) used by :meth:`path_threatened`.
    """

    def __init__(self, graph: LatentGraph, robot, limits: JointLimits,
                 config: PlannerConfig | None = None, risk=None) -> None:
        self.graph = graph
        self.robot = robot
        self.limits = limits
        self.config = config or PlannerConfig()
        self.risk = risk
        self.goal_q: np.ndarray | None = None
        self.goal_exact = False  # the goal is certified on the exact meshes only
        self._exact = None
        # graph None: a subclass finds routes another way (the OMPL baselines)
        self._safe_ids = np.flatnonzero(graph.safe) if graph is not None else np.zeros(0, int)
        self._tree = cKDTree(graph.q[self._safe_ids]) if graph is not None else None
        # the adjacency in the compiled search's dtypes, converted once
        self.csr = None if graph is None else (
            np.ascontiguousarray(graph.indptr, np.int64),
            np.ascontiguousarray(graph.indices, np.int64),
            np.ascontiguousarray(graph.weights, np.float64))
        self.experience: list[np.ndarray] = []  # certified fallback routes, newest last
        self._fallback_failures = 0  # toward the current goal: escalates the budget
        self._moving_start = False  # routing from a moving arm (`_route_moving`): no escalation
        self._escalate = True  # False during a re-route on a threat (`replan`): no escalation
        self._graph_missed = False  # the last route toward this goal: the graph had none
        self._pending: np.ndarray | None = None  # a sampled route left to the next retry
        self._retry_started = 0.0  # `time.perf_counter` at the start of this `replan`
        self._kept_route: tuple[np.ndarray, object, str] | None = None  # `_kept`'s
        self._rerouting = False  # during `replan` (`_kept`)
        self._defer = False  # during `replan` with ``defer`` (`_may_defer`)
        self._deferred = False  # this search left work to the next retry
        self._deferrals = 0  # retries in a row that left work to the next
        self._heuristic_cache: tuple[np.ndarray, np.ndarray] | None = None  # (goal, A*'s)
        self._clearances: list[tuple[bytes, tuple, float]] = []  # `clearance`'s, newest first
        # during `_route_in_time`: {"query": the last route search's `_Query`}, which a
        # search around a mover's predicted region extends (`_Query._inherit`); else None
        self._reuse: dict | None = None

    @property
    def exact(self):
        """The exact-mesh model, for goals the conservative model cannot certify."""
        if self._exact is None:
            from damon_ros.core.robot import Robot

            self._exact = Robot("mesh", self.limits.profile,
                                finger_opening=self.robot.finger_opening)
        return self._exact

    def warm_up(self) -> None:
        """Run every code path once (kernel compilation, caches, the timing library) so the
        first real goal is planned at full speed, not after seconds of start-up work."""
        q = self.graph.q[self._safe_ids[0]] if self.graph is not None else READY
        probe = Shape("sphere", (0.05,), np.array([2.0, 2.0, 2.0]))
        self.segment_free(q, q + 0.01, [probe], self.config.margin)
        self.robot.distances(q[None], [probe])
        self.robot.self_collision(q)  # the link-box screen's kernel
        if self.robot.collision == "fast":  # the exact band's fast side
            self.robot.spheres.band_states(q[None], [probe], self.config.margin, 0.0, 1)
        from damon_ros.planning import space_time
        from damon_ros.planning.trajectory import Trajectory, braking_states

        space_time.warm_up(self.robot)
        zero = np.zeros((2, 7))
        _stop_states(Trajectory(np.array([0.0, 0.1]), np.vstack([q, q]), zero, zero))
        braking_states(q, np.full(7, 0.5), self.limits, BRAKE_LATENCY_S)  # a stop flagged
        if self.config.fallback_budget_s > 0.0:  # a first fallback should not pay for these
            if self.robot.collision == "fast":
                from damon_ros.planning import path_shortcutting, rrt_connect

                rrt_connect.warm_up(self.robot.spheres)
                path_shortcutting.warm_up(self.robot.spheres)
            else:
                import ompl.geometric  # noqa: F401
        if self.graph is not None:
            goal_q = self.graph.q[self._safe_ids[len(self._safe_ids) // 2]]
            self.plan(q, goal_q, [probe])
            self.replan(q, [probe])
            self.goal_q = None

    # ---- geometry -------------------------------------------------------------------
    def segment_free(self, q0: np.ndarray, q1: np.ndarray, obstacles: Sequence[Shape],
                     margin: float, exact: bool = True) -> bool:
        """A straight joint-space segment is free of obstacles (with margin) at every state
        no more than ``resolution`` rad apart; ``exact`` False: without the meshes' say in
        the fast model's contact band (shortcuts: a refusal there costs nothing)."""
        return bool(self.robot.segment_free(q0, q1, obstacles, margin=margin,
                                            resolution=self.config.resolution,
                                            exact_band=exact))

    def clearance(self, q: np.ndarray, obstacles: Sequence[Shape]) -> float:
        """The robot model's distance alone (no witness points: a start margin is asked for
        at every path check, ~20 µs this way against ~0.4 ms with them). The last
        CLEARANCES_KEPT answers for obstacle tuples are kept: a re-plan asks the same one
        for each query it builds (the route, the brake, the re-route around a region)."""
        if not obstacles:
            return math.inf
        q = np.asarray(q, float)
        if not isinstance(obstacles, tuple):
            return float(self.robot.distances(q[None], obstacles)[0])
        key = q.tobytes()
        for kept_q, kept, d in self._clearances:
            if kept is obstacles and kept_q == key:
                return d
        d = float(self.robot.distances(q[None], obstacles)[0])
        self._clearances = [(key, obstacles, d), *self._clearances[:CLEARANCES_KEPT - 1]]
        return d

    def _split_near(self, q: np.ndarray, obstacles: Sequence[Shape]
                    ) -> tuple[tuple[Shape, ...], tuple[Shape, ...]]:
        """(obstacles within 2λ of ``q``, the others): only the first ones get the relaxed
        start margin. With one margin for all, a mover's swept shape overlapping the start
        let a whole direct route (one first segment) graze a static box by 10 mm on the
        fast model, 2 mm into it on the meshes (stress bench S-v0.6-1-s12-002)."""
        d = np.array([self.clearance(q, (o,)) for o in obstacles])
        near = d <= 2.0 * self.config.margin
        return (tuple(o for o, n in zip(obstacles, near, strict=True) if n),
                tuple(o for o, n in zip(obstacles, near, strict=True) if not n))

    def _start_margin(self, q: np.ndarray, obstacles: Sequence[Shape]) -> float:
        """The margin demanded of a first segment (it leaves the current state): λ, or less
        when an obstacle has already come closer than λ, so that the arm can move away.
        When the obstacle is already inside the fast model's conservative envelope (its
        distance ≤ 0, while the meshes still have ≥ 4 mm, see collision.FAST_MODEL_MARGIN), the
        first segment may only move away: no state on it may come any closer."""
        clearance = self.clearance(q, obstacles)
        if clearance > 0.0:
            return min(self.config.margin, 0.5 * clearance)
        return clearance - 1e-4

    def _mover_margin(self, q: np.ndarray, scene: Scene) -> float:
        """The margin of the space-time checks from ``q``: λ, or the start margin when a
        mover (where it is now, not swept) is already closer, never below 0. With the swept
        shapes, a fast mover's 0.3 s sweep over the arm made it negative, and the whole
        remaining trajectory was then checked as if penetration were allowed: a ball
        closing at 1.4 m/s went unflagged until it touched (stress scene S-v1-1.5-012)."""
        return max(0.0, min(self.config.margin,
                            self._start_margin(q, tuple(s for s, _ in scene.moving))))

    # ---- goals ----------------------------------------------------------------------
    def resolve_goal(self, goal, q_near: np.ndarray, obstacles: Sequence[Shape],
                     avoid: np.ndarray | None = None):
        """Joint goal for a pose (IK nearest ``q_near`` with clearance; not within 0.3 rad of
        ``avoid``, when given) or a joint vector. Returns ``(q_goal, reason)``; ``q_goal``
        is None when the goal is refused."""
        if isinstance(goal, PoseGoal):
            result = self.robot.ik(goal.position, goal.orientation, q_near=q_near,
                                   obstacles=obstacles, min_clearance=self.config.margin,
                                   n_seeds=self.config.ik_seeds, avoid=avoid)
            if not result.success:
                return None, f"goal pose refused: {result.reason}"
            q_goal = np.asarray(result.q, float)
        else:
            q_goal = np.asarray(goal, float).reshape(-1)
            if q_goal.shape != (7,) or not np.all(np.isfinite(q_goal)):
                return None, "goal joints must be 7 finite values"
            if not self.limits.within(q_goal):
                return None, "goal joints are outside the joint limits"
        if self.robot.self_collision(q_goal):
            return None, "goal configuration is in self-collision"
        self.goal_exact = False
        if obstacles and self.clearance(q_goal, obstacles) <= self.config.margin:
            exact = float(self.exact.clearance(q_goal, obstacles).distance)
            if exact <= self.config.exact_goal_margin:
                return None, (f"goal configuration is {exact:.3f} m from an obstacle on the "
                              f"exact meshes (needs > {self.config.exact_goal_margin} m)")
            self.goal_exact = True
        return q_goal, ""

    # ---- planning -------------------------------------------------------------------
    def plan(self, q_start: np.ndarray, goal, obstacles=(), qd_start=None) -> PlanResult:
        """Plan from ``q_start`` to a :class:`PoseGoal` or joint goal, certified against all
        ``obstacles`` (shapes, or a :class:`Scene`); remembers the goal for :meth:`replan`.
        ``qd_start``: the arm's joint velocities, when it is moving (see `_route_moving`)."""
        t0 = time.perf_counter()
        q_start = np.asarray(q_start, float)
        problem = self._check_start(q_start)
        if problem:
            return PlanResult(False, problem)
        scene = Scene.of(obstacles)
        q_goal, reason = self.resolve_goal(goal, q_start, scene.now)
        t_ik = time.perf_counter()
        if q_goal is None:
            self.goal_q = None
            return PlanResult(False, reason, timing_ms={"ik": 1e3 * (t_ik - t0)})
        if self.goal_q is None or not np.array_equal(self.goal_q, q_goal):
            self._fallback_failures = self._deferrals = 0
            self._graph_missed, self._pending = False, None
        self.goal_q = q_goal
        result = self._route_in_time(q_start, qd_start, q_goal, scene)
        result.timing_ms["ik"] = 1e3 * (t_ik - t0)
        result.timing_ms["total"] = 1e3 * (time.perf_counter() - t0)
        return result

    def replan(self, q_now: np.ndarray, obstacles=(), qd_now=None,
               escalate: bool = True, defer: bool = False) -> PlanResult:
        """Re-route from the current state toward the goal of the last successful plan.
        ``escalate`` False: the sampling fallback keeps its first budget (a re-route on a
        threat: `_fallback`). ``defer`` (a holding arm's retry, whose arm holds a certified
        stop): a slow search may be left to the next retry (`_may_defer`)."""
        t0 = self._retry_started = time.perf_counter()
        if self.goal_q is None:
            return PlanResult(False, "no goal to re-plan toward")
        q_now = np.asarray(q_now, float)
        problem = self._check_start(q_now)
        if problem:
            return PlanResult(False, problem)
        self._escalate = escalate
        self._rerouting, self._defer, self._deferred = True, defer, False
        try:
            result = self._route_in_time(q_now, qd_now, self.goal_q, Scene.of(obstacles))
        finally:
            self._escalate, self._rerouting, self._defer = True, False, False
        self._deferrals = self._deferrals + 1 if self._deferred else 0
        result.timing_ms["total"] = 1e3 * (time.perf_counter() - t0)
        return result

    def _route_in_time(self, q_start, qd_start, q_goal, scene: Scene) -> PlanResult:
        """`_route_moving`, its timed trajectory then certified in space and time against
        the scene's movers (`space_time.first_contact`): the arm at trajectory time t
        against where each mover is predicted at t, also beyond the swept horizon of the
        path checks. Where a mover's region meets the trajectory, an arm at rest first
        tries waiting at its start (re-timed, `_delayed`); else the route is searched again
        with that region (at the contact instant, grown) as one more obstacle, up to
        ``space_time_reroutes`` times, unless the region covers the start or the goal; a
        trajectory still refused is not returned (the caller holds and retries). Margin: λ,
        or the start margin when something is already closer (as for a first segment). A
        scene without movers costs nothing here."""
        if not scene.moving:
            return self._route_moving(q_start, qd_start, q_goal, scene)
        self._reuse = {}
        try:
            return self._route_around_movers(q_start, qd_start, q_goal, scene)
        finally:
            self._reuse = None

    def _route_around_movers(self, q_start, qd_start, q_goal, scene: Scene) -> PlanResult:
        """`_route_in_time` for a scene with movers; a search around a predicted region
        takes over what the search before it decided (`self._reuse`)."""
        result = self._route_moving(q_start, qd_start, q_goal, scene)
        t0 = time.perf_counter()
        margin = self._mover_margin(q_start, scene)
        at_rest = qd_start is None or float(np.max(np.abs(qd_start))) < MOVING_RAD_S

        def late() -> bool:  # a holding retry that spent RETRY_AROUND_S leaves the rest
            return at_rest and self._may_defer() and self._retry_spent() > RETRY_AROUND_S

        for attempt in range(self.config.space_time_reroutes + 1):
            if not result.success or result.trajectory is None:
                break
            contact = self._contact(result.trajectory, scene, margin)
            if contact is None:
                break
            # the route around a region, refused in turn, is re-timed only when quick
            skip_delays = attempt > 0 and late()
            delayed = self._delayed(result.trajectory, scene, margin,
                                    contact.time_s) if at_rest and not skip_delays else None
            if delayed is not None:  # re-timed: wait where it stands until the mover passed
                result.trajectory = delayed
                break
            region = predicted_region(contact)
            # a region over the goal or the start leaves no route around it: refuse now
            hopeless = min(self.clearance(q_goal, (region,)),
                           self.clearance(q_start, (region,))) <= margin
            late_now = skip_delays or late()
            self._deferred |= late_now
            if attempt == self.config.space_time_reroutes or hopeless or late_now:
                why = "; a retry searches around it only when quick" if late_now else ""
                result = PlanResult(False, f"no route certified in space and time: "
                                    f"{contact.describe()}{why}; holding position",
                                    goal_q=q_goal, edges_checked=result.edges_checked)
                break
            scene = replace(scene, ahead=(*scene.ahead, region))
            result = self._route_moving(q_start, qd_start, q_goal, scene)
            if not result.success:
                result.reason = (f"no route certified in space and time: {contact.describe()}"
                                 f"; around its predicted region: {result.reason}")
        result.timing_ms["space_time"] = 1e3 * (time.perf_counter() - t0)
        return result

    def _contact(self, trajectory, scene: Scene, margin: float):
        """`space_time.first_contact` of a timed trajectory with the scene's movers, then of
        the stops from its states (`_stop_contact`): a trajectory is published only with a
        certified stop at every instant."""
        contact = first_contact(self.robot, trajectory.times, trajectory.positions,
                                scene.moving, margin, self.config.resolution,
                                self.config.prediction, scene.age_s)
        return contact if contact is not None else self._stop_contact(trajectory, scene,
                                                                        margin)

    def _refusal(self, trajectory, scene: Scene, margin: float,
                 hint_s: float | None = None, not_before: float = math.inf) -> float | None:
        """The time of a refused instant or stop when `_contact` is not None, else None:
        without describing the contact, for the yes/no of a delayed start or an escape's
        rest. With ``hint_s`` (where a similar trajectory was refused) the stops from states
        near it go first, then the instants near it (`space_time.refused_at`), then the
        rest of each: the same checks in another order, so the same answer, sooner (a
        delayed start was mostly refused by a stop near where the last one was)."""
        if hint_s is not None:
            contact = self._stop_contact(trajectory, scene, margin, hint_s, "near",
                                         describe=False)
            if contact is not None:
                return contact.time_s
        t = refused_at(self.robot, trajectory.times, trajectory.positions, scene.moving,
                       margin, self.config.resolution, self.config.prediction, scene.age_s,
                       hint_s)
        if t is not None:
            return t
        # a finite ``not_before`` (`_stop_contact`) needs each stop's contact time
        contact = self._stop_contact(trajectory, scene, margin, hint_s,
                                     "all" if hint_s is None else "far",
                                     describe=not math.isinf(not_before), not_before=not_before)
        return None if contact is None else contact.time_s

    def _stop_contact(self, trajectory, scene: Scene, margin: float,
                      hint_s: float | None = None, part: str = "all", describe: bool = True,
                      not_before: float = math.inf):
        """Where braking from one of the trajectory's states would meet a mover's predicted
        region, or None: from states at most STOP_EVERY_RAD / STOP_EVERY_S apart, the stop
        the runtime would send there (`stop_trajectory`: coast, then full-limit brake along
        the velocity) is checked in space and time from that instant on, with STOP_MARGIN_M
        more margin for the states between two checked ones. Braking past a waypoint (the
        stop is straight along the velocity, the path turns there) is checked against the
        static obstacles on the fast model. A scene without movers is not checked: its
        stops stay on certified segments but for such an overshoot (the cost of a static
        scene stays what it was). The end state is checked at rest for REST_HORIZON_S: an
        arm that arrives just before a mover passes through its goal has no stop there.
        On the fast model the stops are screened in one compiled call
        (`space_time.stops_screen`); a stop it flags is asked again here, as the meshes'
        model asks every one. ``part``: "all" the stops, or only those from states within
        HINT_WINDOW_S of ``hint_s`` ("near"), or all but those and the rest at the end
        ("far"); "all" with a ``hint_s`` asks the near ones first (a yes/no question: the
        contact is then not the first in time). ``describe`` False (the yes/no of
        `_refusal`): a stop the compiled screen finds meeting a mover is not asked again
        (that re-ask only described the contact), nor is a stop flagged on the statics
        asked about the movers the screen cleared it of; the contact returned then says
        only when (the stop's start, obstacle -1).
        ``not_before`` finite (an escape from a state whose own stop is refused then,
        `escape`): a stop that meets a mover no earlier than that is no worse than holding
        and passes; the rest at the end does not (it is where the escape goes)."""
        if not scene.moving:
            return None
        p = self.config.prediction
        tau0 = max(scene.age_s, p.min_age_s)
        statics = scene.statics().ahead
        from damon_ros.planning.trajectory import braking_states

        stops = _stop_states(trajectory)
        if hint_s is not None:
            near = np.abs(trajectory.times[stops] - hint_s) <= HINT_WINDOW_S
            stops = {"near": stops[near], "far": stops[~near]}.get(
                part, np.concatenate([stops[near], stops[~near]]))
        j = 0
        fast = self.robot.collision == "fast"
        while j < len(stops):
            what = 0
            if fast:
                j, what = stops_screen(self.robot, trajectory, stops, j, scene.moving,
                                       margin + STOP_MARGIN_M, self.config.resolution, p,
                                       tau0, self.limits, BRAKE_LATENCY_S, statics)
                if j < 0:
                    break
            i = int(stops[j])
            j += 1
            q, qd = trajectory.positions[i], trajectory.velocities[i]
            if what == 1 and not describe:
                return Contact(float(trajectory.times[i]), -1, q, scene.moving[0][0], 0.0)
            times, states = braking_states(q, qd, self.limits, BRAKE_LATENCY_S)
            contact = None if what == 2 and not describe else first_contact(
                self.robot, times, states, scene.moving, margin + STOP_MARGIN_M,
                self.config.resolution, p, tau0 + float(trajectory.times[i]))
            if contact is not None and trajectory.times[i] + contact.time_s < not_before:
                return replace(contact, time_s=float(trajectory.times[i]) + contact.time_s)
            if statics and not self.segment_free(q, states[-1], statics, 0.0, exact=False) \
                    and not self.exact.segment_free(q, states[-1], statics, margin=0.0,
                                                    resolution=self.config.resolution):
                return Contact(float(trajectory.times[i]), -1, q, statics[0], 0.0)
        if part == "near":
            return None
        # the last stop is staying at the end: the arm arrives, then rests there
        end = trajectory.positions[-1]
        if not describe:
            t = refused_at(self.robot, np.array([0.0, REST_HORIZON_S]), np.vstack([end, end]),
                           scene.moving, margin, self.config.resolution, p,
                           tau0 + float(trajectory.times[-1]))
            return None if t is None else Contact(float(trajectory.times[-1]) + t, -1, end,
                                                  scene.moving[0][0], 0.0)
        contact = first_contact(self.robot, np.array([0.0, REST_HORIZON_S]),
                                np.vstack([end, end]), scene.moving, margin,
                                self.config.resolution, p, tau0 + float(trajectory.times[-1]))
        if contact is not None:
            return replace(contact, time_s=float(trajectory.times[-1]) + contact.time_s)
        return None

    def rest_contact(self, q: np.ndarray, qd: np.ndarray | None, scene: Scene,
                     margin: float | None = None):
        """Where stopping now (`stop_trajectory`) and staying at rest for REST_HORIZON_S
        would meet a mover's predicted region, or None: is braking in place a safe place
        to go? The braking line is checked against the static obstacles too (start-margin
        rules: it leaves the current state)."""
        from damon_ros.planning.trajectory import held_until

        q = np.asarray(q, float)
        stop = self.stop_trajectory(q, qd)
        if margin is None:
            margin = self._mover_margin(q, scene)
        statics = scene.statics()
        if statics.now and not _Query(self, q, q, statics).segment_certified(
                q, stop.positions[-1], first=True):
            return Contact(0.0, -1, q, statics.now[0], 0.0)
        return first_contact(self.robot, *_timed(held_until(stop, stop.duration
                                                            + REST_HORIZON_S)),
                             scene.moving, margin, self.config.resolution,
                             self.config.prediction, scene.age_s)

    def trajectory_threatened(self, q_now: np.ndarray, remaining: np.ndarray, times,
                              positions, obstacles) -> tuple[bool, str]:
        """`path_threatened` in space and time: the static obstacles against the rest of
        the path as today (swept, start margin for what leaves the current state), the
        movers against the rest of the timed trajectory (``times`` from now, ``positions``
        from ``q_now``) where each is predicted to be then. A mover that will not meet the
        arm is no reason to stop; one that will is caught however far ahead it meets it.
        The movers' margin is RECHECK_SLACK_M less than at planning (hysteresis)."""
        scene = Scene.of(obstacles)
        if not scene.moving:
            return self.path_threatened(q_now, remaining, scene)
        threatened, why = self.path_threatened(q_now, remaining, scene.statics())
        if threatened:
            return threatened, why
        margin = max(0.0, self._mover_margin(np.asarray(q_now, float), scene)
                     - RECHECK_SLACK_M)
        contact = first_contact(self.robot, np.asarray(times, float),
                                np.asarray(positions, float), scene.moving, margin,
                                self.config.resolution, self.config.prediction, scene.age_s)
        if contact is not None:
            return True, contact.describe()
        return False, ""

    def follow_on_safer(self, q_now: np.ndarray, qd_now: np.ndarray | None,
                        remaining: np.ndarray, times, positions, obstacles) -> bool:
        """The last resort where no route is certified: does following the running
        trajectory on (then REST_HORIZON_S at rest at its end) keep more nominal clearance
        from the movers — each at its reported velocity, no growth — than braking here,
        and stay nominally clear? The static obstacles must still certify the rest of the
        path as at planning. On the stress bench, 27 of 1,000 arms that braked on a mover
        at rest until it moved at 0.56-1.49 m/s were touched; 21 of them, followed on,
        passed it at 17-29 mm."""
        scene = Scene.of(obstacles)
        if not scene.moving or self.path_threatened(q_now, remaining, scene.statics())[0]:
            return False
        # the brake first: following on must beat it and 0, and the (longer) follow-on
        # check ends at its first instant that does not
        floor = max(0.0, self._nominal_clearance(
            *_timed(self.stop_trajectory(q_now, qd_now)), scene))
        return self._nominal_clearance(np.asarray(times, float), np.asarray(positions, float),
                                       scene, floor) > floor

    def _nominal_clearance(self, times: np.ndarray, positions: np.ndarray, scene: Scene,
                           floor: float = -math.inf, step_s: float = 0.02) -> float:
        """Least distance (fast model) of the timed states, then the last one held
        REST_HORIZON_S, from the movers moving on at their reported velocities (at or
        below ``floor``: some distance at or below it, `space_time.least_distance`)."""
        instants = np.arange(0.0, times[-1] + REST_HORIZON_S + step_s, step_s)
        states = np.column_stack([np.interp(instants, times, positions[:, j])
                                  for j in range(positions.shape[1])])
        return least_distance(self.robot, instants, states, scene.moving,
                              self.config.prediction, scene.age_s, floor)

    def _delayed(self, trajectory, scene: Scene, margin: float, refused_s: float):
        """``trajectory`` started after a wait at its first state (the shortest of
        START_DELAYS_S) when that makes it certified in space and time, else None: a mover
        about to cross the way is let past, the waiting arm checked against it as well.
        ``refused_s``: where the trajectory was refused, in its own time; each delayed start
        is asked there first (`_refusal`), then where the last delay was refused."""
        from damon_ros.planning.trajectory import Trajectory, concatenate

        q0 = trajectory.positions[:1]
        rest = np.zeros_like(q0)
        for delay in START_DELAYS_S:
            wait = Trajectory(np.array([0.0, delay]), np.vstack([q0, q0]),
                              np.vstack([rest, rest]), np.vstack([rest, rest]))
            delayed = concatenate(wait, trajectory)
            refused_at_s = self._refusal(delayed, scene, margin, refused_s + delay)
            if refused_at_s is None:
                return delayed
            refused_s = refused_at_s - delay
        return None

    def stop_trajectory(self, q: np.ndarray, qd: np.ndarray | None):
        """How the arm at ``q`` moving at ``qd`` is stopped: `trajectory.stop_trajectory`
        at the full acceleration and jerk limits after BRAKE_LATENCY_S of coasting (a
        one-point hold when it is at rest). Every stop the planner sends is one of these,
        never an empty trajectory, which JTC rejects."""
        from damon_ros.planning.trajectory import stop_trajectory

        return stop_trajectory(q, qd, self.limits, coast_s=BRAKE_LATENCY_S,
                               dt=self.config.trajectory_dt)

    def braking_point(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Where a moving arm comes to rest when braked now: the end of `stop_trajectory`
        (on the straight line along ``qd``), inside the position limits."""
        return self.inside_limits(self.stop_trajectory(q, qd).positions[-1])

    def inside_limits(self, q: np.ndarray) -> np.ndarray:
        """``q`` clipped to the joint limits less IK's margin: a waypoint on a limit is a
        motion that ends on it, which a Franka stops with a reflex (the soak hit joint 1's
        limit through a braking point and through an escape candidate)."""
        return np.clip(q, self.limits.lower + IK_LIMIT_MARGIN,
                       self.limits.upper - IK_LIMIT_MARGIN)

    def keeps_limit_margin(self, q: np.ndarray) -> bool:
        """Whether ``q`` (one state or rows of states) lies inside the joint limits less
        IK's margin: `inside_limits` leaves it as it is."""
        return bool(np.array_equal(self.inside_limits(q), q))

    def _route_moving(self, q_start, qd_start, q_goal, scene: Scene) -> PlanResult:
        """`_route`, for an arm that may be moving. A trajectory starts at rest, so the
        controller brakes the arm past ``q_start`` before it follows one: the route starts
        where the arm stops, and the braking segment before it is certified too (first-
        segment rules). Without that, a goal changed mid-motion sent the arm 0.1-0.2 rad
        along its old direction, through space nobody had checked (a contact with a box in
        the soak)."""
        if qd_start is None or float(np.max(np.abs(qd_start))) < MOVING_RAD_S:
            return self._route_to_goal(q_start, q_goal, scene)
        from damon_ros.planning.trajectory import concatenate

        brake = self.stop_trajectory(q_start, np.asarray(qd_start, float))
        q_stop = brake.positions[-1]
        if not self.keeps_limit_margin(q_stop):
            return PlanResult(False, "braking from the current speed ends too close to a "
                              "joint limit; holding position", goal_q=q_goal)
        query = _Query(self, q_start, q_stop, scene)
        if not query.segment_certified(q_start, q_stop, first=True):
            return PlanResult(False, "braking from the current speed is not certified free; "
                              "holding position", goal_q=q_goal)
        self._moving_start = True
        try:
            result = self._route_to_goal(q_stop, q_goal, scene)
        finally:
            self._moving_start = False
        if result.success:
            # the trajectory starts from the measured position *and velocity*: the brake
            # along the line (certified above), then the route from where it ends at rest
            # (the route's own trajectory is the timing of its path: not timed twice)
            route = result.trajectory if result.trajectory is not None else \
                self._time_parameterize(result.path)
            result.path = np.vstack([q_start[None], result.path])
            result.trajectory = concatenate(brake, route)
        return result

    def _route_to_goal(self, q_start, q_goal, scene: Scene) -> PlanResult:
        """`_route`, through an approach state when only the exact meshes accept the goal
        (a grasp pose millimetres from an object): the route is found to a state near the
        goal that the fast model certifies, and one short segment into the goal is certified
        on the meshes. Without it every search edge into the goal was a mesh query (0.4 s
        of a 0.25 s budget on MotionBenchMaker shelves) and a sampling search could not
        reach the goal at all (its states must be fast-model valid)."""
        approach = self._approach(q_start, q_goal, scene) if self.goal_exact else None
        if approach is None:
            return self._route(q_start, q_goal, scene)
        result = self._route(q_start, approach, scene)
        if result.success:
            result.path = np.vstack([result.path, q_goal[None]])
            result.trajectory = self._time_parameterize(result.path)
        result.goal_q = q_goal
        return result

    def _approach(self, q_start, q_goal, scene: Scene, tries: int = 12,
                  rng: np.random.Generator | None = None) -> np.ndarray | None:
        """A state near ``q_goal`` with the full margin on the fast model whose straight
        segment into the goal is certified (exact meshes for the goal's end): the nearest
        of random perturbations of the goal (0.1-0.4 rad) and graph vertices near it whose
        segment passes, at most ``tries`` segments checked. None: no such state (the route
        is then searched into the goal itself)."""
        rng = rng or np.random.default_rng(0)
        pool = [self._retreat(q_goal, scene.ahead)]
        pool += [self.inside_limits(q_goal + rng.uniform(-a, a, (16, 7))) for a in APPROACH_RAD]
        if self._tree is not None:
            _, idx = self._tree.query(q_goal, k=min(16, len(self._safe_ids)))
            pool.append(self.graph.q[self._safe_ids[np.atleast_1d(idx)]])
        pool = np.vstack(pool)
        clear = self.robot.distances(pool, scene.ahead) if scene.ahead else np.full(
            len(pool), math.inf)
        query = _Query(self, q_start, q_goal, scene)
        order = [i for i in np.argsort(np.linalg.norm(pool - q_goal, axis=1))
                 if clear[i] > self.config.margin]
        for i in order[:tries]:
            if not self.robot.self_collision(pool[i]) and \
                    query.segment_certified(pool[i], q_goal, first=False, last=True) and \
                    self.robot.segment_self_collision_free(pool[i], q_goal):
                return pool[i]
        return None

    def _retreat(self, q_goal: np.ndarray, obstacles: Sequence[Shape], step: float = 0.02,
                 steps: int = 25) -> np.ndarray:
        """States on a climb of the fast model's clearance from ``q_goal`` (finite-difference
        gradient, ``step`` rad a move): the way out of a grasp pocket. Random perturbations
        of a goal inside a shelf mostly push the hand into the shelf; the gradient points
        away from what is close. Returns up to three states that keep the full margin,
        nearest the goal first, possibly none (also on the meshes alone: no gradient)."""
        if not obstacles or self.robot.collision != "fast":
            return np.empty((0, 7))
        q, out, eye = q_goal.copy(), [], np.eye(7) * 1e-4
        for _ in range(steps):
            d = self.robot.distances(np.vstack([q, q + eye, q - eye]), obstacles)
            if d[0] > self.config.margin:
                out.append(q.copy())
                if len(out) == 3:
                    break
            grad = d[1:8] - d[8:]
            norm = float(np.linalg.norm(grad))
            if not np.isfinite(norm) or norm <= 0.0:
                break
            q = self.inside_limits(q + step * grad / norm)
        return np.array(out).reshape(-1, 7)

    def _check_start(self, q: np.ndarray) -> str:
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            return "start state must be 7 finite joint positions"
        if not self.limits.within(q, tolerance=START_LIMIT_TOLERANCE):
            return "start state is outside the joint limits"
        return ""

    def _route(self, q_start, q_goal, scene: Scene) -> PlanResult:
        t0 = time.perf_counter()
        reuse = self._reuse
        query = _Query(self, q_start, q_goal, scene, None if reuse is None else reuse.get(
            "query"))
        around_region = reuse is not None and "query" in reuse
        if reuse is not None:
            reuse["query"] = query
        # a search around a mover's predicted region: the kept route is the one just refused
        kept = None if around_region else self._kept(query)
        if kept is not None:
            result = PlanResult(True, "", kept[0], kept[1], q_goal, source=kept[2])
            result.timing_ms["search"] = 1e3 * (time.perf_counter() - t0)
            return result
        missed_before = self._graph_missed
        if missed_before:  # the graph had no route here last time: hand over sooner
            query.deadline = min(query.deadline,
                                 t0 + QUICK_HANDOVER_SHARE * self.config.graph_budget())
        order = query.order
        if order is None:
            order = query.order = self._node_order(q_start, scene.now)
        path_ids, searched = None, 0
        for width in self.config.widen:
            searched = len(order) if width == 0 else min(width, len(order))
            active = np.zeros(self.graph.n_vertices, bool)
            for m in order[:searched]:
                active[self.graph.members[m]] = True
            active &= self.graph.safe
            path_ids = self._lazy_astar(query, active)
            if path_ids is not None or searched == len(order) or \
                    time.perf_counter() >= query.deadline:
                break
        t_search = time.perf_counter()
        self._graph_missed = path_ids is None
        result = PlanResult(False, "", goal_q=q_goal, subgraph=int(order[0]) if len(order) else -1,
                            searched_nodes=searched, lazy_iterations=query.iterations)
        if path_ids is None:
            budget = " within the time budget" if time.perf_counter() >= query.deadline else ""
            result.reason = (f"no certified route to the goal in the graph{budget} "
                             f"({query.checked} edges checked, {query.rejected} blocked)")
            deferred = self._may_defer() and (around_region or (
                not missed_before and t_search - t0 > RETRY_GRAPH_S))
            self._deferred |= deferred
            path, source, note = (None, "", "; RRT-Connect is left to the next retry") \
                if deferred else self._fallback(query)
            if path is None:
                result.reason += f"{note}; holding position"
            else:
                result.success, result.path, result.source = True, path, source
                result.reason = ""
                result.trajectory = self._time_parameterize(path)
        else:
            path = np.array([query.config(v) for v in path_ids])
            if self.config.shortcut:
                path = self._graph_shortened(path, query)
            result.success, result.path = True, path
            result.trajectory = self._time_parameterize(path)
        if result.success:
            self._kept_route = (result.path, result.trajectory, result.source)
        t_end = time.perf_counter()
        result.edges_checked, result.edges_rejected = query.checked, query.rejected
        result.timing_ms.update(search=1e3 * (t_search - t0), shortcut_and_timing=1e3 * (
            t_end - t_search))
        return result

    def _kept(self, query: _Query) -> tuple[np.ndarray, object, str] | None:
        """In a re-route (`replan`; a new goal is searched afresh): the last route `_route`
        found, with its timing and source, when this query starts where it did (within
        KEPT_START_RAD: an arm still at rest there) toward the same goal and the route is
        certified for the obstacles now (`_certified`); else None. An arm
        waiting out a mover (a delayed start) is re-routed at each frame that shows the
        mover later than predicted, and each search found the same route again: on the
        stress bench 24 re-routes in one wait, 8-12 ms each, most of it the search, its
        shortening and its timing. A holding arm's retries repeat one search too. A route
        refused here (something now lies on it) leaves the search as before.
        Two rules differ from a stored route's (`_from_experience`), both because the
        search after a refusal found no graph route and sampled anew, at 8-20 ms:
        - the fast screen (`_screened`) is not asked: RRT-Connect's routes often pass only
          in the meshes' contact band (15 of the 30 re-routes over 10 ms on 120 stress
          scenes, seed 1205);
        - from an arm at rest, the route is certified against what stands still
          (`Scene.statics`), not the movers' swept shapes: the space-time check after it
          (`_route_in_time`) certifies it against where the movers will be, and delays its
          start or refuses it. All 148 re-routes over 10 ms on 500 stress scenes (up to
          0.6 m/s, seed 1606) came from arms at rest, waiting or holding; 140 of them
          searched (measured with the first rule alone). A route searched around a mover's
          predicted region is certified against that region too."""
        if self._kept_route is None or not self._rerouting:
            return None
        path, trajectory, source = self._kept_route
        if not np.array_equal(path[-1], query.q_goal) or \
                float(np.max(np.abs(path[0] - query.q_start))) > KEPT_START_RAD:
            return None
        if not np.array_equal(path[0], query.q_start):  # the arm settled a little: re-timed
            path, trajectory = np.vstack([query.q_start[None], path[1:]]), None
        statics = query.scene.statics()  # itself when a predicted region was added
        if statics is not query.scene and not self._moving_start:
            query = _Query(self, query.q_start, query.q_goal, statics)
        if not self._certified(path, query):
            return None
        if trajectory is None:
            trajectory = self._time_parameterize(path)
        return path, trajectory, source

    def _from_experience(self, query: _Query) -> np.ndarray | None:
        """A stored fallback route that starts and ends near this query's (within
        EXPERIENCE_REACH_RAD), re-certified for the obstacles now; the newest first. On the
        fast model a route goes to `_certified` only when one compiled call finds all of it
        clear (`_screened`): a route the obstacles now block was mostly refused at its
        waypoints, and certifying it segment by segment first cost up to 5 ms of a re-route
        (stress bench), time the graph search then lacked."""
        for route in reversed(self.experience):
            ends = (np.min(np.linalg.norm(route - query.q_start, axis=1)),
                    np.min(np.linalg.norm(route - query.q_goal, axis=1)))
            if max(ends) > EXPERIENCE_REACH_RAD:
                continue
            path = _via(route, query.q_start, query.q_goal)
            query.checked += len(path) - 1
            if self._screened(path, query) and self._certified(path, query):
                return path
        return None

    def _screened(self, path: np.ndarray, query: _Query) -> bool:
        """False when the fast model alone refuses some segment of ``path`` (the first at
        the start margin, the others at λ; a last segment into a goal that only the meshes
        accept is left to `_certified`). True says nothing more: `_certified` decides. A
        route that only the meshes' contact band would pass is not reused: the searches
        after it find a route there."""
        if self.robot.collision != "fast" or not query.scene.ahead:
            return True
        if self.goal_exact:
            path = path[:-1]
        if len(path) < 2:
            return True
        margins = np.full(len(path) - 1, self.config.margin)
        margins[0] = min(margins[0], query.start_margin)
        return self.robot.spheres.route_clear(path, margins, self.config.resolution,
                                              query.scene.ahead)

    def _may_defer(self) -> bool:
        """Whether this search may leave work to the next retry (RETRY_AROUND_S,
        RETRY_GRAPH_S): a holding arm's retry (`replan` with ``defer``, from rest), after
        fewer than RETRY_DEFERRALS such retries in a row. The mover that refused a route
        has usually moved on by the next retry, and the route kept (`_kept`) or a quick
        search then passes."""
        return self._defer and self._deferrals < RETRY_DEFERRALS and not self._moving_start

    def _retry_spent(self) -> float:
        """Seconds since this `replan` began: what the deferral rules (RETRY_AROUND_S,
        RETRY_SHORTEN_S) weigh."""
        return time.perf_counter() - self._retry_started

    def _fallback(self, query: _Query) -> tuple[np.ndarray | None, str, str]:
        """A stored route (`_from_experience`), else RRT-Connect under the same checker,
        where the graph has no route. Stored routes come after the graph, not before it:
        tried first, they were 190-221 of 270-340 soak decisions, with motions of 3.8-4.6 s
        (p50) against 1.3-1.7 s for graph routes, and goal times grew over a 10-minute soak
        (p50 3.8 -> 8.5 s; graph first: 2.7-4.6 s in 9 of 10 windows). Each failure
        toward the same goal doubles the next budget (to 8x) and changes the sampling seed,
        so a holding arm never repeats the identical failing search; a route found is kept
        (`experience`) for the next query that meets the same blockage. Returns (path,
        source, note for the reason)."""
        if self.config.fallback_budget_s <= 0.0:
            return None, "", ""
        path = self._pending_route(query)
        if path is not None:
            return path, "rrtconnect", ""
        path = self._from_experience(query)
        if path is not None:  # the same blockage as before: no sampling search
            return path, "experience", ""
        attempt = self._fallback_failures
        # the escalation is for a holding arm's retries: a moving arm coasts on while it
        # searches (an 0.8 s search let a stress-bench arm run into the mover it re-routed
        # for), and an arm whose trajectory a mover threatens may have to escape it (soak: a
        # 0.4 s search, then the escape from a mover predicted to reach the arm in 0.27 s)
        budget = self._fallback_budget(attempt if self._escalate and not self._moving_start
                                       else 0)
        raw = self._sampling_route(query, budget, seed=attempt)
        if raw is not None and self._may_defer() and self._retry_spent() > RETRY_SHORTEN_S:
            self._pending, self._deferred = raw, True
            return None, "", "; RRT-Connect found a route, shortened by the next retry"
        path = None if raw is None else self._shortened(raw, query)
        if path is not None:
            self._found(path)
            return path, "rrtconnect", ""
        self._fallback_failures += 1
        found = "a route that failed certification" if raw is not None else "no route"
        return None, "", (f"; RRT-Connect fallback found {found} in {budget:.2f} s (attempt "
                          f"{attempt + 1}; the next one gets "
                          f"{self._fallback_budget(attempt + 1):.2f} s "
                          "and new samples)")

    def _found(self, path: np.ndarray) -> None:
        """A sampled route was certified: the budget starts over and the route is kept."""
        self._fallback_failures = 0
        self.experience = [*self.experience, path][-self.config.experience_routes:]

    def _pending_route(self, query: _Query) -> np.ndarray | None:
        """The route RRT-Connect found in the last retry (`RETRY_SHORTEN_S`), shortened and
        certified now, when this query starts where it did (within KEPT_START_RAD: the arm
        held there) toward the same goal and the fast model still passes it (`_screened`);
        else None. Taken once either way."""
        raw, self._pending = self._pending, None
        if raw is None or not np.array_equal(raw[-1], query.q_goal) or \
                float(np.max(np.abs(raw[0] - query.q_start))) > KEPT_START_RAD:
            return None
        raw = np.vstack([query.q_start[None], raw[1:]])
        path = self._shortened(raw, query) if self._screened(raw, query) else None
        if path is not None:
            self._found(path)
        return path

    def _sampling_route(self, query: _Query, budget: float, seed: int) -> np.ndarray | None:
        """RRT-Connect between the query's ends: compiled over the fast model's spheres
        (`rrt_connect`), or OMPL where the robot has no sphere model. Edges leaving the
        start keep its margin, edges leaving the goal half the goal's fast clearance when
        that is below λ (a goal certified on the meshes), all others λ."""
        margin = self.config.margin
        obstacles = query.scene.ahead
        if self.robot.collision != "fast":
            from damon_ros.planning.sampling import sampling_route

            return sampling_route("rrtconnect", self.robot, self.limits, query.q_start,
                                  query.q_goal, obstacles, min(margin, query.start_margin),
                                  self.config.resolution, budget, seed=seed)
        from damon_ros.planning.rrt_connect import rrt_connect

        goal_clearance = self.clearance(query.q_goal, obstacles)
        if goal_clearance <= 0.0:  # the fast model refuses the goal: no tree reaches it
            return None
        goal_margin = min(margin, 0.5 * goal_clearance)
        return rrt_connect(self.robot.spheres, query.q_start, query.q_goal,
                           self.limits.lower, self.limits.upper, obstacles, margin,
                           (query.start_margin, goal_margin), self.config.resolution,
                           budget, seed=seed)

    def _graph_shortened(self, path: np.ndarray, query: _Query) -> np.ndarray:
        """A graph route (each edge certified) shortened. On the fast model the compiled
        shortcut first (`path_shortcutting`, as many pull rounds as `_pull_tight`), its
        result kept when it is certified as a whole (`_certified`: self-collision, the
        start's near and far margins, a goal only the meshes accept); else `_shortcut`,
        which certifies each segment as it goes. In Python the pull toward the midpoints
        was a quarter of the slowest re-plans' time (family D: up to 5 ms a route)."""
        if self.robot.collision == "fast":
            from damon_ros.planning.path_shortcutting import shortcut

            short = shortcut(self.robot.spheres, path, query.scene.ahead, query.start_margin,
                             self.config.margin, self.config.resolution, self.limits.lower,
                             self.limits.upper, rounds=PULL_ROUNDS,
                             deadline=self._pull_deadline(query))
            if self._certified(short, query):
                return short
        return self._shortcut(path, query)

    def _shortened(self, path: np.ndarray, query: _Query) -> np.ndarray | None:
        """A sampled route shortened and certified, or None when it fails certification.
        On the fast model the compiled shortcut goes first (`path_shortcutting`: the same
        questions as `_shortcut`, without self-collision and without a Python call per
        segment); where its result is refused (self-collision, a goal only the meshes
        accept), `_shortcut` decides."""
        if not self.config.shortcut:
            return path if self._certified(path, query) else None
        if self.robot.collision == "fast":
            from damon_ros.planning.path_shortcutting import shortcut

            short = shortcut(self.robot.spheres, path, query.scene.ahead, query.start_margin,
                             self.config.margin, self.config.resolution, self.limits.lower,
                             self.limits.upper, deadline=self._pull_deadline(query))
            if self._certified(short, query):
                return short
        short = self._shortcut(path, query)
        return short if self._certified(short, query) else None

    def _pull_deadline(self, query: _Query) -> float:
        """When the compiled shortcut's last pull round may begin: for a route from a moving
        arm, which coasts and brakes while it is computed, the graph's handover deadline;
        otherwise never cut (the pull shortens a route that is already clear). Stress
        bench, 1-1.5 m/s: an 11 ms pull in a 35 ms re-route of a moving arm; cut for every
        re-route, it lengthened the executed paths and did not shorten the slowest."""
        return query.deadline if self._moving_start else math.inf

    def _fallback_budget(self, attempt: int) -> float:
        """The sampling budget of the ``attempt``-th try (from 0) toward one goal."""
        return self.config.fallback_budget_s * 2 ** min(attempt, 3)

    def _certified(self, path: np.ndarray, query: _Query) -> bool:
        """Every segment certified by the query's rules (first segment, goal segment) and
        free of self-collision on the meshes."""
        last = len(path) - 2
        return all(query.segment_certified(a, b, first=i == 0, last=i == last)
                   and self.robot.segment_self_collision_free(a, b)
                   for i, (a, b) in enumerate(zip(path, path[1:], strict=False)))

    def _node_order(self, q: np.ndarray, obstacles: Sequence[Shape]) -> np.ndarray:
        """Obstacle nodes by distance from the obstacle point closest to the arm (GJK witness
        point); with no obstacles, every node is equally relevant."""
        n = len(self.graph.nodes)
        if not obstacles:
            return np.arange(n)
        witness = self.robot.clearance(q, obstacles).obstacle_point
        return self.graph.nearest_nodes(witness, k=n)

    def _attach(self, q: np.ndarray, active_ids: np.ndarray) -> list[tuple[int, float]]:
        """The k nearest active vertices to a configuration, with joint-space distances: a
        direct scan of a small active set, the KD-tree over all safe vertices otherwise."""
        k = self.config.k_attach
        if len(active_ids) <= 4096:
            d = np.linalg.norm(self.graph.q[active_ids] - q, axis=1)
            nearest = np.argsort(d)[:k] if len(d) <= k else np.argpartition(d, k)[:k]
            return [(int(active_ids[i]), float(d[i])) for i in nearest]
        dist, idx = self._tree.query(q, k=min(4 * k, len(self._safe_ids)))
        return [(int(self._safe_ids[i]), float(x)) for x, i in zip(
            np.atleast_1d(dist), np.atleast_1d(idx), strict=True)][:k]

    def _lazy_astar(self, query: _Query, active: np.ndarray) -> list[int] | None:
        """A* over active safe vertices plus start and goal; edges on the found path are
        checked in order and a blocked one removed before searching again (lazy PRM). The
        A* itself is compiled (`graph_search`): one iteration is well under a millisecond."""
        active_ids = np.flatnonzero(active)
        start_links = self._attach(query.q_start, active_ids)
        goal_links = dict(self._attach(query.q_goal, active_ids))
        direct = float(np.linalg.norm(query.q_goal - query.q_start))
        heuristic = self._heuristic(query.q_goal)
        while query.iterations == 0 or (query.iterations < self.config.max_lazy_iterations
                                        and time.perf_counter() < query.deadline):
            query.iterations += 1
            path = query.search.shortest(
                active, heuristic, [(v, query.link_weight(_Query.START, v, w))
                                    for v, w in start_links],
                {v: query.link_weight(v, _Query.GOAL, w) for v, w in goal_links.items()},
                query.link_weight(_Query.START, _Query.GOAL, direct))
            if path is None:
                return None
            if all(query.edge_free(u, v) for u, v in zip(path, path[1:], strict=False)):
                return path
        return None

    def _heuristic(self, q_goal: np.ndarray) -> np.ndarray:
        """A*'s heuristic, every vertex's joint-space distance to ``q_goal``: kept for the
        last goal, which every re-plan toward it and every widened search asks for again
        (~0.5 ms a time over the whole graph)."""
        cached = self._heuristic_cache
        if cached is None or not np.array_equal(cached[0], q_goal):
            cached = self._heuristic_cache = (q_goal.copy(), np.linalg.norm(
                self.graph.q - q_goal, axis=1))
        return cached[1]

    def _shortcut(self, path: np.ndarray, query: _Query) -> np.ndarray:
        """Greedy shortcutting: from each kept waypoint jump to the farthest later waypoint
        whose straight segment is certified free (fewer stops, shorter motion)."""
        keep = [0]
        i = 0
        while i < len(path) - 1:
            for j in range(len(path) - 1, i, -1):
                if j == i + 1:
                    break
                query.checked += 1
                if query.segment_certified(path[i], path[j], first=i == 0,
                                           last=j == len(path) - 1, exact=False) and \
                        self.robot.segment_self_collision_free(path[i], path[j]):
                    break
            keep.append(j)
            i = j
        return self._pull_tight(path[keep], query)

    def _pull_tight(self, path: np.ndarray, query: _Query, rounds: int = PULL_ROUNDS,
                    fractions: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1)) -> np.ndarray:
        """Pull each interior waypoint toward the midpoint of its neighbours — as far as its
        two segments stay certified (the largest of ``fractions`` that works) — for a few
        rounds: the detour through a far graph vertex shrinks toward the obstacle's
        silhouette. Cheap obstacle checks first, mesh self-collision only for a winner."""
        path = path.copy()
        for _ in range(rounds):
            moved = 0.0
            for i in range(1, len(path) - 1):
                target = 0.5 * (path[i - 1] + path[i + 1])
                for f in fractions:
                    candidate = path[i] + f * (target - path[i])
                    if not self.limits.within(candidate):
                        continue
                    query.checked += 2
                    if (query.segment_certified(path[i - 1], candidate, first=i == 1,
                                                exact=False)
                            and query.segment_certified(candidate, path[i + 1], first=False,
                                                        last=i + 1 == len(path) - 1,
                                                        exact=False)
                            and self.robot.segment_self_collision_free(path[i - 1], candidate)
                            and self.robot.segment_self_collision_free(candidate, path[i + 1])):
                        moved = max(moved, float(np.max(np.abs(candidate - path[i]))))
                        path[i] = candidate
                        break
            if moved < 0.01 or time.perf_counter() > query.deadline:
                break
        return path

    def _time_parameterize(self, path: np.ndarray):
        from damon_ros.planning.trajectory import time_parameterize

        c = self.config
        return time_parameterize(path, self.limits, velocity_scale=c.velocity_scale,
                                 acceleration_scale=c.acceleration_scale,
                                 jerk_scale=c.jerk_scale, dt=c.trajectory_dt)

    def escape(self, q_now: np.ndarray, obstacles, candidates: int = 96,
               rng: np.random.Generator | None = None, qd_now=None,
               started: float | None = None) -> PlanResult:
        """A short certified move to a configuration with more clearance, for when no route
        to the goal exists and an obstacle is closing in: holding still is not safe from
        something that moves. Candidates are nearby graph vertices and random joint
        perturbations, ranked by clearance from the swept obstacles and from where the
        movers are predicted over REST_HORIZON_S; the clearest whose straight segment is
        certified (against the obstacles now) wins — with movers, only one whose timed
        move, and REST_HORIZON_S at rest after it, is certified in space and time (with its
        stops): evade where the mover will be, not where it is. A moving arm (``qd_now``)
        escapes from where it brakes to, the brake part of the trajectory. Where an arm at
        rest can't hold (`rest_contact`: a mover's prediction reaches it at t_hold), the
        escape's stops need only be no worse than holding (none meets a mover before
        t_hold); its own states and its rest are certified in full. Where nothing is
        certified and stopping meets a mover, at rest or braking, the clearest move that
        keeps clear of the movers' nominal paths (`nominally_clear`) is a last resort
        (source "last resort"). With every stop held to the full rule, an arm 4 cm above a
        ball rising at 0.13 m/s found no escape (each one's first stop rests in the ball's
        way, as holding does), held, and was hit: the 10-minute soak's contacts. A moving
        arm none of whose brake-then-move escapes keeps clear that way turns while braking
        (`_swerve`), the same last resort. ``started``: when the computation that asks for
        the escape began (`time.perf_counter`; default now), the measured state's time: a
        swerve turns only after it will have reached the controller."""
        t0 = time.perf_counter()
        q_now = np.asarray(q_now, float)
        scene = Scene.of(obstacles)
        if not scene.now:
            return PlanResult(False, "nothing to escape from")
        start = self._escape_start(q_now, qd_now, scene)
        if start is None:
            return PlanResult(False, "no certified escape move found (braking from the "
                              "current speed is not certified free)")
        brake, q0, brake_free = start
        pool, clear, current = self._escape_pool(q0, scene, candidates,
                                                 rng or np.random.default_rng(0))
        query = _Query(self, q0, q0, scene)
        # with movers the clearance now can be large and still shrinking: more than λ will do
        floor = self.config.margin if scene.moving else max(current, self.config.margin)
        margin = self._mover_margin(q_now, scene)
        # where stopping meets a mover: the stops' relaxed rule for an arm at rest only
        # (moving arms with it regressed three stress scenes), the last resort for both
        hold_at = self._hold_refused_at(q_now, qd_now, scene, margin)
        not_before = math.inf if brake is not None else hold_at
        moves = []  # (target, path, trajectory) of the candidates certified on the statics
        # mesh self-collision (~0.15 ms a move) is asked only of a move that would be taken:
        # most candidates of a last resort fail the space-time rule first (soak: ~3 ms)
        self_free = self.robot.segment_self_collision_free
        # after a brake into a mover's grown region no escape is certified, only the last
        # resort: its move (the clearest that qualifies) is taken as soon as it is found,
        # not after certifying all 24 candidates. The same move, sooner: such an arm is
        # moving toward a mover that has just started, and every millisecond counts there
        last_resort_only = not brake_free
        if last_resort_only and math.isinf(hold_at):
            return self._no_escape(query, t0)
        ranked = _clearest(clear, floor)
        if not ranked and scene.moving:
            clear = self._clear_of_predictions(pool, scene)
            ranked = _clearest(clear, floor)
        for i in ranked:
            query.checked += 1
            if not query.segment_certified(q0, pool[i], first=True):
                continue
            path = np.array([q0, pool[i]])
            trajectory = self._time_parameterize(path)
            if brake is not None:
                from damon_ros.planning.trajectory import concatenate

                path = np.vstack([q_now[None], path])
                trajectory = concatenate(brake, trajectory)
            if last_resort_only:
                if self._last_resort_clear(q0, pool[i], trajectory, scene):
                    return self._last_resort(hold_at, current, clear[i], path, trajectory,
                                             query, t0)
                continue
            moves.append((i, path, trajectory))
            if (not scene.moving or self._rests_clear(trajectory, scene, margin, not_before)) \
                    and self_free(q0, pool[i]):
                return self._escape_result(f"escaping: clearance {current:.3f} → "
                                           f"{clear[i]:.3f} m", path, trajectory, query, t0)
        if not math.isinf(hold_at):  # the clearest move whose nominal path keeps clear
            for i, path, trajectory in moves:
                if self._last_resort_clear(q0, pool[i], trajectory, scene):
                    return self._last_resort(hold_at, current, clear[i], path, trajectory,
                                             query, t0)
            if brake is not None:  # every such move brakes first: turn while braking
                swerve = self._swerve(brake, pool, clear, ranked[:SWERVE_CANDIDATES], scene,
                                      query, t0 if started is None else started)
                if swerve is not None:
                    return self._last_resort(hold_at, current, *swerve, query, t0)
        return self._no_escape(query, t0)

    def _escape_start(self, q_now: np.ndarray, qd_now, scene: Scene):
        """Where an escape starts: (None, ``q_now``, True) for an arm at rest; for a moving
        one (brake, where it ends, whether the brake is certified against everything).
        None when the brake ends too close to a joint limit or meets a static obstacle.
        A brake into a mover's grown region leaves only the last resort (a two-camera
        stress run: an arm on a last-resort escape, refused every move for its brake, held
        and was hit)."""
        if qd_now is None or float(np.max(np.abs(qd_now))) < MOVING_RAD_S:
            return None, q_now, True
        brake = self.stop_trajectory(q_now, np.asarray(qd_now, float))
        q0 = brake.positions[-1]
        brake_free = _Query(self, q_now, q0, scene).segment_certified(q_now, q0, first=True)
        if not self.keeps_limit_margin(q0) or (not brake_free and not
                _Query(self, q_now, q0, scene.statics()).segment_certified(q_now, q0,
                                                                            first=True)):
            return None
        return brake, q0, brake_free

    def _escape_pool(self, q0: np.ndarray, scene: Scene, candidates: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        """Escape candidates around ``q0`` (nearby graph vertices and random perturbations
        of up to 0.4 rad, half each), their clearances from the swept obstacles and the
        movers' predicted regions, and the clearance of ``q0`` itself."""
        ranking = (*scene.ahead, *self._predicted(scene))
        jitter = self.inside_limits(q0 + rng.uniform(-0.4, 0.4, (candidates // 2, 7)))
        pool = jitter
        if self._tree is not None:
            _, idx = self._tree.query(q0, k=min(candidates // 2, len(self._safe_ids)))
            pool = np.vstack([self.graph.q[self._safe_ids[np.atleast_1d(idx)]], jitter])
        return pool, self.robot.distances(pool, ranking), self.clearance(q0, ranking)

    def _clear_of_predictions(self, pool: np.ndarray, scene: Scene) -> np.ndarray:
        """The candidates' clearances from the statics (swept) and from where the movers are
        predicted (`_predicted`), not from the movers' swept regions: an arm inside a fast
        mover's sweep has every candidate within reach inside it too, and ranked by it, none
        is tried (S-v1-1.5-s2710-118: a ball at 1 m/s, 0.2 s from a braking arm, found no
        escape, last resort included, in ten tries). The space-time rules then judge each."""
        return self.robot.distances(pool, (*scene.statics().ahead, *self._predicted(scene)))

    def _swerve(self, brake, pool: np.ndarray, clear: np.ndarray, ranked: list,
                scene: Scene, query: _Query,
                started: float) -> tuple[float, np.ndarray, object] | None:
        """The last resort of a moving arm whose every brake-then-move escape meets a mover:
        ``(clearance, path, trajectory)`` of the first of the ``ranked`` candidates (indices
        into ``pool``, clearest first) that the arm turns to from its ``brake`` (the stop
        already sent) after `_swerve_branch` (`trajectory.swerve_trajectory`), clear of the
        movers' nominal paths (`nominally_clear`), its states certified against the statics
        chord by chord and free of self-collision, inside the joint limits less IK's margin
        as every escape target is (`inside_limits`); else None. Its path is its states every
        `SWERVE_CHORD_S` (the runtime follows and re-checks it as a path). A swerve found
        after its own turn (the computation since ``started`` took longer than estimated)
        is searched once more, turning later: the arm has braked on meanwhile."""
        for _ in range(2):
            branch_s = self._swerve_branch(started)
            found = self._swerve_from(brake, branch_s, pool, clear, ranked, scene, query)
            if found is None or time.perf_counter() - started <= branch_s:
                return found
        return found

    @staticmethod
    def _swerve_branch(started: float) -> float:
        """When a swerve computed from now on may turn: `SWERVE_BRANCH_S` after the measured
        state, or later where the computation since ``started`` (`time.perf_counter`) will
        not have ended by then (`SWERVE_LATE_FACTOR` times what it has taken so far). A
        swerve that arrived after its turn asked the arm to be where it was not: on a
        loaded machine (an escape of 35-82 ms) the arm lagged it, its re-check failed, it
        stopped and was hit (S-v0.6-1-s2709-073)."""
        return max(SWERVE_BRANCH_S, SWERVE_LATE_FACTOR * (time.perf_counter() - started))

    def _swerve_from(self, brake, branch_s: float, pool: np.ndarray, clear: np.ndarray,
                     ranked: list, scene: Scene,
                     query: _Query) -> tuple[float, np.ndarray, object] | None:
        """`_swerve`'s search for one turning time ``branch_s``."""
        from damon_ros.planning.trajectory import swerve_trajectory

        statics = _Query(self, brake.positions[0], brake.positions[0], scene.statics())
        every = max(1, round(SWERVE_CHORD_S / self.config.trajectory_dt))
        for i in ranked:
            trajectory = swerve_trajectory(brake, branch_s, pool[i], self.limits,
                                           self.config.trajectory_dt)
            if trajectory is None or not self.keeps_limit_margin(trajectory.positions) or \
                    not self.nominally_clear(trajectory.times, trajectory.positions, scene):
                continue  # (on its way into IK's margin of a limit: a Franka reflex)
            query.checked += 1
            states = np.vstack([trajectory.positions[::every], trajectory.positions[-1:]])
            if self._chords_free(states, statics):
                return float(clear[i]), states, trajectory
        return None

    def _chords_free(self, states: np.ndarray, statics: _Query) -> bool:
        """A swerve's ``states``: each chord certified against the statics (the first by the
        first-segment rules) and free of self-collision."""
        return all(statics.segment_certified(a, b, first=k == 0)
                   and self.robot.segment_self_collision_free(a, b)
                   for k, (a, b) in enumerate(zip(states[:-1], states[1:], strict=True)))

    def _last_resort_clear(self, q0: np.ndarray, target: np.ndarray, trajectory,
                           scene: Scene) -> bool:
        """An escape's last resort (`escape`): free of self-collision, and clear of the
        movers' nominal paths (`nominally_clear`)."""
        return self.robot.segment_self_collision_free(q0, target) and \
            self.nominally_clear(trajectory.times, trajectory.positions, scene)

    def _last_resort(self, hold_at: float, current: float, clear: float, path: np.ndarray,
                     trajectory, query: _Query, t0: float) -> PlanResult:
        return self._escape_result(
            f"escaping as a last resort (holding meets a mover's prediction {hold_at:.2f} s "
            f"from now, no move is certified against its grown region; this one keeps clear "
            f"of its nominal path): clearance {current:.3f} → {clear:.3f} m", path,
            trajectory, query, t0, "last resort")

    def _no_escape(self, query: _Query, t0: float) -> PlanResult:
        return PlanResult(False, "no certified escape move found", edges_checked=query.checked,
                          timing_ms={"total": 1e3 * (time.perf_counter() - t0)})

    def _escape_result(self, reason: str, path: np.ndarray, trajectory, query: _Query,
                       t0: float, source: str = "escape") -> PlanResult:
        return PlanResult(True, reason, path=path, trajectory=trajectory, goal_q=self.goal_q,
                          edges_checked=query.checked, source=source,
                          timing_ms={"total": 1e3 * (time.perf_counter() - t0)})

    def nominally_clear(self, times: np.ndarray, positions: np.ndarray, obstacles) -> bool:
        """The timed states (``times`` from now), then REST_HORIZON_S at rest at the last,
        against each mover where its reported velocity takes it (no growth, no margin; the
        check's half step kept): the last resort of an escape from a hold that a mover's
        prediction reaches where no move is certified against the grown regions (the arm
        is already within them), and the re-check of that escape while it runs."""
        scene = Scene.of(obstacles)
        times, positions = then_resting(times, positions)
        nominal = replace(self.config.prediction, position_sigma_m=0.0,
                          velocity_sigma_m_s=0.0, velocity_sigma_rel=0.0,
                          acceleration_m_s2=0.0)
        return refused_at(self.robot, times, positions, scene.moving, 0.0,
                          self.config.resolution, nominal, scene.age_s) is None

    def _hold_refused_at(self, q: np.ndarray, qd: np.ndarray | None, scene: Scene,
                         margin: float) -> float:
        """When braking in place and resting there would meet a mover, checked as a stop
        of a trajectory is (margin + STOP_MARGIN_M), less one check interval (the first
        refused instant is up to one late): an escape's stops compare with it
        (`_stop_contact`'s ``not_before``). Infinite when holding is certified."""
        if not scene.moving:
            return math.inf
        contact = self.rest_contact(q, qd, scene, margin + STOP_MARGIN_M)
        if contact is None or contact.obstacle < 0:
            return math.inf
        p = self.config.prediction
        speed = max(float(np.linalg.norm(v)) for _, v in scene.moving)
        interval = p.step_m / p.rate(speed, max(scene.age_s, p.min_age_s) + contact.time_s)
        return max(0.0, contact.time_s - interval)

    def _rests_clear(self, trajectory, scene: Scene, margin: float,
                     not_before: float = math.inf) -> bool:
        """The trajectory, then REST_HORIZON_S at rest at its end, certified in space and
        time with its stops; with ``not_before`` finite (holding where the arm is meets a
        mover then) a stop only has to meet no mover before that (`_stop_contact`)."""
        from damon_ros.planning.trajectory import held_until

        return self._refusal(held_until(trajectory, trajectory.duration + REST_HORIZON_S),
                             scene, margin, not_before=not_before) is None

    def _predicted(self, scene: Scene) -> tuple[Shape, ...]:
        """Each mover where it is predicted a quarter, half, three quarters and all of
        REST_HORIZON_S from now (not grown): what an escape move should get away from."""
        tau0 = max(scene.age_s, self.config.prediction.min_age_s)
        return tuple(s.moved_to(s.position + v * (tau0 + f * REST_HORIZON_S))
                     for s, v in scene.moving for f in (0.25, 0.5, 0.75, 1.0))

    # ---- monitoring -----------------------------------------------------------------
    def path_threatened(self, q_now: np.ndarray, remaining: np.ndarray,
                        obstacles) -> tuple[bool, str]:
        """Is the rest of the path (from ``q_now`` through ``remaining`` waypoints) no longer
        certified free against the current obstacles? Returns (threatened, why).

        ``remaining[0]`` is the point of the path nearest the arm, so the first two segments
        (the step back onto the path and the rest of the segment the arm is on) leave the
        current state: they are held to the start margin, exactly as a re-route from here
        would hold its first segment. With the full margin there, an arm that started
        closer than 2λ to an obstacle would find each fresh re-route "threatened" at once
        and halt and re-route again at every check (seen in the camera demo at 40 Hz).
        """
        scene = Scene.of(obstacles)
        if not scene.now:
            return False, ""
        q_now = np.asarray(q_now, float)
        points = np.vstack([q_now[None], np.asarray(remaining, float).reshape(-1, 7)])
        query = _Query(self, q_now, q_now, scene)
        for i, (a, b) in enumerate(zip(points, points[1:], strict=False)):
            if not query.segment_certified(a, b, first=i <= 1, last=i == len(points) - 2):
                return True, f"{self._nearest_name(a, b, scene.ahead)} blocks the remaining path"
        if self.risk is not None:
            p = float(self.risk(q_now, scene.now))
            if p > 0.5:
                return True, f"p(collision) at the current state is {p:.2f}"
        return False, ""

    def _nearest_name(self, a: np.ndarray, b: np.ndarray, obstacles: Sequence[Shape]) -> str:
        """The name of the obstacle nearest the segment ``a``-``b`` (states at the planner's
        resolution), so that a log says what blocked the path (the box's jitter, a mover)."""
        n = int(np.ceil(float(np.max(np.abs(b - a))) / self.config.resolution)) + 1
        states = a + np.linspace(0.0, 1.0, max(n, 2))[:, None] * (b - a)
        gaps = [float(self.robot.distances(states, [shape]).min()) for shape in obstacles]
        k = int(np.argmin(gaps))
        return obstacles[k].name or f"obstacle {k}"


def _via(route: np.ndarray, q_start: np.ndarray, q_goal: np.ndarray) -> np.ndarray:
    """``route`` reused from ``q_start`` to ``q_goal``: on from its waypoint nearest the start
    to its waypoint nearest the goal (backwards if need be)."""
    i = int(np.argmin(np.linalg.norm(route - q_start, axis=1)))
    j = int(np.argmin(np.linalg.norm(route - q_goal, axis=1)))
    middle = route[i:j + 1] if i <= j else route[j:i + 1][::-1]
    path = np.vstack([q_start[None], middle, q_goal[None]])
    step = np.max(np.abs(np.diff(path, axis=0)), axis=1)
    return path[np.concatenate([[True], step > 1e-9])]


def _stop_states(trajectory) -> np.ndarray:
    """Indices of the moving states whose stops `_stop_contact` checks: the first moving
    one, then each STOP_EVERY_RAD (largest joint) or STOP_EVERY_S after the last."""
    from damon_ros.planning.trajectory import AT_REST_RAD_S

    return _stop_indices(trajectory.times, trajectory.positions, trajectory.velocities,
                         AT_REST_RAD_S, STOP_EVERY_S, STOP_EVERY_RAD)


@njit(cache=True)
def _stop_indices(times, positions, velocities, at_rest, every_s, every_rad):
    out = np.empty(times.shape[0], np.int64)
    n = 0
    for i in range(times.shape[0]):
        if np.max(np.abs(velocities[i])) < at_rest:
            continue
        if n == 0 or times[i] - times[out[n - 1]] >= every_s or \
                np.max(np.abs(positions[i] - positions[out[n - 1]])) >= every_rad:
            out[n] = i
            n += 1
    return out[:n]


def _timed(trajectory) -> tuple[np.ndarray, np.ndarray]:
    return trajectory.times, trajectory.positions


def then_resting(times, positions) -> tuple[np.ndarray, np.ndarray]:
    """Timed states (``times`` from now), then REST_HORIZON_S at rest at the last: a move
    and the hold it ends in, as an escape is certified and re-checked."""
    return (np.append(np.asarray(times, float), float(times[-1]) + REST_HORIZON_S),
            np.vstack([positions, positions[-1:]]))


def _clearest(clear: np.ndarray, floor: float, count: int = 24) -> list[int]:
    """The ``count`` clearest escape candidates, clearest first, that gain 1 cm over the
    floor."""
    return [int(i) for i in np.argsort(-clear)[:count] if clear[i] > floor + 0.01]
