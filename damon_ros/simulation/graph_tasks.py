"""Closed-loop runs of the graph planner as engine jobs (``learning.engines``).

A job names a graph file and a scenario file (plain data, so it can travel to a Ray node);
each worker keeps its robot models and the graph it last loaded, since loading a graph and
building the pinocchio/coal models cost more than most runs.
"""

from __future__ import annotations

from damon_ros.core.robot import Robot
from damon_ros.core.scenario import Scenario, load_scenario
from damon_ros.learning.graph import LatentGraph
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
from damon_ros.planning.reactive import ReactivePlanner
from damon_ros.simulation.closed_loop import RunRecord, SimConfig, run_scenario


class GraphTaskState:
    """Per worker: the fast and exact robot models and the graph loaded last."""

    def __init__(self) -> None:
        self.fast, self.mesh = Robot("fast"), Robot("mesh")
        self._graph: tuple[str, LatentGraph] | None = None

    def graph(self, path: str) -> LatentGraph:
        if self._graph is None or self._graph[0] != path:
            self._graph = (path, LatentGraph.load(path))
        return self._graph[1]

    def planner(self, path: str, config: PlannerConfig | None = None,
                warm: bool = True) -> GraphPlanner:
        """A fresh planner on the graph; ``warm``: warmed up, for runs whose planning time
        is measured."""
        planner = GraphPlanner(self.graph(path), self.fast, self.fast.limits, config)
        if warm:
            planner.warm_up()
        return planner

    def run(self, graph_path: str, scenario: Scenario, seed: int,
            config: PlannerConfig | None = None) -> RunRecord:
        """One closed-loop run with a fresh planner (no state carried between tasks)."""
        runtime = ReactivePlanner(self.planner(graph_path, config))
        return run_scenario(scenario, runtime, "damon", self.mesh, self.fast,
                            SimConfig(seed=seed))


def setup() -> GraphTaskState:
    return GraphTaskState()


def run_job(state: GraphTaskState, job: dict) -> dict:
    """``job``: ``graph`` and ``scenario`` paths, ``seed``, optionally ``planner`` (a dict
    of :class:`PlannerConfig` fields); any other keys are echoed."""
    scenario = load_scenario(job["scenario"])
    config = PlannerConfig(**job["planner"]) if job.get("planner") else None
    record = state.run(job["graph"], scenario, job["seed"], config).as_json()
    return {**job, **record, "family": scenario.family, "dynamic": scenario.is_dynamic}

