"""``damon-ros bench-tracker``: the tracker measured against ground truth, frame by frame.

Scenarios are rendered by the mock camera (with its noise and dropout) at the camera rate
and fed to the real tracker; every track is matched to the true obstacle of its colour
nearest it, and per true shape kind (a compound counts as ``compound``) and motion the table
gives: the share of frames whose estimate contains the true object (dense surface samples
of every part inside it — the tracker's safety rule), the median volume excess (estimate
volume / true volume - 1), the centre error (estimate centre vs the centre of the true
object's enclosing box), the velocity error, and the tracker's CPU time per frame (one
process and one BLAS thread as in the node, offline; CPU rather than wall time so that a
loaded machine does not inflate it).
Frames whose detection is flagged partial (cut off or occluded) are counted apart ("cut
contained"): the parts an occluder or the image border may hide are bounded by the class
prior there, which the true object need not keep to. ``--out`` writes every row as JSON lines for
``damon-ros report --tracker``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict

import numpy as np


def _true_centre(parts) -> np.ndarray:
    from damon_ros.core.shapes import enclosing_vertices

    v = np.vstack([enclosing_vertices(p) for p in parts])
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def measure(scenarios, seconds: float, fps: float, seed: int,
            cameras: str = "camera.yaml") -> list[dict]:
    """One row per (frame, true obstacle) seen: kind, motion, containment, errors, time,
    and the scenario and instant (to find a miss again).

    ``cameras``: comma-separated camera files, rendered at the same instant and fused
    (`Tracker.update_views`)."""
    from damon_ros.core import shapes
    from damon_ros.perception.camera import load_cameras
    from damon_ros.perception.tracking import Tracker
    from damon_ros.simulation.renderer import (
        load_render_settings,
        render,
        render_settings_kwargs,
        scene_at,
    )

    views = load_cameras(cameras)
    settings = load_render_settings()
    rng = np.random.default_rng(seed)
    rows = []
    for scenario in scenarios:
        tracker = Tracker(views[0])
        for t in np.arange(0.0, seconds, 1.0 / fps):
            frames = [render(camera, scene_at(scenario, t), **render_settings_kwargs(settings,
                                                                                      rng))
                      for camera in views]
            t0 = time.process_time()  # CPU time: what one core spends, whatever the load
            tracks = tracker.update_views(views, frames, t)
            elapsed = (time.process_time() - t0) / len(views)  # per camera frame
            detections = tracker.detections
            for obstacle in scenario.obstacles:
                parts = obstacle.parts_at(t)
                same = [tr for tr in tracks if tr.color == obstacle.color and tr.last_seen == t]
                centre = _true_centre(parts)
                if not same:
                    rows.append({"kind": _kind(obstacle), "moving": _moving(obstacle, t),
                                 "seen": False, "time_ms": 1e3 * elapsed,
                                 "cams": len(views), "set": cameras,
                                 "scenario": scenario.name, "t": float(t)})
                    continue
                track = min(same, key=lambda tr: np.linalg.norm(tr.shape.position - centre))
                samples = np.vstack([shapes.surface_samples(p, 0.008) for p in parts])
                partial = any(d.partial and d.shape is track.shape for d in detections)
                rows.append({
                    "kind": _kind(obstacle), "moving": _moving(obstacle, t), "seen": True,
                    "partial": partial,
                    "contained": bool(np.all(shapes.contains(track.shape, samples, 1e-9))),
                    "excess": shapes.volume(track.shape) / sum(shapes.volume(p) for p in parts)
                    - 1.0,
                    "centre_m": float(np.linalg.norm(_estimate_centre(track.shape) - centre)),
                    "velocity_mps": float(np.linalg.norm(track.velocity
                                                         - obstacle.velocity_at(t))),
                    "estimate": track.shape.kind, "time_ms": 1e3 * elapsed,
                    "cams": len(views), "set": cameras, "scenario": scenario.name,
                    "t": float(t)})
    return rows


def _estimate_centre(shape) -> np.ndarray:
    from damon_ros.core.shapes import enclosing_vertices

    v = enclosing_vertices(shape)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def _kind(obstacle) -> str:
    return "compound" if obstacle.is_compound else obstacle.shape.kind


def _moving(obstacle, t: float) -> bool:
    return bool(np.linalg.norm(obstacle.velocity_at(t)) > 0.0)


def summarise(rows: list[dict]) -> tuple[list[dict], list[dict]]:
    """Per (camera set, kind, motion), in the order the sets were given: frames, seen,
    partial, the share contained (of the whole views), excess, centre and velocity errors,
    the estimates made; and per camera set the CPU time per frame per camera (p50, p95)."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["set"], r["kind"], "moving" if r["moving"] else "static")].append(r)
    sets = list(dict.fromkeys(r["set"] for r in rows))  # in the order given
    out = []
    for (camera_set, kind, motion), rs in sorted(groups.items(),
                                                 key=lambda kv: (sets.index(kv[0][0]), kv[0][1:])):
        seen = [r for r in rs if r["seen"]]
        full = [r for r in seen if not r["partial"]]
        kinds: dict[str, int] = defaultdict(int)
        for r in seen:
            kinds[r["estimate"]] += 1

        def p(key, q, scale=1.0, rows=full):
            vals = [r[key] for r in rows]
            return scale * float(np.percentile(vals, q)) if vals else float("nan")

        out.append({
            "set": sets.index(camera_set) + 1, "cameras": camera_set, "cams": rs[0]["cams"],
            "kind": kind, "motion": motion, "frames": len(rs), "seen": len(seen),
            "partial": len(seen) - len(full),
            "contained_pct": 100 * float(np.mean([r["contained"] for r in full]))
            if full else float("nan"),
            "partial_contained_pct": 100 * float(np.mean([r["contained"] for r in seen
                                                          if r["partial"]]))
            if len(seen) > len(full) else float("nan"),
            "excess_pct": 100 * p("excess", 50), "centre_p50_mm": p("centre_m", 50, 1e3),
            "centre_p95_mm": p("centre_m", 95, 1e3), "velocity_p50": p("velocity_mps", 50),
            "estimates": ",".join(f"{k}:{n}" for k, n in sorted(kinds.items()))})
    times = [{"set": i, "cameras": c,
              "p50_ms": float(np.percentile([r["time_ms"] for r in rows if r["set"] == c], 50)),
              "p95_ms": float(np.percentile([r["time_ms"] for r in rows if r["set"] == c], 95))}
             for i, c in enumerate(sets, start=1)]
    return out, times


def table(rows: list[dict]) -> str:
    groups, times = summarise(rows)
    header = (f"{'kind':<9} {'motion':<7} {'cams':>5} {'frames':>6} {'seen':>6} {'partial':>7} "
              f"{'contained':>9} {'cut contained':>13} {'excess p50':>10} {'centre p50 mm':>13} "
              f"{'centre p95 mm':>13} {'vel p50 m/s':>11} {'estimates':<22}")
    lines = [header, "-" * len(header)]
    for g in groups:
        lines.append(
            f"{g['kind']:<9} {g['motion']:<7} {g['set']}:{g['cams']:<3} {g['frames']:>6} "
            f"{g['seen']:>6} {g['partial']:>7} {g['contained_pct']:>8.2f}% "
            f"{g['partial_contained_pct']:>12.2f}% "
            f"{g['excess_pct']:>9.0f}% {g['centre_p50_mm']:>13.1f} {g['centre_p95_mm']:>13.1f} "
            f"{g['velocity_p50']:>11.3f} {g['estimates']:<22}")
    lines.append("")
    for t in times:
        lines.append(f"set {t['set']} ({t['cameras']}): tracker CPU time per 640x480 frame per "
                     f"camera (all obstacles, one process): p50 {t['p50_ms']:.2f} ms, "
                     f"p95 {t['p95_ms']:.2f} ms")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from damon_ros.core.scenario import ScenarioError, load_scenario, scenario_files

    parser = argparse.ArgumentParser(prog="damon-ros bench-tracker",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", required=True, help="scenario files or folders")
    parser.add_argument("--seconds", type=float, default=4.0, help="scenario time per scenario")
    parser.add_argument("--fps", type=float, default=15.0, help="frames per scenario second")
    parser.add_argument("--seed", type=int, default=0, help="render noise seed")
    parser.add_argument("--out", default=None,
                        help="also write every row as JSON lines (for damon-ros report)")
    parser.add_argument("--cameras", nargs="+", default=["camera.yaml"], metavar="FILES",
                        help="camera sets, each a comma-separated list of camera files (paths "
                             "or shipped names) fused together; e.g. camera.yaml "
                             "camera.yaml,camera_side.yaml compares one and two cameras")
    args = parser.parse_args(argv)
    try:
        scenarios = [load_scenario(f) for f in scenario_files(args.scenarios)]
    except ScenarioError as exc:
        print(f"damon-ros bench-tracker: {exc}", file=sys.stderr)
        return 2
    if not scenarios:
        print("damon-ros bench-tracker: no scenario files", file=sys.stderr)
        return 2
    from damon_ros.perception.camera import load_cameras

    try:
        for cameras in args.cameras:
            load_cameras(cameras)
    except (OSError, ValueError) as exc:
        print(f"damon-ros bench-tracker: --cameras: {exc}", file=sys.stderr)
        return 2
    from damon_ros.ros.environment import limit_threads

    # one core, as the tracker node runs (`node_main`): BLAS worker threads busy-wait for
    # work and their CPU time, counted by process_time, tripled some frames (F-001)
    limit_threads()
    rows = [r for cameras in args.cameras
            for r in measure(scenarios, args.seconds, args.fps, args.seed, cameras)]
    print(table(rows))
    if args.out:
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
    return 0
