"""``damon-ros soak``, short: every node over real DDS for 45 s, three windows, a verdict.

The soak itself bounds every wait (node start-up, each window) and stops its nodes in a
``finally``, also when pytest-timeout interrupts it, so it runs in this process. Ground-
truth obstacles (``--no-camera``) as in test_demo.py: the camera + tracker path is covered
by test_node_tracker.py, and this 2-core machine cannot also render and track at speed.
"""

from __future__ import annotations

import json
import math

import numpy as np
from rosutil import next_domain_id

from damon_ros.tools import soak
from damon_ros.tools.soak_monitor import cdr_stamp
from damon_ros.tools.soak_report import LIMIT_KEYS, NODES, verdict


def test_short_soak_passes_with_goals_reached_and_every_node_measured(tmp_path, capsys):
    code = soak.main(["--minutes", "0.75", "--window-s", "15", "--goal-period-s", "5",
                      "--startup-s", "10", "--no-camera", "--out", str(tmp_path),
                      "--domain-id", str(next_domain_id(__file__))])
    out = capsys.readouterr().out
    assert code == 0, out[-6000:]
    result = json.loads((tmp_path / "soak.json").read_text())
    rows = result["rows"]
    assert len(rows) == 3 and out.count("[soak] window") == 3, out[-3000:]
    assert result["verdict"]["passed"] and not result["crashes"]
    assert sum(r["goals_sent"] for r in rows) >= 8  # one per 5 s over 45 s
    assert sum(r["goals_reached"] for r in rows) > 0
    for row in rows:
        assert row["contacts"] == 0 and row["violations"] == 0, row
        assert row["joint_states_hz"] > 800 and row["commands_hz"] > 800, row
        for name in (n for n in NODES if n != "tracker"):
            assert row["rss_mb"][name] > 20.0, (name, row["rss_mb"])
    assert rows[0]["reroute_decided_ms"]["n"] + rows[0]["plan_decided_ms"]["n"] > 0
    for name in ("soak_scenario.yaml", "mock_panda.log", "planner.log"):
        assert (tmp_path / name).stat().st_size > 0
    assert "verdict: PASS" in out and "| win |" in out


def _row(p99: float, rss: float, contacts: int = 0, acceleration: int = 0) -> dict:
    limits = dict.fromkeys(LIMIT_KEYS, 0) | {"q_outside": 0, "acceleration": acceleration}
    return {"contacts": contacts, "min_clearance_m": 0.05, "limits": limits,
            "goals_sent": 10, "goals_reached": 9,
            "reroute_after_input_ms": {"p99": p99, "n": 100},
            "rss_mb": dict.fromkeys(("mock_panda", "planner"), rss)}


def test_verdict_fails_on_contact_violation_latency_and_memory_drift():
    assert verdict([_row(100.0, 200.0)] * 3, [], "")["passed"]
    cases = {
        "0 contacts": [_row(100.0, 200.0), _row(100.0, 200.0, contacts=1), _row(100, 200)],
        "0 limit violations": [_row(100.0, 200.0, acceleration=2)] + [_row(100.0, 200.0)] * 2,
        "p99 re-route latency last <= 1.10 x first": [_row(100.0, 200.0)] * 2 +
        [_row(111.0, 200.0)],
        "RSS planner last <= 1.10 x first": [_row(100.0, 200.0)] * 2 + [_row(100.0, 221.0)],
    }
    for check, rows in cases.items():
        result = verdict(rows, [], "")
        assert not result["passed"] and check in result["failed"], (check, result)
    crashed = verdict([_row(100.0, 200.0)] * 3, ["planner exited with -9"], "")
    assert crashed["failed"] == ["no crash"]
    short = verdict([_row(100.0, 200.0), _row(500.0, 900.0)], [], "")
    assert short["passed"]  # drift is not judged on fewer than 3 windows
    assert any(c["ok"] is None and "not checked" in c["detail"] for c in short["checks"])


def test_soak_scenario_is_valid_and_sweeps_last_the_whole_run(tmp_path):
    from damon_ros.core.scenario import load_scenario

    path, goals = soak.write_soak_scenario(tmp_path, 300.0)
    scenario = load_scenario(path)
    assert len(goals) == len(soak.GOAL_SCENARIOS) >= 2
    moving = [o for o in scenario.obstacles if o.is_dynamic]
    assert len(moving) == len(soak.SWEEPS)
    for o in moving:
        assert o.waypoints[-1, 0] >= 300.0
        ends = {tuple(np.round(o.position_at(t), 3)) for t in o.waypoints[1:, 0]}
        assert len(ends) == 2  # back and forth between its two end points
    assert math.isclose(scenario.time_limit, 300.0)


def test_cdr_stamp_reads_the_header_of_a_serialised_message():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    msg = JointState(name=["a"], position=[1.0])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1234, 500_000_000
    assert cdr_stamp(serialize_message(msg)) == 1234.5
