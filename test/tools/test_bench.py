"""damon-ros bench: JSON lines as FORMAT.md says, and contact scored on the exact meshes."""

from __future__ import annotations

import json

import numpy as np

from damon_ros.cli import main as cli
from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios, load_scenario
from damon_ros.planning.graph_planner import GraphPlanner, PlanResult
from damon_ros.planning.reactive import ReactivePlanner
from damon_ros.simulation.closed_loop import SimConfig, run_scenario
from damon_ros.tools.bench import main as bench

FIELDS = {"scenario", "planner", "success", "collided", "min_clearance_m", "total_time_s",
          "planning_time_s", "replans", "replan_latency_ms", "path_length_rad",
          "max_joint_velocity", "max_joint_acceleration", "limits_respected", "error"}


def test_two_scenarios_two_planners_write_every_field(tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: 1\nname: broken\n")
    scenarios = [str(public_scenarios_dir() / n) for n in ("B-001.yaml", "G-002.yaml")]
    assert bench(["--scenarios", *scenarios, str(bad), "--planners", "damon,rrtconnect",
                  "--out", str(out), "--quiet"]) == 0
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    errors = [r for r in lines if "planner" not in r]
    runs = [r for r in lines if "planner" in r]
    assert len(errors) == 1 and "bad.yaml" in errors[0]["error"]
    assert {(r["scenario"], r["planner"]) for r in runs} == {
        (s, p) for s in ("B-001", "G-002") for p in ("damon", "rrtconnect")}
    for r in runs:
        assert FIELDS <= set(r), FIELDS - set(r)
        assert r["success"] and not r["collided"] and r["limits_respected"]
        assert r["min_clearance_m"] > 0 and r["total_time_s"] > r["planning_time_s"] > 0
        assert r["planner_settings"]
    table = capsys.readouterr().out
    assert "family" in table and "rrtconnect" in table


class _Reckless(GraphPlanner):
    """Deliberately unsafe: always the straight line, never checked."""

    def _route(self, q_start, q_goal, scene) -> PlanResult:
        path = np.array([q_start, q_goal])
        return PlanResult(True, "", path=path, trajectory=self._time_parameterize(path),
                          goal_q=q_goal)

    def _route_moving(self, q_start, qd_start, q_goal, scene) -> PlanResult:
        return self._route(q_start, q_goal, scene)  # not even the braking segment


def test_a_colliding_planner_run_is_scored_as_contact():
    scenario = next(s for s in load_public_scenarios() if s.name == "A-001")
    fast, mesh = Robot("fast"), Robot("mesh")
    # the straight line from start to goal goes through A-001's box
    q_goal = scenario.goal.joints
    states = scenario.start + np.linspace(0, 1, 50)[:, None] * (q_goal - scenario.start)
    assert mesh.distances(states, scenario.obstacles_at(0.0)).min() < 0
    runtime = ReactivePlanner(_Reckless(None, fast, fast.limits))
    record = run_scenario(scenario, runtime, "reckless", mesh, fast, SimConfig())
    assert record.collided and not record.success
    assert record.min_clearance_m <= 0.0


def test_mbm_table_counts_contacts_refusals_and_every_set_together():
    from damon_ros.tools.report import mbm_table

    rec = [{"set": "box", "planner": "damon", "success": True, "planning_time_s": 0.01,
            "path_length_rad": 2.0, "error": None},
           {"set": "box", "planner": "damon", "success": False, "planning_time_s": 0.5,
            "path_length_rad": None, "error": "path touches meshes"},
           {"set": "cage", "planner": "damon", "success": True, "planning_time_s": 0.03,
            "path_length_rad": 4.0, "error": None},
           {"set": "cage", "scenario": "cage/scene0001.yaml", "success": False,
            "error": "goal outside the joint limits"}]
    lines = mbm_table(rec)
    box = next(line for line in lines if line.startswith("| box |"))
    assert "| 2 | 1 (50.0 %) | 1 |" in box and "| 10.0 |" in box
    total = next(line for line in lines if line.startswith("| **all** |"))
    assert "| 3 | 2 (66.7 %) | 1 |" in total and "| 3.00 |" in total
    assert lines.index(total) > lines.index(box)
    assert "Refused before planning (1)" in lines[-1]


def test_the_stress_section_is_written_per_band_and_kept_apart(tmp_path):
    from damon_ros.tools.report import main as report

    def run(band, planner, ok, collided, clearance, replans):
        return {"scenario": f"S-{band}-{planner}-{ok}", "band": band, "planner": planner,
                "success": ok, "collided": collided, "min_clearance_m": clearance,
                "replan_latency_ms": replans}

    ideal, noisy = tmp_path / "ideal.jsonl", tmp_path / "noisy.jsonl"
    ideal.write_text("\n".join(json.dumps(r) for r in [
        run("1-1.5 m/s", "damon", False, True, -0.001, [4.0]),
        run("0.1-0.3 m/s", "damon", True, False, 0.02, [2.0, 6.0]),
        run("0.1-0.3 m/s", "damon", True, False, 0.03, []),
        run("static", "damon", True, False, 0.05, [])]))
    noisy.write_text(json.dumps(run("0.1-0.3 m/s", "damon", False, False, 0.01, [])))
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("# Benchmarks\n\nkept text\n")
    assert report(["--stress", f"ideal={ideal}", "--stress", f"33 ms={noisy}",
                   "--stress-command", "damon-ros bench --by-band", "--out", str(page)]) == 0
    text = page.read_text()
    assert "kept text" in text and text.count("<!-- stress -->") == 1
    rows = [line for line in text.splitlines() if line.startswith("| 0.1-0.3") or
            line.startswith("| 1-1.5")]
    assert rows[0].startswith("| 0.1-0.3 m/s | damon | 2/2 (100.0 %) | 0 | 20.0 | 4.0 / ")
    assert "| 0/1 (0.0 %) | 0 | 10.0 |" in rows[0]  # the second label's cells
    assert rows[1].startswith("| 1-1.5 m/s | damon | 0/1 (0.0 %) | 1 | -1.0 |")
    assert "| static |" not in text and (tmp_path / "benchmarks_stress.png").stat().st_size
    # a second report replaces the section instead of adding one
    assert report(["--stress", f"ideal={ideal}", "--out", str(page)]) == 0
    assert page.read_text().count("<!-- stress -->") == 1


def test_the_band_table_gives_the_executing_arms_re_routes_their_own_p99_and_failed_retries():
    from damon_ros.tools.bench import band_summary

    runs = [{"band": "0.1-0.3 m/s", "planner": "damon", "success": True, "collided": False,
             "min_clearance_m": 0.02, "replan_latency_ms": [2.0, 30.0, 3.0],
             "replan_resumed": [False, True, False], "retry_failed_ms": [5.0, 9.0]},
            {"band": "0.1-0.3 m/s", "planner": "damon", "success": True, "collided": False,
             "min_clearance_m": 0.03, "replan_latency_ms": [4.0]}]  # an older record
    header, _, row = band_summary(runs).splitlines()
    assert header.split()[-8:] == ["exec", "p99", "ms", "failed", "retries", "failed", "p99",
                                   "ms"]
    cells = row.split()  # ..., replans, p50, p99, max, exec p99, failed retries, failed p99
    assert cells[-7] == "4" and float(cells[-4]) == 30.0
    # the holding arm's 30 ms retry is left out; the older record has no flags to read
    assert float(cells[-3]) == round(float(np.percentile([2.0, 3.0], 99)), 2)
    # a holding arm's retries that found no route: counted apart, with their own p99
    assert cells[-2] == "2" and float(cells[-1]) == round(float(np.percentile([5.0, 9.0], 99)), 2)


def test_the_stress_view_groups_runs_by_mover_speed_band(tmp_path, capsys):
    folder = tmp_path / "stress"
    assert cli(["scenarios", "generate", "--families", "S", "--bands", "0.3:0.6,1.0:1.5",
                "--count", "1", "--seed", "2", "--out", str(folder), "--quiet"]) == 0
    out = tmp_path / "results.jsonl"
    assert bench(["--scenarios", str(folder), str(public_scenarios_dir() / "A-001.yaml"),
                  "--planners", "damon", "--out", str(out), "--by-band", "--quiet"]) == 0
    runs = {r["scenario"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert runs["A-001"]["band"] == "static" and runs["A-001"]["mover_speed_m_s"] == 0.0
    for path in folder.iterdir():
        r = runs[load_scenario(path).name]
        assert r["band"] == ("0.3-0.6 m/s" if "v0.3" in path.name else "1-1.5 m/s")
        assert r["planner_settings"]["space_time"] is True
    table = capsys.readouterr().out
    assert "clr min mm" in table and "1-1.5 m/s" in table and "static" in table


def test_bench_tracker_compares_camera_sets_and_refuses_a_bad_camera_list(tmp_path, capsys):
    from damon_ros.tools.bench_tracker import main as bench_tracker

    scenario = str(public_scenarios_dir() / "A-001.yaml")
    assert bench_tracker(["--scenarios", scenario, "--seconds", "0.3", "--fps", "10",
                          "--cameras", "camera.yaml", "camera.yaml,camera_side.yaml"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()
            if line.startswith("box ")]
    assert [r[2] for r in rows] == ["1:1", "2:2"]  # set number: cameras, one row per set
    assert all(r[6] == "100.00%" for r in rows)  # the estimate contains the box
    assert int(rows[1][8].rstrip("%")) < int(rows[0][8].rstrip("%"))  # less volume excess
    assert bench_tracker(["--scenarios", scenario, "--cameras", "camera.yaml,nowhere.yaml"]) == 2
    assert "nowhere.yaml" in capsys.readouterr().err
    assert bench(["--scenarios", scenario, "--perception", "camera", "--cameras", "x,",
                  "--out", str(tmp_path / "r.jsonl")]) == 2


def test_the_plan_once_ablation_runs_the_closed_loop(tmp_path):
    """``damon-noreplan`` goes through the same closed loop as damon (which passes the
    arm's velocity to every update): it plans once and never re-routes."""
    out = tmp_path / "noreplan.jsonl"
    assert bench(["--scenarios", str(public_scenarios_dir() / "D-001.yaml"), "--planners",
                  "damon-noreplan", "--out", str(out), "--quiet"]) == 0
    (record,) = map(json.loads, out.read_text().splitlines())
    assert record["planner"] == "damon-noreplan" and "run failed" not in str(record["error"])
    assert record["replans"] == 0


def test_bench_tracker_rows_feed_the_reports_perception_section(tmp_path, capsys):
    from damon_ros.tools.bench_tracker import main as bench_tracker
    from damon_ros.tools.report import main as report

    rows = tmp_path / "tracker.jsonl"
    assert bench_tracker(["--scenarios", str(public_scenarios_dir() / "B-001.yaml"),
                          "--seconds", "0.2", "--fps", "10", "--out", str(rows)]) == 0
    assert {r["kind"] for r in map(json.loads, rows.read_text().splitlines())} == {"sphere"}
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("# Benchmarks\n\n## Planners\n\nkept\n")
    for _ in range(2):  # a second run replaces the section, it does not add one
        assert report(["--tracker", str(rows), "--tracker-command", "bench-tracker B",
                       "--out", str(page)]) == 0
    text = page.read_text()
    assert "kept" in text and text.count("## Perception against ground truth") == 1
    assert "`bench-tracker B`" in text
    line = next(x for x in text.splitlines() if x.startswith("| camera.yaml | sphere |"))
    assert "| 100.00 % |" in line
