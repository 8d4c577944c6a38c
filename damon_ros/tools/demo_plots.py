"""Plots a person looks at after a demo: joints against limits, clearance, an animation."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ARM_FRAMES = ("panda_link0", "panda_link1", "panda_link2", "panda_link3", "panda_link4",
              "panda_link5", "panda_link6", "panda_link7", "panda_hand", "panda_hand_tcp")
COLORS = {"red": "tab:red", "green": "tab:green", "blue": "tab:blue", "yellow": "gold"}


def write_plots(out: Path, scenario, result: dict) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    from damon_ros.core.limits import joint_limits

    rec = result["recording"]
    limits = joint_limits("panda")
    t, q, qd = np.array(rec.t), np.array(rec.q), np.array(rec.qd)
    files = [_joints(out / "joints.png", t, q, qd, limits),
             _clearance(out / "clearance.png", np.array(rec.clearance_t),
                        np.array(rec.clearance))]
    files.append(_animation(out / "demo.gif", scenario, t, q, rec))
    return files


def _joints(path: Path, t, q, qd, limits) -> Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(7, 2, figsize=(11, 13), sharex=True)
    for j in range(7):
        a, b = axes[j]
        a.plot(t, q[:, j], "b-")
        a.axhline(limits.lower[j], color="r", ls=":")
        a.axhline(limits.upper[j], color="r", ls=":")
        a.set_ylabel(f"q{j + 1} (rad)")
        b.plot(t, qd[:, j], "g-")
        b.axhline(limits.velocity[j], color="r", ls=":")
        b.axhline(-limits.velocity[j], color="r", ls=":")
        b.set_ylabel(f"dq{j + 1} (rad/s)")
    axes[-1][0].set_xlabel("scenario time (s)")
    axes[-1][1].set_xlabel("scenario time (s)")
    fig.suptitle("Joint positions and velocities against the Panda's limits (red)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _clearance(path: Path, t, d) -> Path:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(t, d, "k-")
    ax.axhline(0.0, color="r", ls=":", label="contact")
    ax.set(xlabel="scenario time (s)", ylabel="clearance (m)",
           title="Exact (mesh) clearance between the arm and every obstacle")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _animation(path: Path, scenario, t, q, rec, fps: float = 10.0) -> Path:
    import imageio.v2 as imageio
    import matplotlib.pyplot as plt

    from damon_ros.core.robot import Robot

    robot = Robot("fast")
    frames = []
    times = np.arange(t[0], t[-1], 1.0 / fps) if len(t) > 1 else t
    plans = [(tt, p) for tt, p in rec.trajectories if len(p)]
    fig = plt.figure(figsize=(6, 5))
    for when in times:
        k = int(np.searchsorted(t, when))
        k = min(k, len(t) - 1)
        fig.clf()
        ax = fig.add_subplot(projection="3d")
        pts = np.array([robot.fk(q[k], f)[:3, 3] for f in ARM_FRAMES])
        ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], "o-", color="0.3", lw=4, ms=3)
        for obstacle in scenario.obstacles:
            for part in obstacle.parts_at(when):
                draw_shape(ax, part, COLORS[obstacle.color], estimate=False)
        for shape in _estimate_at(rec.estimates, when):
            draw_shape(ax, shape, "0.2", estimate=True)
        current = [p for tt, p in plans if tt <= when]
        if current:
            tcp = np.array([robot.tcp_pose(x)[0] for x in current[-1][::5]])
            ax.plot(tcp[:, 0], tcp[:, 1], tcp[:, 2], "g--", lw=1)
        ax.set(xlim=(-0.2, 0.9), ylim=(-0.8, 0.8), zlim=(0.0, 1.0), xlabel="x", ylabel="y",
               zlabel="z", title=f"{scenario.name}  t = {when:5.2f} s\n"
               "filled: true obstacles, wireframe: what the planner is told")
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    imageio.mimsave(path, frames, duration=1.0 / fps, loop=0)
    return path


def _estimate_at(estimates: list, when: float) -> list:
    """The planner's obstacle shapes as last received at or before ``when``."""
    shapes = []
    for t, current in estimates:
        if t > when:
            break
        shapes = current
    return shapes


def draw_shape(ax, shape, color, estimate: bool) -> None:
    """A shape as it is: a sphere as a sphere, a (rotated) box, cylinder or point set as
    the hull of its `enclosing_vertices`; a true one filled, an estimate as a wireframe."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from damon_ros.core.shapes import enclosing_vertices

    if shape.kind == "sphere":
        u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 16), np.linspace(0, np.pi, 9))
        xyz = [shape.position[i] + shape.size[0] * w for i, w in enumerate(
            (np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)))]
        if estimate:
            ax.plot_wireframe(*xyz, color=color, lw=0.5, alpha=0.7)
        else:
            ax.plot_surface(*xyz, color=color, alpha=0.5, linewidth=0)
        return
    faces = shape_faces(shape)
    if faces is None:  # flat or a single point: show the points
        ax.scatter(*enclosing_vertices(shape).T, color=color, s=4)
        return
    ax.add_collection3d(Poly3DCollection(faces, facecolor="none" if estimate else color,
                                         edgecolor=color if estimate else "none",
                                         alpha=0.7 if estimate else 0.5, linewidth=0.5))


def shape_faces(shape) -> np.ndarray | None:
    """(N, 3, 3) hull triangles of a non-sphere shape's `enclosing_vertices`; None if flat."""
    from scipy.spatial import ConvexHull, QhullError

    from damon_ros.core.shapes import enclosing_vertices

    vertices = enclosing_vertices(shape, sides=16)
    try:
        return vertices[ConvexHull(vertices).simplices]
    except (QhullError, ValueError):
        return None
