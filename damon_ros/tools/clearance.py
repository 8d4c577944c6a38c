"""``damon-ros clearance``: the robot's exact clearance to each obstacle of scenarios.

A quick, true look at a scenario before planning anything: for the start state (and the
goal's joint solution when the file gives one) it prints the exact mesh distance, with the
closest link, to every obstacle.
"""

from __future__ import annotations

import argparse
import sys

from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.scenario import ScenarioError, load_scenario, scenario_files


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="damon-ros clearance",
        description="Print the Panda's exact (mesh) clearance to every obstacle of scenarios.",
    )
    parser.add_argument("scenarios", nargs="*",
                        help="scenario files or folders (default: the public scenarios)")
    parser.add_argument("--time", type=float, default=0.0,
                        help="time (s) at which moving obstacles are placed (default 0)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from damon_ros.core.robot import Robot

    robot = Robot(collision="mesh")
    files = scenario_files(args.scenarios or [public_scenarios_dir()])
    if not files:
        print("damon-ros clearance: no scenario files found", file=sys.stderr)
        return 2
    failures = 0
    print(f"{'scenario':<10} {'state':<6} {'obstacle':<10} {'shape':<9} {'clearance_m':>11}  link")
    for path in files:
        try:
            scenario = load_scenario(path)
        except ScenarioError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failures += 1
            continue
        states = [("start", scenario.start)]
        if scenario.goal.joints is not None:
            states.append(("goal", scenario.goal.joints))
        for label, q in states:
            for obstacle in scenario.obstacles:
                c = robot.clearance(q, obstacle.parts_at(args.time))
                kind = "compound" if obstacle.is_compound else obstacle.shape.kind
                print(f"{scenario.name:<10} {label:<6} {obstacle.name:<10} "
                      f"{kind:<9} {c.distance:>11.4f}  {c.link}")
    return 1 if failures else 0
