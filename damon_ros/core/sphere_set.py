"""The file format of a fitted sphere set (``config/panda_spheres.json``): JSON, no pickle.

Kept apart from the fit (:mod:`damon_ros.core.sphere_fit`, which needs the meshes) so that
:mod:`damon_ros.core.collision` can load a set without importing the fitter.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT = "damon_ros.sphere_set"
VERSION = 1


@dataclass(frozen=True)
class SphereSet:
    """Spheres fixed to joint frames: ``joints`` (S,), ``centers`` (S, 3) in the joint frame,
    ``radii`` (S,), ``links`` (S,) for witness labels, and the fit's bound ``delta`` (m):
    no sphere bulges more than that beyond the meshes."""

    joints: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    links: tuple[str, ...]
    delta: float
    bulge: np.ndarray  # per sphere, radius - depth of its centre: the proven excess bound

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps({
            "format": FORMAT, "version": VERSION, "delta": self.delta,
            "note": "fitted by damon_ros.core.sphere_fit to the convex collision meshes of "
                    "panda.urdf (fingers at FINGER_OPENING); centres in the joint frame, m",
            "spheres": [{"joint": int(j), "link": n, "center": [round(float(x), 7) for x in c],
                         "radius": round(float(r), 7), "bulge": round(float(b), 7)}
                        for j, n, c, r, b in zip(self.joints, self.links, self.centers,
                                                 self.radii, self.bulge, strict=True)],
        }, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> SphereSet:
        data = json.loads(Path(path).read_text())
        if data.get("format") != FORMAT or data.get("version") != VERSION:
            raise ValueError(f"{path}: not a {FORMAT} v{VERSION} file")
        s = data["spheres"]
        return cls(np.array([e["joint"] for e in s], dtype=np.int64),
                   np.array([e["center"] for e in s], dtype=float),
                   np.array([e["radius"] for e in s], dtype=float),
                   tuple(e["link"] for e in s), float(data["delta"]),
                   np.array([e["bulge"] for e in s], dtype=float))
