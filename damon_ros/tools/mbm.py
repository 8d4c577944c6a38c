"""MotionBenchMaker problems (MoveIt PlanningScene + MotionPlanRequest YAML) as scenarios.

Reads ``panda_problems.tar.bz2`` directly (or its extracted folder): every
``<set>/sceneNNNN.yaml`` with its ``requestNNNN.yaml`` becomes a static scenario with a joint
goal (the goal pose is the goal joints' TCP pose). MoveIt cylinders are
``[height, radius]``; boxes are full extents. The data set's start states open each finger
to :data:`FINGER_OPENING` (0.065 m, beyond the Panda's 0.04 m joint limit: VAMP's Panda
model is built the same way), and its problems are scored with that hand: the bench builds
both collision models with it. At our default 0.04 m, 70 of the 700 goals (most of the cage
set) put the fingers into the grasped object; at 0.065 m none does.
"""

from __future__ import annotations

import tarfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from damon_ros.core.scenario import Scenario, ScenarioError, parse_scenario

JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")
FINGER_OPENING = 0.065
"""m, each finger in every start state of the data set; a problem with another is refused."""


def _obstacles(scene: dict, source: str) -> list[dict]:
    out = []
    objects = (scene.get("world") or {}).get("collision_objects") or []
    for obj in objects:
        for k, (prim, pose) in enumerate(zip(obj.get("primitives") or [],
                                             obj.get("primitive_poses") or [], strict=False)):
            dims = prim.get("dimensions") or []
            if prim.get("type") == "box":
                shape, size = "box", list(dims)
            elif prim.get("type") == "cylinder":
                shape, size = "cylinder", [dims[1], dims[0]]  # MoveIt: [height, radius]
            elif prim.get("type") == "sphere":
                shape, size = "sphere", list(dims)
            else:
                raise ScenarioError(source, f"{obj.get('id')}", f"unsupported primitive "
                                    f"{prim.get('type')!r}")
            out.append({"name": f"{obj.get('id')}_{k}", "shape": shape, "size": size,
                        "color": "red", "pose": {"position": pose["position"],
                                                 "orientation": pose["orientation"]}})
    return out


def _joint_values(names, positions) -> list[float]:
    table = dict(zip(names, positions, strict=False))
    return [float(table[j]) for j in JOINTS]


def problem(set_name: str, index: str, scene: dict, request: dict, robot) -> Scenario:
    """One MotionBenchMaker problem as a static :class:`Scenario` with a joint goal."""
    source = f"{set_name}/scene{index}.yaml"
    js = request["start_state"]["joint_state"]
    start = _joint_values(js["name"], js["position"])
    fingers = dict(zip(js["name"], js["position"], strict=False))
    if any(abs(float(fingers.get(f, FINGER_OPENING)) - FINGER_OPENING) > 1e-9 for f in FINGERS):
        raise ScenarioError(source, "start_state", f"fingers at "
                            f"{[fingers.get(f) for f in FINGERS]}, the bench models "
                            f"{FINGER_OPENING} m")
    constraints = request["goal_constraints"][0]["joint_constraints"]
    goal = _joint_values([c["joint_name"] for c in constraints],
                         [c["position"] for c in constraints])
    position, quat = robot.tcp_pose(np.array(goal))
    data = {
        "format": 1, "name": f"{set_name}-{index}", "robot": "panda",
        "description": f"MotionBenchMaker {set_name} problem {index}",
        "start": {"joints": start},
        "goal": {"pose": {"position": position.tolist(), "orientation": quat.tolist()},
                 "joints": goal},
        "obstacles": _obstacles(scene, source), "time_limit": 30.0,
    }
    return parse_scenario(data, source)


def _pairs(path: Path) -> Iterator[tuple[str, str, str, str]]:
    """(set, index, scene text, request text) from a tarball or a folder."""
    if path.is_file():
        with tarfile.open(path, "r:*") as tar:
            members = {m.name: m for m in tar.getmembers() if m.isfile()}
            for name in sorted(members):
                p = Path(name)
                if p.name.startswith("scene") and p.suffix == ".yaml":
                    index = p.stem[len("scene"):]
                    req = str(p.with_name(f"request{index}.yaml"))
                    if req in members:
                        yield (p.parent.name, index,
                               tar.extractfile(members[name]).read().decode(),
                               tar.extractfile(members[req]).read().decode())
        return
    for scene in sorted(path.rglob("scene*.yaml")):
        index = scene.stem[len("scene"):]
        req = scene.with_name(f"request{index}.yaml")
        if req.exists():
            yield scene.parent.name, index, scene.read_text(), req.read_text()


def load_problems(path: str | Path, robot, per_set: int | None = None
                  ) -> Iterator[tuple[str, Scenario | ScenarioError]]:
    """(set name, scenario or the error that rejected it) for every problem."""
    counts: dict[str, int] = {}
    for set_name, index, scene_text, request_text in _pairs(Path(path)):
        name = set_name.removesuffix("_panda")
        if per_set is not None and counts.get(name, 0) >= per_set:
            continue
        counts[name] = counts.get(name, 0) + 1
        try:
            yield name, problem(name, index, yaml.safe_load(scene_text),
                                yaml.safe_load(request_text), robot)
        except (ScenarioError, KeyError, TypeError, IndexError, yaml.YAMLError) as exc:
            yield name, exc if isinstance(exc, ScenarioError) else ScenarioError(
                f"{set_name}/scene{index}.yaml", "<problem>", f"unreadable: {exc!r}")


def is_mbm(path: str | Path) -> bool:
    p = Path(path)
    return p.name.endswith((".tar.bz2", ".tar.gz", ".tar")) or (
        p.is_dir() and any(p.rglob("request*.yaml")))
