"""``damon-ros report``: docs/BENCHMARKS.md from benchmark result files.

Every number in the page is computed here from the JSON lines that ``damon-ros bench``
(and ``damon-ros bench-tracker --out``: the perception section) wrote, and the page names
the command that produced each file, so anyone can regenerate it. Plots (T and re-plan
latency distributions per planner) are written beside it. Without ``--results``,
``--tracker`` and ``--stress`` rewrite only their own sections, between their
``<!-- perception -->`` / ``<!-- stress -->`` markers.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

# ../shared/DAMON.md, Table 2 of the paper: (T s, smoothness) per family, and success.
PAPER = {"A": (3.2, 0.31), "B": (4.7, 0.35), "C": (5.1, 0.41), "D": (6.5, 0.57),
         "E": (7.3, 0.51)}
PAPER_SUCCESS = {"static": 98.6, "dynamic": 97.8}
PUBLISHED_MBM = ("VAMP RRT-Connect (one CPU core): median 35 µs planning, 95th pct 343 µs, "
                 "100 % solved; cuRobo (RTX 6000 Ada GPU): median 31 ms, 100 % solved — as "
                 "published (shared/benchmarks/motionbenchmaker/README.md), not measured here.")


def load(path: str | Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def _median(values) -> float:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


def _p(values, q) -> float:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.percentile(values, q)) if values else float("nan")


def _fmt(x: float, digits: int = 2) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def paper_table(records: list[dict]) -> list[str]:
    """Our DAMON beside the paper's, families A–E, laid out like Table 2."""
    runs = [r for r in records if r.get("planner") == "damon" and r.get("family") in PAPER]
    lines = ["| setting | ours T (s) | paper T (s) | ours smooth. Σ‖ΔΘ‖ (rad) | paper smooth. | "
             "ours success | runs |", "|---|---|---|---|---|---|---|"]
    for family, (t_paper, s_paper) in PAPER.items():
        rs = [r for r in runs if r["family"] == family]
        if not rs:
            continue
        ok = [r for r in rs if r.get("success")]
        lines.append(f"| {family} | {_fmt(_median([r['total_time_s'] for r in ok]))} | {t_paper} "
                     f"| {_fmt(_median([r['path_length_rad'] for r in ok]))} | {s_paper} | "
                     f"{100 * len(ok) / len(rs):.0f} % | {len(rs)} |")
    lines.append("\nOurs: T is simulated time from the goal to the goal held (planning, "
                 "re-planning and motion); smoothness is FORMAT.md's `path_length_rad`, "
                 "Σ‖ΔΘ‖ over the executed joint path sampled at the control rate. The paper "
                 "sums over its via points, so the two smoothness columns are not the same "
                 "measure.")
    for kind, dynamic in (("static", False), ("dynamic", True)):
        rs = [r for r in records if r.get("planner") == "damon" and "dynamic" in r
              and r["dynamic"] == dynamic]
        if rs:
            rate = 100 * np.mean([bool(r.get("success")) for r in rs])
            lines.append(f"\nSuccess, {kind} scenarios (all families): ours {rate:.1f} % of "
                         f"{len(rs)} runs; paper {PAPER_SUCCESS[kind]} %.")
    return lines


def planner_table(records: list[dict]) -> list[str]:
    by: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        if r.get("planner") and r.get("family"):
            by[r["planner"]].append(r)
    lines = ["| planner | runs | success | contacts | median T (s) | median path (rad) | "
             "plan p50 (ms) | re-plan p50 (ms) | re-plan p99 (ms) | re-plans |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, rs in sorted(by.items()):
        ok = [r for r in rs if r.get("success")]
        replans = [x for r in rs for x in (r.get("replan_latency_ms") or [])]
        lines.append(
            f"| {name} | {len(rs)} | {100 * len(ok) / len(rs):.1f} % | "
            f"{sum(bool(r.get('collided')) for r in rs)} | "
            f"{_fmt(_median([r.get('total_time_s') for r in ok]))} | "
            f"{_fmt(_median([r.get('path_length_rad') for r in ok]))} | "
            f"{_fmt(_median([1e3 * r['planning_time_s'] for r in rs if r.get('planning_time_s')]), 1)} | "  # noqa: E501
            f"{_fmt(_median(replans), 1)} | {_fmt(_p(replans, 99), 1)} | {len(replans)} |")
    settings = {r["planner"]: r.get("planner_settings") for r in records if r.get("planner")}
    lines.append("\nPlanner settings: " + "; ".join(
        f"`{k}` {json.dumps(v)}" for k, v in sorted(settings.items())))
    return lines


def mbm_table(records: list[dict]) -> list[str]:
    """Per set and planner: problems, solved, contacts on the exact meshes, plan time p50/p95
    and path length p50, then every set together; problems refused before planning (a goal
    outside the joint limits) are counted beneath."""
    by: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in records:
        if r.get("set") and r.get("planner"):
            by[(r["set"], r["planner"])].append(r)
            by[("all", r["planner"])].append(r)
    lines = ["| set | planner | problems | solved | contacts | plan p50 (ms) | plan p95 (ms) | "
             "path p50 (rad) |", "|---|---|---|---|---|---|---|---|"]
    for (name, planner), rs in sorted(by.items(), key=lambda kv: (kv[0][0] == "all", kv[0])):
        times = [1e3 * r["planning_time_s"] for r in rs]
        solved = [r for r in rs if r.get("success")]
        touches = sum(r.get("error") == "path touches meshes" for r in rs)
        label = f"**{name}**" if name == "all" else name
        lines.append(f"| {label} | {planner} | {len(rs)} | {len(solved)} "
                     f"({100 * len(solved) / len(rs):.1f} %) | {touches} | "
                     f"{_fmt(_median([1e3 * r['planning_time_s'] for r in solved] or times), 1)}"
                     f" | {_fmt(_p(times, 95), 1)} | "
                     f"{_fmt(_median([r['path_length_rad'] for r in solved]), 2)} |")
    refused = [r for r in records if r.get("set") and not r.get("planner")]
    if refused:
        lines += ["", f"Refused before planning ({len(refused)}): " + "; ".join(
            str(r.get("error")) for r in refused)]
    return lines


def _band_key(band: str) -> float:
    """Bands in order of speed ("0.1-0.3 m/s" < "0.3-0.6 m/s" ...); others last."""
    try:
        return float(band.split("-")[0])
    except ValueError:
        return math.inf


def _stress_groups(runs: dict[str, list[dict]]):
    """{(band, planner): {label: records}} over every labelled run of the stress bench."""
    by: dict[tuple[str, str], dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for label, records in runs.items():
        for r in records:
            if r.get("planner") and r.get("band") not in (None, "static", "other"):
                by[(r["band"], r["planner"])][label].append(r)
    return dict(sorted(by.items(), key=lambda kv: (_band_key(kv[0][0]), kv[0][1])))


def stress_table(runs: dict[str, list[dict]]) -> list[str]:
    """Per speed band and planner, for each labelled run (ideal perception, latency and
    noise, ...): success, contacts, the least clearance of all runs on the exact meshes, and
    the re-route latency p50/p99."""
    labels = list(runs)
    head = "| band | planner | " + " | ".join(
        f"{label}: success | contacts | least clearance (mm) | re-route p50 / p99 (ms)"
        for label in labels) + " |"
    lines = [head, "|---|---|" + "---|---|---|---|" * len(labels)]
    for (band, planner), per_label in _stress_groups(runs).items():
        cells = []
        for label in labels:
            rs = per_label.get(label, [])
            if not rs:
                cells.append("– | – | – | –")
                continue
            ok = sum(bool(r.get("success")) for r in rs)
            clear = [1e3 * r["min_clearance_m"] for r in rs
                     if r.get("min_clearance_m") is not None]
            replans = [x for r in rs for x in (r.get("replan_latency_ms") or [])]
            cells.append(f"{ok}/{len(rs)} ({100 * ok / len(rs):.1f} %) | "
                         f"{sum(bool(r.get('collided')) for r in rs)} | "
                         f"{_fmt(min(clear, default=math.nan), 1)} | "
                         f"{_fmt(_p(replans, 50), 1)} / {_fmt(_p(replans, 99), 1)}")
        lines.append(f"| {band} | {planner} | " + " | ".join(cells) + " |")
    return lines


def stress_plot(runs: dict[str, list[dict]], out_dir: Path) -> Path:
    """Success per speed band, one line per planner and labelled run, beside the paper's
    dynamic success (97.8 %, a single number over its dynamic scenes, drawn flat)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _stress_groups(runs)
    bands = sorted({band for band, _ in groups}, key=_band_key)
    fig, ax = plt.subplots(figsize=(7, 4))
    for planner in sorted({p for _, p in groups}):
        for label in runs:
            rates = []
            for band in bands:
                rs = groups.get((band, planner), {}).get(label, [])
                rates.append(100 * np.mean([bool(r.get("success")) for r in rs]) if rs
                             else np.nan)
            if not np.all(np.isnan(rates)):  # a planner not run with this label
                ax.plot(bands, rates, marker="o", label=f"{planner}, {label}")
    ax.axhline(PAPER_SUCCESS["dynamic"], color="grey", linestyle="--",
               label=f"paper, dynamic ({PAPER_SUCCESS['dynamic']} %)")
    ax.set(xlabel="mover speed band", ylabel="success (%)",
           title="Stress bench: success vs mover speed")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out_dir / "benchmarks_stress.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def stress_section(runs: dict[str, list[dict]], command: str, out_dir: Path) -> list[str]:
    figure = stress_plot(runs, out_dir)
    scenes = {r.get("scenario") for rs in runs.values() for r in rs}
    return ["## Stress bench: movers crossing the hand's way, per speed band", "",
            f"`{command}`", "", f"{len(scenes)} scenes; each labelled run is one "
            "`damon-ros bench --by-band` result file.", "", *stress_table(runs), "",
            f"![success vs speed]({figure.name})"]


def perception_table(rows: list[dict]) -> list[str]:
    """`damon-ros bench-tracker --out` rows: per camera set, shape kind and motion, the share of
    whole-view frames whose estimate contains the true object, excess, errors and CPU time."""
    from damon_ros.tools.bench_tracker import summarise

    groups, times = summarise(rows)
    lines = ["| cameras | kind | motion | frames | partial | contained | cut contained | "
             "excess p50 | "
             "centre p50 (mm) | centre p95 (mm) | velocity p50 (m/s) | estimates |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for g in groups:
        lines.append(f"| {g['cameras']} | {g['kind']} | {g['motion']} | {g['frames']} | "
                     f"{g['partial']} | {_fmt(g['contained_pct'])} % | "
                     f"{_fmt(g['partial_contained_pct'])} % | "
                     f"{_fmt(g['excess_pct'], 0)} % | {_fmt(g['centre_p50_mm'], 1)} | "
                     f"{_fmt(g['centre_p95_mm'], 1)} | {_fmt(g['velocity_p50'], 3)} | "
                     f"{g['estimates'].replace(',', ', ')} |")
    lines.append("\nContained: the share of frames, of those whose detection is not flagged "
                 "partial, in which every surface sample of the true object (8 mm apart) lies "
                 "in the estimate; cut contained: the same of the frames flagged partial (cut "
                 "off or occluded: what may be hidden is bounded by the class prior). "
                 "Excess: estimate volume / true volume - 1. Tracker CPU time "
                 "per 640x480 frame per camera (one process, offline): " + "; ".join(
                     f"{t['cameras']} p50 {t['p50_ms']:.2f} ms, p95 {t['p95_ms']:.2f} ms"
                     for t in times) + ".")
    return lines


def plots(records: list[dict], out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        if r.get("planner") and r.get("family"):
            by[r["planner"]].append(r)
    names = sorted(by)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].boxplot([[r["total_time_s"] for r in by[n] if r.get("success")] or [np.nan]
                     for n in names], tick_labels=names)
    axes[0].set(ylabel="T (s)", title="Task time T per planner (successful runs)")
    axes[1].boxplot([[x for r in by[n] for x in (r.get("replan_latency_ms") or [])] or [np.nan]
                     for n in names], tick_labels=names)
    axes[1].set(ylabel="ms", yscale="log", title="Re-plan latency per planner")
    for a in axes:
        a.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    path = out_dir / "benchmarks_distributions.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return [path]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros report",
                                     description="Write docs/BENCHMARKS.md from bench results.")
    parser.add_argument("--results", default=None,
                        help="public-scenario results (JSON lines): the whole page anew; "
                             "without it only the sections of --stress and --tracker are "
                             "rewritten")
    parser.add_argument("--results-command", default="",
                        help="the command that produced --results (quoted in the page)")
    parser.add_argument("--stress", action="append", default=[], metavar="LABEL=FILE",
                        help="stress-bench results (bench --by-band) under a label, e.g. "
                             "ideal=s.jsonl; repeat for each perception setting. Alone (no "
                             "--results): only the page's stress section is rewritten")
    parser.add_argument("--stress-command", default="",
                        help="the commands that produced --stress (quoted in the page)")
    parser.add_argument("--mbm", default=None,
                        help="MotionBenchMaker results (JSON lines); alone, only the page's "
                             "MotionBenchMaker section is rewritten")
    parser.add_argument("--mbm-command", default="", help="the command that produced --mbm")
    parser.add_argument("--tracker", action="append", default=[],
                        help="damon-ros bench-tracker --out results (JSON lines); repeatable")
    parser.add_argument("--tracker-command", action="append", default=[],
                        help="the command that produced each --tracker file, in order")
    parser.add_argument("--out", default="docs/BENCHMARKS.md")
    args = parser.parse_args(argv)
    if len(args.tracker_command) != len(args.tracker):
        parser.error("give one --tracker-command for each --tracker file")
    if not (args.results or args.tracker or args.stress or args.mbm):
        parser.error("give --results (the whole page), --stress, --mbm or --tracker (their "
                     "sections)")
    if args.results and not args.results_command:
        parser.error("--results needs --results-command")
    runs = {}
    for item in args.stress:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            parser.error(f"--stress {item!r}: expected LABEL=FILE")
        runs[label] = load(path)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.results:
        write_page(args, out)
    if args.mbm:
        write_marked(out, "mbm", [
            "## MotionBenchMaker (static, many obstacles, joint goals; plan once)", "",
            f"`{args.mbm_command}`", "", *mbm_table(load(args.mbm)), "",
            f"Published reference: {PUBLISHED_MBM}", ""])
    if runs:
        write_marked(out, "stress", stress_section(runs, args.stress_command, out.parent))
    if args.tracker:
        section = ["## Perception against ground truth (the tracker, frame by frame)", ""]
        for path, command in zip(args.tracker, args.tracker_command, strict=True):
            section += [f"`{command}`", "", *perception_table(load(path)), ""]
        write_marked(out, "perception", section)
    print(f"wrote {out}")
    return 0


def write_page(args: argparse.Namespace, out: Path) -> None:
    """The page from ``--results``; marked sections of the old page (MotionBenchMaker's,
    the stress bench's, ...) kept."""
    records = load(args.results)
    figures = plots(records, out.parent)
    lines = ["# Benchmarks", "",
             "Generated by `damon-ros report` from result files; every number below comes from "
             "the command quoted above its table, run on the project's 2-core machine "
             "(no GPU).", "",
             "## DAMON against the paper's Table 2 (public scenarios, families A–E)", "",
             f"`{args.results_command}`", "", *paper_table(records), "",
             "## DAMON against OMPL on the same runs (all public scenarios)", "",
             f"`{args.results_command}`", "", *planner_table(records), "",
             *[f"![distributions]({f.name})" for f in figures], ""]
    kept = _marked_sections(out.read_text()) if out.exists() else []
    out.write_text("\n".join(lines + kept) + "\n")


def write_marked(page: Path, name: str, lines: list[str]) -> None:
    """Put ``lines`` between the ``<!-- name -->`` markers of ``page`` (appended the first
    time); `main` carries such sections over when it writes the page anew."""
    text = page.read_text() if page.exists() else "# Benchmarks\n"
    mark = (f"<!-- {name} -->", f"<!-- /{name} -->")
    block = "\n".join([mark[0], *lines, mark[1]])
    if mark[0] in text and mark[1] in text:
        head, rest = text.split(mark[0], 1)
        text = head + block + rest.split(mark[1], 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    page.write_text(text)


def _marked_sections(text: str) -> list[str]:
    """Sections other commands keep in the page between ``<!-- name -->`` and
    ``<!-- /name -->`` (the ablation's table): carried over, not lost to a new report."""
    import re

    return [m.group(0) + "\n" for m in re.finditer(r"<!-- ([\w-]+) -->.*?<!-- /\1 -->", text,
                                                   flags=re.S)]
