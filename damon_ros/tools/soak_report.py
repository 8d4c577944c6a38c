"""The soak run's judgement: the verdict on the window rows, the tables, the progress lines.

Pure functions of the rows `damon_ros.tools.soak_monitor.Monitor` closes (plain dicts, as
written to ``soak.json``), so the pass/fail rules can be read and tested without a graph.
The bounds are in `damon_ros.tools.soak`'s module docstring and ``damon-ros soak --help``.
"""

from __future__ import annotations

import math
from collections import Counter

DRIFT_BOUND = 1.10  # last window / first window, p99 re-route latency and each node's RSS
DRIFT_MIN_WINDOWS = 3  # fewer windows: too short to tell drift from warm-up
DRIFT_MIN_SAMPLES = 30  # re-routes per window below which its p99 is not compared
NODES = ("mock_panda", "controller", "planner", "mock_camera", "tracker")
VIOLATIONS = ("velocity", "acceleration", "jerk", "position", "q_outside")
# /damon/sim/limits counters (damon_ros.simulation.mock_arm.LimitMonitor);
# *_jitter are a subset, late apart
LIMIT_KEYS = ("velocity", "acceleration", "jerk", "position", "late", "acceleration_jitter",
              "jerk_jitter")


# ----------------------------------------------------------------------------- verdict

def _drift(first: float, last: float) -> tuple[bool | None, str]:
    if not (math.isfinite(first) and math.isfinite(last)) or first <= 0.0:
        return None, "no data"
    return last <= DRIFT_BOUND * first, f"{last / first:.3f} x"


def verdict(rows: list[dict], crashes: list[str], note: str) -> dict:
    """Every check with its numbers; passed only if none failed (the rules:
    `damon_ros.tools.soak`'s module doc)."""
    checks = []

    def check(name: str, ok: bool | None, detail: str) -> None:
        checks.append({"check": name, "ok": ok, "detail": detail})

    check("no crash", not crashes and not note, "; ".join(crashes) or note or "all nodes ran")
    contacts = sum(r["contacts"] for r in rows)
    clearance = min((r["min_clearance_m"] for r in rows), default=math.nan)
    check("0 contacts", contacts == 0 and bool(rows),
          f"{contacts} contact rounds, min clearance {clearance:.3f} m (exact meshes)")
    total = {k: sum(r["limits"][k] for r in rows) for k in (*VIOLATIONS, *LIMIT_KEYS[4:])}
    check("0 limit violations", sum(total[k] for k in VIOLATIONS) == 0 and bool(rows),
          ", ".join(f"{total[k]} {k}" for k in VIOLATIONS) + f" (of the acceleration and "
          f"jerk ones {total['acceleration_jitter']} and {total['jerk_jitter']} are within "
          f"the limits at the controller's own tick spacing); {total['late']} late commands")
    reached = sum(r["goals_reached"] for r in rows)
    in_period = sum(r.get("goals_reached_in_period", 0) for r in rows)
    timed_out = sum(len(r.get("goals_missed", [])) for r in rows)
    check("goals reached", reached > 0,
          f"{reached} of {sum(r['goals_sent'] for r in rows)} goals reached ({in_period} "
          f"within the goal period), {timed_out} unreached at the timeout")
    _drift_checks(rows, check)
    failed = [c["check"] for c in checks if c["ok"] is False]
    return {"passed": not failed, "failed": failed, "checks": checks,
            "bound": DRIFT_BOUND, "min_windows_for_drift": DRIFT_MIN_WINDOWS}


def _drift_checks(rows: list[dict], check) -> None:
    if len(rows) < DRIFT_MIN_WINDOWS:
        check("latency/RSS drift", None, f"not checked: {len(rows)} windows < "
              f"{DRIFT_MIN_WINDOWS}")
        return
    first, last = rows[0], rows[-1]
    a, b = first["reroute_after_input_ms"], last["reroute_after_input_ms"]
    name = f"p99 re-route latency last <= {DRIFT_BOUND:.2f} x first"
    counts = (a.get("n", 0), b.get("n", 0))
    if min(counts) < DRIFT_MIN_SAMPLES:  # a p99 of a few values is their maximum: noise
        check(name, None, f"not checked: {counts[0]} and {counts[1]} re-routes, fewer than "
              f"{DRIFT_MIN_SAMPLES} in a window")
    else:
        ok, detail = _drift(a["p99"], b["p99"])
        check(name, ok, f"{a['p99']:.1f} -> {b['p99']:.1f} ms over {counts[0]} and "
              f"{counts[1]} re-routes ({detail})")
    for name in NODES:
        if name not in first["rss_mb"]:
            continue
        mb = (first["rss_mb"][name], last["rss_mb"].get(name, math.nan))
        ok, detail = _drift(*mb)
        check(f"RSS {name} last <= {DRIFT_BOUND:.2f} x first", ok,
              f"{mb[0]:.1f} -> {mb[1]:.1f} MB ({detail})")


# ----------------------------------------------------------------------------- report

def print_progress(row: dict, windows: int) -> None:
    rr = row["reroute_after_input_ms"]
    rss = ", ".join(f"{k.split(' ')[0]} {v:.0f}" for k, v in row["rss_mb"].items())
    cpu = ", ".join(f"{k.split(' ')[0]} {v:.2f}" for k, v in row.get("cpu_cores", {}).items())
    print(f"[soak] window {row['window']}/{windows} ({row['t0_s']:.0f}-{row['t1_s']:.0f} s): "
          f"js {row['joint_states_hz']:.0f} Hz, cmd {row['commands_hz']:.0f} Hz, frames "
          f"{row['frames_hz']:.1f} Hz, goals {row['goals_reached']}/{row['goals_sent']}, "
          f"re-routes {rr['n']} p99 {rr['p99']:.0f} ms, contacts {row['contacts']}, "
          f"violations {row['violations']}, RSS MB {rss}, CPU cores {cpu} (load "
          f"{row.get('load_avg', math.nan):.1f})", flush=True)


def _fmt(value, spec: str = ".1f") -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan"
    return format(value, spec)


def _table(header: list[str], lines: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in lines)) for i, h in enumerate(header)]
    out = ["| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |",
           "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += ["| " + " | ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) + " |"
            for r in lines]
    return "\n".join(out)


def report_tables(rows: list[dict]) -> list[str]:
    """Tables per window: throughput and drops, latency, safety and memory, and each
    node's CPU share in cores (from /proc/<pid>/stat, with the machine's load average)."""
    if not rows:
        return ["(no window completed)"]
    throughput = _table(
        ["win", "t (s)", "js Hz", "cmd Hz", "frames Hz", "obst Hz", "goals sent/reached",
         "goal T p50 s", "traj", "holds", "js skipped", "js gaps", "js max gap ms",
         "untracked frames"],
        [[str(r["window"]), f"{r['t0_s']:.0f}-{r['t1_s']:.0f}", _fmt(r["joint_states_hz"]),
          _fmt(r["commands_hz"]), _fmt(r["frames_hz"]), _fmt(r["obstacles_hz"]),
          f"{r['goals_sent']}/{r['goals_reached']}", _fmt(r["goal_time_s_p50"], ".2f"),
          str(r["trajectories"]), str(r["holds"]), str(r["js_skipped"]), str(r["js_gaps"]),
          _fmt(r["js_max_gap_ms"]), _fmt(r["frames_untracked"], "d")] for r in rows])
    latency = _table(
        ["win", "re-routes", "decided p50/p90/p99/max ms", "after input p50/p90/p99/max ms",
         "plans", "plan p50 ms", "tracker fps", "tracker lat p50/p95/p99 ms"],
        [[str(r["window"]), str(r["reroute_decided_ms"]["n"]),
          _pcts(r["reroute_decided_ms"]), _pcts(r["reroute_after_input_ms"]),
          str(r["plan_decided_ms"]["n"]), _fmt(r["plan_decided_ms"]["p50"]),
          _fmt(r["tracker"].get("tracked_fps")),
          f"{_fmt(r['tracker'].get('latency_p50_ms'))}/"
          f"{_fmt(r['tracker'].get('latency_p95_ms'))}/"
          f"{_fmt(r['tracker'].get('latency_p99_ms'))}"] for r in rows])
    names = list(rows[0]["rss_mb"])
    safety = _table(
        ["win", "contacts", "min clr m", "violations v/a/j/pos/q", "a/j jitter", "late cmds",
         *[f"RSS {n.split(' ')[0]} MB" for n in names]],
        [[str(r["window"]), str(r["contacts"]), _fmt(r["min_clearance_m"], ".3f"),
          "/".join(str(r["limits"][k]) for k in VIOLATIONS),
          f"{r['limits']['acceleration_jitter']}/{r['limits']['jerk_jitter']}",
          str(r["limits"]["late"]), *[_fmt(r["rss_mb"].get(n)) for n in names]]
         for r in rows])
    cpu_names = list(rows[0].get("cpu_cores", {}))
    cpu = _table(
        ["win", *[f"CPU {n.split(' ')[0]}" for n in cpu_names], "load avg"],
        [[str(r["window"]), *[_fmt(r.get("cpu_cores", {}).get(n), ".2f") for n in cpu_names],
          _fmt(r.get("load_avg"))] for r in rows]) if cpu_names else None
    return [throughput, latency, safety] + ([cpu] if cpu else [])


def _pcts(p: dict) -> str:
    return "/".join(_fmt(p[k], ".0f") for k in ("p50", "p90", "p99", "max"))


def goal_lines(records: list[dict]) -> list[str]:
    """One line per goal sent: when, reached after how long (or how it ended), and the
    causes of the planner's holds while it was in force."""
    lines = []
    for k, r in enumerate(records, 1):
        ended = (f"reached after {r['reached_after_s']:.2f} s" if r["outcome"] == "reached"
                 else r["outcome"])
        holds = "; ".join(f"{n} x {cause}" for cause, n in
                          sorted(r["holds"].items(), key=lambda kv: -kv[1]))
        lines.append(f"  {k:3d} {r['goal']} sent at {r['sent_s']:.1f} s: {ended}"
                     + (f"; holds: {holds}" if holds else ""))
    return lines


def print_report(result: dict) -> None:
    for table in report_tables(result["rows"]):
        print("\n" + table)
    records = [g for r in result["rows"] for g in r.get("goal_records", [])]
    if records:
        print(f"\ngoals ({len(records)}), times from the first window's start:")
        print("\n".join(goal_lines(records)))
    missed = [why for r in result["rows"] for why in r.get("goals_missed", [])]
    if missed:
        print(f"\ngoals unreached at the timeout, truly unreachable ({len(missed)}), with "
              "what the planner was doing then:")
        for why, count in Counter(missed).most_common():
            print(f"  {count} x {why}")
    v = result["verdict"]
    print(f"\nverdict: {'PASS' if v['passed'] else 'FAIL'} (bounds: 0 crashes, 0 contacts, "
          f"0 limit violations, >= 1 goal reached; with >= {DRIFT_MIN_WINDOWS} windows the "
          f"last window's p99 re-route latency and each node's mean RSS <= "
          f"{DRIFT_BOUND:.2f} x the first window's)")
    for c in v["checks"]:
        mark = {True: "ok  ", False: "FAIL", None: "n/a "}[c["ok"]]
        print(f"  {mark} {c['check']}: {c['detail']}")
    if v["failed"]:
        print("failed: " + "; ".join(v["failed"]))
