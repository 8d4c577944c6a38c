"""`RetryPacer`: how often a holding arm searches for a route again."""

from __future__ import annotations

import numpy as np

from damon_ros.core.shapes import Shape
from damon_ros.planning.graph_planner import Scene
from damon_ros.planning.reactive import RetryPacer


def _scene(*positions) -> Scene:
    return Scene.of([Shape("sphere", (0.05,), np.asarray(p, float), name=f"s{k}")
                     for k, p in enumerate(positions)])


def test_a_repeated_failure_backs_off_and_the_searches_keep_their_share():
    pacer = RetryPacer(period_s=0.1, max_period_s=0.8, cpu_share=0.5)
    scene = _scene((0.5, 0.0, 0.5))
    t, busy, starts = 0.0, 0.0, []
    while t < 20.0:
        if pacer.due(t, scene):
            starts.append(t)
            spent = 0.25  # each failing search takes its whole budget
            busy += spent
            pacer.failed(t, spent, "no route: blocked 0.12 m from the goal", scene)
            t += spent
        t += 0.05  # the planner's updates
    assert busy / t <= 0.5 + 1e-9  # at most half of the time searching
    gaps = np.diff(starts)
    assert gaps[-1] >= 0.8 - 1e-9  # backed off to the longest period
    assert gaps[0] < gaps[-1]


def test_a_new_failure_or_a_changed_scene_is_retried_soon():
    pacer = RetryPacer(period_s=0.1, max_period_s=0.8, cpu_share=0.5)
    scene = _scene((0.5, 0.0, 0.5))
    for k in range(6):  # backed off: 0.8 s between retries
        pacer.failed(10.0 * k, 0.01, "no route", scene)
    assert not pacer.due(50.5, scene)
    assert pacer.due(50.5, _scene((0.5, 0.1, 0.5)))  # the obstacle moved 10 cm
    assert pacer.due(50.5, _scene((0.5, 0.0, 0.5), (0.2, 0.2, 0.2)))  # a new one
    assert not pacer.due(50.01, _scene((0.5, 0.1, 0.5)))  # yet within the share
    pacer.failed(60.0, 0.01, "another reason", scene)
    assert pacer.due(60.1, scene)  # a different failure starts at the base period
    pacer.reset()
    assert pacer.due(60.0, scene)
