"""``damon-ros bench``: closed-loop benchmark of DAMON and OMPL planners on scenario files.

Every (scenario, planner) run is simulated without ROS by :mod:`damon_ros.simulation.closed_loop`
(the runtime loop, PID follower and mock arm of the nodes) and written as one JSON line as
../shared/scenarios/FORMAT.md says; a summary table per scenario family and planner
follows. MotionBenchMaker problem sets (the tarball or its folder) are static, many-obstacle
problems with joint goals: there each planner plans once and the path is verified on the
exact meshes, reporting success and planning time per set — the numbers the arm-planning
literature compares.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import defaultdict

import numpy as np

from damon_ros.core.limits import PROFILES
from damon_ros.ros.environment import freeze_start_up_heap

PLANNERS = ("damon", "damon-noreplan", "rrt", "rrtstar", "rrtconnect")


class _PlanOnce:
    """The ``damon-noreplan`` ablation: plan once, never re-route, hold or escape."""

    def __init__(self, runtime) -> None:
        self.inner = runtime

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def update(self, t, q_now, obstacles, perception_age_s: float = 0.0, qd_now=None):
        if self.inner.state != "executing":
            return None
        if np.max(np.abs(np.asarray(q_now) - self.inner.path[-1])) <= \
                self.inner.config.goal_tolerance_rad:
            self.inner.state = "reached"
        return None


MBM_MARGIN = 0.0
"""λ (m) for MotionBenchMaker unless ``--margin`` says otherwise: its scenes are exact and
static, and its validity is no contact (margin 0) on the meshes; the fast model already
contains them (plus 2 mm). λ = 10 mm, the node's default, is reserve for perception and
moving obstacles, and closes grasp goals the data set places 8-30 mm from an object."""


def make_runtime(name: str, model, fast, seed: int, solve_time: float,
                 margin: float | None = None, fallback_s: float | None = None,
                 space_time: bool = True, resting_buffer_m: float | None = None):
    from dataclasses import replace

    from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
    from damon_ros.planning.ompl_baseline import OmplPlanner
    from damon_ros.planning.reactive import ReactivePlanner, RuntimeConfig

    config = PlannerConfig() if margin is None else PlannerConfig(margin=margin)
    if fallback_s is not None:
        config = replace(config, fallback_budget_s=fallback_s)
    if name in ("damon", "damon-noreplan"):
        planner = GraphPlanner(model.graph, fast, fast.limits, config)
        settings = {"graph_vertices": model.graph.n_vertices, "margin_m": planner.config.margin,
                    "resolution_rad": planner.config.resolution,
                    "time_budget_s": planner.config.time_budget_s,
                    "fallback_budget_s": planner.config.fallback_budget_s,
                    "model": model.directory.name}
    else:
        planner = OmplPlanner(name, fast, fast.limits, config, solve_time=solve_time, seed=seed)
        settings = planner.settings()
    planner.warm_up()
    settings["space_time"] = space_time
    runtime_config = RuntimeConfig(space_time=space_time)
    if resting_buffer_m is not None:
        runtime_config = replace(runtime_config, resting_buffer_m=resting_buffer_m)
    settings["resting_buffer_m"] = runtime_config.resting_buffer_m
    runtime = ReactivePlanner(planner, runtime_config)
    return (_PlanOnce(runtime) if name == "damon-noreplan" else runtime), settings


def run_scenarios(scenarios, planners, model, out, args) -> list[dict]:
    from damon_ros.core.robot import Robot
    from damon_ros.simulation.closed_loop import SimConfig, run_scenario
    from damon_ros.simulation.scenario_generation import mover_speed, speed_band

    fast, mesh = Robot("fast", args.profile), Robot("mesh")
    config = SimConfig(perception=args.perception, perception_latency=args.latency,
                       perception_noise=args.noise, seed=args.seed,
                       cameras=tuple(c.strip() for c in args.cameras.split(",")))
    freeze_start_up_heap()  # as a node does once built (`node_main`): plans are timed
    records = []
    for scenario in scenarios:
        for name in planners:
            runtime, settings = make_runtime(name, model, fast, args.seed, args.solve_time,
                                             args.margin, space_time=not args.no_space_time,
                                             resting_buffer_m=args.resting_buffer)
            t0 = time.perf_counter()
            try:
                record = run_scenario(scenario, runtime, name, mesh, fast, config).as_json()
            except Exception as exc:  # one broken run must not stop the benchmark
                record = {"scenario": scenario.name, "planner": name, "success": False,
                          "error": f"run failed: {exc!r}"}
            speed = mover_speed(scenario)
            band = speed_band(speed)
            record.update(family=scenario.family, dynamic=scenario.is_dynamic,
                          mover_speed_m_s=round(speed, 3),
                          band=("static" if speed == 0.0 else
                                f"{band[0]:g}-{band[1]:g} m/s" if band else "other"),
                          planner_settings=settings, perception=args.perception,
                          **({"cameras": args.cameras} if args.perception == "camera" else {}),
                          wall_time_s=round(time.perf_counter() - t0, 3))
            records.append(record)
            out.write(json.dumps(record) + "\n")
            out.flush()
            if not args.quiet:
                print(f"  {scenario.name:<10} {name:<15} "
                      f"{'ok  ' if record.get('success') else 'FAIL'} "
                      f"T={record.get('total_time_s') or float('nan'):.2f}s "
                      f"{record.get('error') or ''}", file=sys.stderr)
    return records


def run_mbm(path, planners, model, out, args) -> list[dict]:
    """Plan once per MotionBenchMaker problem; verify the path on the exact meshes."""
    from damon_ros.core.robot import Robot
    from damon_ros.tools.mbm import FINGER_OPENING, load_problems

    fast = Robot("fast", finger_opening=FINGER_OPENING)
    mesh = Robot("mesh", finger_opening=FINGER_OPENING)
    freeze_start_up_heap()
    records = []
    for set_name, scenario in load_problems(path, fast, args.per_set):
        if isinstance(scenario, Exception):
            record = {"scenario": str(getattr(scenario, "source", "?")), "set": set_name,
                      "error": str(scenario), "success": False}
            out.write(json.dumps(record) + "\n")
            records.append(record)
            continue
        obstacles = scenario.obstacles_at(0.0)
        for name in planners:
            if name == "damon-noreplan":
                continue  # identical to damon when nothing moves
            margin = MBM_MARGIN if args.margin is None else args.margin
            # plan once: damon's sampling fallback gets OMPL's budget (the node's 0.1 s is a
            # first try that a holding arm escalates; here there is no second call)
            runtime, settings = make_runtime(name, model, fast, args.seed, args.solve_time,
                                             margin, fallback_s=args.solve_time)
            t0 = time.perf_counter()
            result = runtime.planner.plan(scenario.start, scenario.goal.joints, obstacles)
            elapsed = time.perf_counter() - t0
            verified = result.success and _mesh_free(mesh, result.path, obstacles)
            record = {"scenario": scenario.name, "set": set_name, "planner": name,
                      "success": bool(verified), "planning_time_s": elapsed,
                      "path_length_rad": result.path_length if result.success else None,
                      "error": None if verified else (result.reason or "path touches meshes"),
                      "planner_settings": settings}
            records.append(record)
            out.write(json.dumps(record) + "\n")
            out.flush()
    return records


def _mesh_free(mesh, path: np.ndarray, obstacles, step: float = 0.02) -> bool:
    """No state of the path, ``step`` rad apart, touches an obstacle on the exact meshes."""
    for a, b in zip(path, path[1:], strict=False):
        n = max(1, math.ceil(float(np.max(np.abs(b - a))) / step))
        if any(mesh.in_collision(a + t * (b - a), obstacles)
               for t in np.linspace(0.0, 1.0, n + 1)):
            return False
    return True


def _pct(values, q: float) -> float:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.percentile(values, q)) if values else float("nan")


def summary(records: list[dict]) -> str:
    """One row per (family or set, planner)."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in records:
        if "planner" in r:
            groups[(r.get("family") or r.get("set") or "?", r["planner"])].append(r)
    header = (f"{'family':<18} {'planner':<15} {'runs':>4} {'success':>8} {'contacts':>8} "
              f"{'over lim':>8} {'T p50 s':>8} {'path p50':>8} {'plan p50 ms':>11} "
              f"{'plan p99 ms':>11} "
              f"{'replan p50 ms':>13} {'replan p99 ms':>13}")
    lines = [header, "-" * len(header)]
    for (family, planner), rs in sorted(groups.items()):
        replans = [x for r in rs for x in (r.get("replan_latency_ms") or [])]
        plans = [1e3 * r["planning_time_s"] for r in rs if r.get("planning_time_s") is not None]
        lines.append(
            f"{family:<18} {planner:<15} {len(rs):>4} "
            f"{100 * np.mean([bool(r.get('success')) for r in rs]):>7.1f}% "
            f"{sum(bool(r.get('collided')) for r in rs):>8} "
            f"{sum(r.get('limits_respected') is False for r in rs):>8} "
            f"{_pct([r.get('total_time_s') for r in rs], 50):>8.2f} "
            f"{_pct([r.get('path_length_rad') for r in rs], 50):>8.2f} "
            f"{_pct(plans, 50):>11.1f} {_pct(plans, 99):>11.1f} "
            f"{_pct(replans, 50):>13.2f} {_pct(replans, 99):>13.2f}")
    return "\n".join(lines)


def band_summary(records: list[dict]) -> str:
    """The stress view: one row per (mover speed band, planner) — success, contacts, the
    least clearance (over each run's minimum: worst, 5th percentile, median), re-plan
    latency (p50, p99, and the most), and its p99 over the re-routes of an executing arm
    (a threat, a stall) alone: without a holding arm's retries, which find a route for an
    arm already braked to rest."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in records:
        if "planner" in r and "band" in r:
            groups[(r["band"], r["planner"])].append(r)
    header = (f"{'band':<14} {'planner':<12} {'runs':>4} {'success':>8} {'contacts':>8} "
              f"{'clr min mm':>10} {'clr p5 mm':>9} {'clr p50 mm':>10} {'replans':>7} "
              f"{'replan p50 ms':>13} {'replan p99 ms':>13} {'replan max ms':>13} "
              f"{'exec p99 ms':>11} {'failed retries':>14} {'failed p99 ms':>13}")
    lines = [header, "-" * len(header)]
    for (band, planner), rs in sorted(groups.items()):
        clear = [1e3 * r["min_clearance_m"] for r in rs if r.get("min_clearance_m") is not None]
        replans = [x for r in rs for x in (r.get("replan_latency_ms") or [])]
        executing = [x for r in rs for x, resumed in zip(
            r.get("replan_latency_ms") or [], r.get("replan_resumed") or [], strict=False)
            if not resumed]
        failed = [x for r in rs for x in (r.get("retry_failed_ms") or [])]
        lines.append(
            f"{band:<14} {planner:<12} {len(rs):>4} "
            f"{100 * np.mean([bool(r.get('success')) for r in rs]):>7.1f}% "
            f"{sum(bool(r.get('collided')) for r in rs):>8} "
            f"{min(clear, default=float('nan')):>10.1f} {_pct(clear, 5):>9.1f} "
            f"{_pct(clear, 50):>10.1f} {len(replans):>7} "
            f"{_pct(replans, 50):>13.2f} {_pct(replans, 99):>13.2f} "
            f"{max(replans, default=float('nan')):>13.2f} {_pct(executing, 99):>11.2f} "
            f"{len(failed):>14} {_pct(failed, 99):>13.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from damon_ros.core.scenario import ScenarioError, load_scenario, scenario_files
    from damon_ros.learning.bundle import DamonModel, ModelError
    from damon_ros.tools.mbm import is_mbm

    parser = argparse.ArgumentParser(prog="damon-ros bench", description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", required=True,
                        help="scenario files or folders, or a MotionBenchMaker tarball/folder")
    parser.add_argument("--planners", default="damon,rrtconnect",
                        help=f"comma-separated, from {','.join(PLANNERS)}")
    parser.add_argument("--out", default="results.jsonl", help="JSON lines output")
    parser.add_argument("--model", default=None, help="model directory (default: shipped)")
    parser.add_argument("--perception", choices=("ideal", "camera"), default="ideal")
    parser.add_argument("--cameras", default="camera.yaml",
                        help="--perception camera: comma-separated camera files (paths or "
                             "shipped names), rendered together and fused, e.g. "
                             "camera.yaml,camera_side.yaml")
    parser.add_argument("--latency", type=float, default=0.03, help="perception latency (s)")
    parser.add_argument("--noise", type=float, default=0.0, help="obstacle position noise (m)")
    parser.add_argument("--solve-time", type=float, default=1.0, help="OMPL budget per plan (s)")
    parser.add_argument("--margin", type=float, default=None,
                        help="λ (m) for every planner (default: the planner's 0.01 on "
                             f"scenario files, {MBM_MARGIN} on MotionBenchMaker problems)")
    parser.add_argument("--per-set", type=int, default=None,
                        help="at most this many MotionBenchMaker problems per set")
    parser.add_argument("--profile", choices=PROFILES, default="panda",
                        help="joint-limit profile the planners and the limit check use (fr3: "
                             "libfranka's position-dependent velocity bound)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--by-band", action="store_true",
                        help="also a table per mover speed band (the stress bench: "
                             "`damon-ros scenarios generate --families S --bands all`)")
    parser.add_argument("--no-space-time", action="store_true",
                        help="certify paths against swept obstacles only (the rule before "
                             "space-time certification), for comparison")
    parser.add_argument("--resting-buffer", type=float, default=None,
                        help="m a new goal's route keeps beyond the margin from anything at rest "
                             "(default: the planner node's resting_buffer_m, 0.05; 0 = off)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.margin is not None and not 0.0 <= args.margin <= 0.5:
        parser.error("--margin must be in [0, 0.5] m")
    if args.resting_buffer is not None and not 0.0 <= args.resting_buffer <= 0.5:
        parser.error("--resting-buffer must be in [0, 0.5] m")
    if args.perception == "camera":
        from damon_ros.perception.camera import load_cameras

        try:
            load_cameras(args.cameras)
        except (OSError, ValueError) as exc:
            print(f"damon-ros bench: --cameras: {exc}", file=sys.stderr)
            return 2
    planners = [p.strip() for p in args.planners.split(",") if p.strip()]
    unknown = sorted(set(planners) - set(PLANNERS))
    if unknown:
        print(f"damon-ros bench: unknown planner(s) {unknown}; choose from {PLANNERS}",
              file=sys.stderr)
        return 2
    try:
        model = DamonModel.load(args.model)
    except ModelError as exc:
        print(f"damon-ros bench: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    records, bad = [], 0
    with open(args.out, "w") as out:
        scenarios = []
        for path in args.scenarios:
            if is_mbm(path):
                records += run_mbm(path, planners, model, out, args)
                continue
            for file in scenario_files([path]):
                try:
                    scenarios.append(load_scenario(file))
                except ScenarioError as exc:  # reported per file; the others still run
                    bad += 1
                    print(f"damon-ros bench: skipped {exc}", file=sys.stderr)
                    out.write(json.dumps({"scenario": str(file), "error": str(exc)}) + "\n")
        records += run_scenarios(scenarios, planners, model, out, args)
    print(summary(records))
    if args.by_band:
        print("\n" + band_summary(records))
    print(f"\n{len(records)} runs in {time.perf_counter() - t0:.0f} s; {bad} bad scenario "
          f"file(s); results in {args.out}")
    return 0
