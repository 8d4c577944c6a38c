"""``damon-ros bench-loops`` runs the 1 kHz pair and prints a CPU row for every process."""

from __future__ import annotations

import os
import re

from rosutil import next_domain_id

from damon_ros.tools import bench_loops


def test_prints_a_cpu_row_per_process(capsys):
    code = bench_loops.main(["--seconds", "1", "--warmup", "4", "--readers", "1",
                             "--realtime-priority", "0",
                             "--domain-id", str(next_domain_id(__file__))])
    out = capsys.readouterr().out
    assert code == 0, out
    for name in ("mock_panda", "controller", "reader 0", "all"):
        row = re.search(rf"^\| {name} \| ([0-9.]+) \|", out, re.MULTILINE)
        assert row is not None, out
        assert name == "reader 0" or float(row.group(1)) > 0.0, out  # the loops ran
        # per-thread times add up to no more than the machine has (a thread's own stat,
        # not its process's total counted once per thread)
        assert name == "all" or float(row.group(1)) <= os.cpu_count() + 0.05, out


def test_refuses_bad_arguments(capsys):
    assert bench_loops.main(["--seconds", "0"]) == 2
    assert bench_loops.main(["--domain-id", "101"]) == 2
    assert "--seconds must be > 0" in capsys.readouterr().err
