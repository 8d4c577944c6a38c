"""``damon-ros scenarios generate``: fresh scenario files like the public families.

Held-out scenes for benchmarks and the runtime model: ``--families ADG --count 100 --seed 7``
writes ``<family>-s7-<i>.yaml`` files into ``--out``, each validated by the project's own
reader, start and goal clear of every obstacle at every instant. An existing file is not
overwritten unless ``--force`` (nothing is lost by a second run with other settings).

The stress family S (1–3 movers crossing the hand's way, spheres, boxes and compound
objects, plus static boxes) is generated only when asked for; ``--bands all`` writes
``--count`` scenarios per speed band of the stress bench (0.1–0.3, 0.3–0.6, 0.6–1.0,
1.0–1.5 m/s), the band in each name: ``--families S --bands all --count 250`` is the
1,000-scenario stress suite.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    from damon_ros.simulation.scenario_generation import (
        ALL_FAMILIES,
        FAMILIES,
        GenerationConfig,
    )

    defaults = GenerationConfig()
    parser = argparse.ArgumentParser(
        prog="damon-ros scenarios",
        description="Generate format-1 scenario files like the public families.",
        epilog="families: " + "; ".join(f"{k} {v}" for k, v in ALL_FAMILIES.items()))
    parser.add_argument("action", choices=["generate"])
    parser.add_argument("--families", default="".join(FAMILIES),
                        help=f"family letters (default: {''.join(FAMILIES)}; S is the "
                             "stress family)")
    parser.add_argument("--count", type=int, default=10, help="scenarios per family")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--speed", default=f"{defaults.speed[0]}:{defaults.speed[1]}",
                        help="speed band of the movers, m/s, as LOW:HIGH")
    parser.add_argument("--bands", default=None,
                        help="several speed bands, LOW:HIGH,LOW:HIGH,... or 'all' (the "
                             "stress bands); --count scenarios per family and band, the band "
                             "in each name; replaces --speed")
    parser.add_argument("--min-clearance", type=float, default=defaults.min_clearance,
                        help="start and goal from every obstacle at every instant (m)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")
    parser.add_argument("--quiet", action="store_true")
    return parser


def _speed_band(text: str, flag: str = "--speed") -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split(":"))
    except ValueError as exc:
        raise ValueError(f"{flag} {text!r}: expected LOW:HIGH in m/s") from exc
    if not 0.0 < low <= high:
        raise ValueError(f"{flag} {text!r}: need 0 < LOW <= HIGH")
    return low, high


def _bands(text: str | None) -> list[tuple[float, float]] | None:
    """The bands of ``--bands`` (None: the single ``--speed`` band, names untagged)."""
    from damon_ros.simulation.scenario_generation import STRESS_BANDS

    if text is None:
        return None
    if text == "all":
        return list(STRESS_BANDS)
    return [_speed_band(part, "--bands") for part in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from damon_ros.core.robot import Robot
    from damon_ros.simulation.scenario_generation import (
        ALL_FAMILIES,
        GenerationConfig,
        ScenarioGenerator,
        write_scenarios,
    )

    unknown = sorted(set(args.families) - set(ALL_FAMILIES))
    try:
        if unknown or args.count < 1:
            raise ValueError(f"unknown families {unknown}" if unknown else "--count must be >= 1")
        bands = _bands(args.bands)
        speeds = bands or [_speed_band(args.speed)]
    except ValueError as exc:
        print(f"damon-ros scenarios: {exc}", file=sys.stderr)
        return 2
    mesh = Robot("mesh")
    files, written = [], 0
    for speed in speeds:
        config = GenerationConfig(speed=speed, min_clearance=args.min_clearance)
        band_files, band_written = write_scenarios(
            ScenarioGenerator(mesh, config), Path(args.out), args.families,
            args.count * len(args.families), args.seed, args.force, tag_band=bands is not None)
        files += band_files
        written += band_written
    kept = len(files) - written
    if not args.quiet:
        for family in args.families:
            print(f"{family}: {args.count} scenarios x {len(speeds)} band(s) "
                  f"({ALL_FAMILIES[family]})", file=sys.stderr)
    print(f"wrote {written} scenario files to {args.out}" + (
        f"; kept {kept} existing (use --force to overwrite)" if kept else ""))
    return 0
