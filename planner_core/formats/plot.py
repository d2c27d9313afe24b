"""Figures like the paper's (figs. 2-4): top view, 3-D view, derivatives against bounds.

matplotlib is an optional dependency and is imported here only (Agg backend).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.problem import ORDER_NAMES, FloatArray, Polytope, Trajectory

if TYPE_CHECKING:
    from planner_core.formats.io import Scenario


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _vertices(poly: Polytope) -> FloatArray | None:
    try:
        from planner_core.geometry import polytope_vertices

        v = polytope_vertices(poly)
    except (ImportError, ValueError):
        return None
    return v if v.shape[0] >= 4 else None


def _hull2d(pts: FloatArray) -> FloatArray:
    from scipy.spatial import ConvexHull

    h = ConvexHull(pts)
    idx = [*list(h.vertices), h.vertices[0]]
    return np.asarray(pts[idx])


def _samples(traj: Trajectory, n: int = 1500) -> tuple[FloatArray, FloatArray]:
    t = np.linspace(traj.t0, traj.t_end, n)
    return t, traj.evaluate(t, 0)


def plot_path2d(traj: Trajectory, obstacles: Sequence[Polytope], path: str) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 7))
    for i, poly in enumerate(traj.corridors or ()):
        v = _vertices(poly) if poly is not None else None
        if v is not None:
            h = _hull2d(v[:, :2])
            ax.plot(h[:, 0], h[:, 1], color="tab:green", lw=0.7, alpha=0.6,
                    label="corridor (top view)" if i == 0 else None)
    for i, poly in enumerate(obstacles):
        v = _vertices(poly)
        if v is not None:
            h = _hull2d(v[:, :2])
            ax.fill(h[:, 0], h[:, 1], color="0.45", alpha=0.8, label="obstacle" if i == 0 else None)
    _, p = _samples(traj)
    ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=2, label="trajectory")
    ctrl = traj.control_points.reshape(-1, 3)
    ax.plot(ctrl[:, 0], ctrl[:, 1], ".", color="tab:orange", ms=3, label="control points")
    w = traj.waypoints
    ax.plot(w[:, 0], w[:, 1], "o", color="tab:red", ms=6, label="waypoints")
    for i, q in enumerate(w):
        ax.annotate(str(i), q[:2], textcoords="offset points", xytext=(5, 5))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectory, top view")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _faces(poly: Polytope) -> list[FloatArray]:
    from scipy.spatial import ConvexHull

    v = _vertices(poly)
    if v is None:
        return []
    hull = ConvexHull(v)
    return [v[s] for s in hull.simplices]


def plot_path3d(traj: Trajectory, obstacles: Sequence[Polytope], path: str) -> None:
    plt = _plt()
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(9, 7))
    ax = fig.add_subplot(projection="3d")
    for poly in obstacles:
        faces = _faces(poly)
        if faces:
            ax.add_collection3d(Poly3DCollection(faces, facecolor="0.5", edgecolor="none", alpha=0.5))
    for cor in traj.corridors or ():
        faces = _faces(cor) if cor is not None else []
        if faces:
            ax.add_collection3d(Poly3DCollection(faces, facecolor="none", edgecolor="tab:green",
                                                 linewidths=0.2, alpha=0.25))
    _, p = _samples(traj)
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="tab:blue", lw=2)
    w = traj.waypoints
    ax.scatter(w[:, 0], w[:, 1], w[:, 2], color="tab:red", s=20)
    lo = np.min(p, axis=0) - 1.0
    hi = np.max(p, axis=0) + 1.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title("Trajectory, obstacles (grey) and corridors (green)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_derivatives(traj: Trajectory, lo: FloatArray, hi: FloatArray, path: str) -> None:
    plt = _plt()
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    t = np.linspace(traj.t0, traj.t_end, 2000)
    colors = ("tab:blue", "tab:orange", "tab:green")
    units = ("m/s", "m/s²", "m/s³", "m/s⁴")
    for k, ax in enumerate(axes, start=1):
        v = traj.evaluate(t, k)
        for a in range(3):
            ax.plot(t, v[:, a], color=colors[a], lw=1.2, label="xyz"[a])
            for bound in (lo[k - 1, a], hi[k - 1, a]):
                if np.isfinite(bound):
                    ax.axhline(bound, color=colors[a], ls="--", lw=0.8, alpha=0.7)
        for tb in traj.times:
            ax.axvline(tb, color="0.85", lw=0.6, zorder=0)
        ax.set_ylabel(f"{ORDER_NAMES[k]} [{units[k - 1]}]")
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("t [s]")
    axes[0].set_title("Derivatives per axis (dashed: bounds; grey: waypoint times)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_all(traj: Trajectory, scenario: Scenario, prefix: str) -> list[str]:
    """Write PREFIX_path2d.png, PREFIX_path3d.png and PREFIX_derivatives.png; return the paths."""
    paths = [f"{prefix}_path2d.png", f"{prefix}_path3d.png", f"{prefix}_derivatives.png"]
    plot_path2d(traj, scenario.obstacles, paths[0])
    plot_path3d(traj, scenario.obstacles, paths[1])
    b = scenario.problem.bounds
    plot_derivatives(traj, b.lo, b.hi, paths[2])
    return paths
