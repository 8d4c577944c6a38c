"""``damon-ros scenarios generate``: fresh scenario files like the public families.

Held-out scenes for benchmarks and the runtime model: ``--families ADG --count 100 --seed 7``
writes ``<family>-s7-<i>.yaml`` files into ``--out``, each validated by the project's own
reader, start and goal clear of every obstacle at every instant. An existing file is not
overwritten unless ``--force`` (nothing is lost by a second run with other settings).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    from damon_ros.simulation.scenario_generation import FAMILIES, GenerationConfig

    defaults = GenerationConfig()
    parser = argparse.ArgumentParser(
        prog="damon-ros scenarios",
        description="Generate format-1 scenario files like the public families.",
        epilog="families: " + "; ".join(f"{k} {v}" for k, v in FAMILIES.items()))
    parser.add_argument("action", choices=["generate"])
    parser.add_argument("--families", default="".join(FAMILIES),
                        help="family letters (default: all)")
    parser.add_argument("--count", type=int, default=10, help="scenarios per family")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--speed", default=f"{defaults.speed[0]}:{defaults.speed[1]}",
                        help="speed band of the movers, m/s, as LOW:HIGH")
    parser.add_argument("--min-clearance", type=float, default=defaults.min_clearance,
                        help="start and goal from every obstacle at every instant (m)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")
    parser.add_argument("--quiet", action="store_true")
    return parser


def _speed_band(text: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split(":"))
    except ValueError as exc:
        raise ValueError(f"--speed {text!r}: expected LOW:HIGH in m/s") from exc
    if not 0.0 < low <= high:
        raise ValueError(f"--speed {text!r}: need 0 < LOW <= HIGH")
    return low, high


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from damon_ros.core.robot import Robot
    from damon_ros.simulation.scenario_generation import (
        FAMILIES,
        GenerationConfig,
        ScenarioGenerator,
        write_scenarios,
    )

    unknown = sorted(set(args.families) - set(FAMILIES))
    try:
        if unknown or args.count < 1:
            raise ValueError(f"unknown families {unknown}" if unknown else "--count must be >= 1")
        config = GenerationConfig(speed=_speed_band(args.speed), min_clearance=args.min_clearance)
    except ValueError as exc:
        print(f"damon-ros scenarios: {exc}", file=sys.stderr)
        return 2
    generator = ScenarioGenerator(Robot("mesh"), config)
    files, written = write_scenarios(generator, Path(args.out), args.families,
                                     args.count * len(args.families), args.seed, args.force)
    kept = len(files) - written
    if not args.quiet:
        for family in args.families:
            print(f"{family}: {args.count} scenarios ({FAMILIES[family]})", file=sys.stderr)
    print(f"wrote {written} scenario files to {args.out}" + (
        f"; kept {kept} existing (use --force to overwrite)" if kept else ""))
    return 0
