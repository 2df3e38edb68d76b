"""Plots of a trajectory (matplotlib, Agg backend): energy, momentum maps, deformation, bodies.

- ``energy.png``: total, kinetic and potential energy, and the relative error |E - E0| / |E0|;
- ``momenta.png``: the momentum maps (103), (108), (109) minus their initial values: total linear
  momentum, affine momentum J = sum_K (x_K p_K^T + phi_K pi_K), angular momentum J - J^T;
- ``deformation.png``: trace invariants K_a = Tr(G^a) (17), volumes det phi_K and relative
  volumes det phi_L / det phi_1 (79), one line per body for at most :data:`TRACED_BODIES`
  bodies (evenly sampled) and the band between the smallest and largest value over all bodies;
- ``bodies.png`` (n = 2): first and last frame, each body drawn as the image of the disc of its
  drawing radius under phi (an ellipse) with the image of the material axis e_1 as a line (at
  most :data:`DRAWN_BODIES` bodies, evenly sampled, for large systems);
- optionally ``bodies.gif`` / ``bodies.mp4``: the animation of the n = 2 bodies.

Every plot reads the trajectory one frame at a time (``h5md.open_trajectory``), so memory is
O(N) for any number of frames.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402

from affinebody.h5md import Trajectory  # noqa: E402

DPI = 110
#: Bodies drawn as individual lines in deformation.png (the band covers all of them).
TRACED_BODIES = 16
#: Bodies drawn as ellipses in bodies.png and the animation.
DRAWN_BODIES = 5000


def _sample(bodies: int, most: int) -> np.ndarray:
    """Evenly spaced body indices, at most ``most`` of them."""
    return np.unique(np.linspace(0, bodies - 1, min(bodies, most)).round().astype(int))


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_energy(trajectory: Trajectory, path: str | Path) -> Path:
    """Energies and the relative energy error |E(t) - E(0)| / |E(0)| versus time."""
    t = trajectory.time
    obs = trajectory.observables
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.plot(t, obs["total_energy"], label="total E", color="k")
    top.plot(t, obs["kinetic_energy"], label="kinetic T", alpha=0.8)
    top.plot(t, obs["potential_energy"], label="potential V", alpha=0.8)
    top.set_ylabel("energy")
    top.legend(loc="best")
    e = obs["total_energy"]
    scale = max(abs(float(e[0])), np.finfo(float).tiny)
    error = np.abs(e - e[0]) / scale
    bottom.semilogy(t[1:], np.maximum(error[1:], 1e-17), color="C3")
    bottom.set_ylabel("|E - E(0)| / |E(0)|")
    bottom.set_xlabel("time")
    top.set_title("energy (75a)")
    fig.tight_layout()
    return _save(fig, Path(path))


def _components(values: np.ndarray, skew: bool = False):
    """(label, series) of the entries of [T, n] or [T, n, n] arrays (upper triangle if skew)."""
    if values.ndim == 2:
        return [(f"[{a}]", values[:, a]) for a in range(values.shape[1])]
    n = values.shape[-1]
    return [(f"[{a},{b}]", values[:, a, b]) for a in range(n) for b in range(n)
            if not skew or a < b]


def plot_momenta(trajectory: Trajectory, path: str | Path) -> Path:
    """Changes of the momentum maps since t = 0 (conserved when V has the symmetry)."""
    t = trajectory.time
    obs = trajectory.observables
    panels = [
        ("linear momentum p (103)", obs["linear_momentum"], False),
        ("affine momentum J (109)", obs["affine_momentum"], False),
        ("angular momentum J - J^T", obs["angular_momentum"], True),
    ]
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 8), sharex=True)
    for ax, (title, values, skew) in zip(axes, panels, strict=True):
        values = np.asarray(values)
        change = values - values[:1]
        for label, series in _components(change, skew):
            ax.plot(t, series, label=label, lw=1)
        worst = float(np.max(np.abs(change))) if change.size else 0.0
        ax.set_title(f"{title}: change since t = 0 (max {worst:.2e})", fontsize=9)
        if values.shape[-1] <= 3:
            ax.legend(fontsize=7, ncol=3, loc="best")
    axes[-1].set_xlabel("time")
    fig.tight_layout()
    return _save(fig, Path(path))


def plot_deformation(trajectory: Trajectory, path: str | Path) -> Path:
    """Trace invariants K_a (17), volumes det phi_K and relative volumes (79): lines for a
    sample of bodies, a band from the smallest to the largest value over all bodies."""
    from affinebody.deformation import trace_invariants

    t = trajectory.time
    n, bodies = trajectory.n, trajectory.bodies
    traced = _sample(bodies, TRACED_BODIES)
    series = []  # per frame: [n + 2, traced] values and [n + 2, 2] min/max over all bodies
    for k in range(trajectory.frames):
        phi = np.asarray(trajectory.phi[k])
        invariants = np.asarray(trace_invariants(phi))  # [N, n]
        volumes = np.linalg.det(phi)
        columns = [invariants[:, a] for a in range(n)] + [volumes, volumes / volumes[0]]
        series.append((np.stack([c[traced] for c in columns]),
                       np.stack([(np.min(c), np.max(c)) for c in columns])))
    lines = np.stack([s[0] for s in series])  # [T, n + 2, traced]
    bands = np.stack([s[1] for s in series])  # [T, n + 2, 2]
    labels = [f"K{a + 1} = Tr G^{a + 1}" for a in range(n)] + ["det phi_K",
                                                              "det phi_K / det phi_1"]
    fig, axes = plt.subplots(n + 2, 1, figsize=(7, 2.2 * (n + 2)), sharex=True)
    for row, ax in enumerate(axes):
        if bodies > len(traced):
            ax.fill_between(t, bands[:, row, 0], bands[:, row, 1], color="0.85",
                            label=f"range over all {bodies} bodies")
        ax.plot(t, lines[:, row, :], lw=0.8)
        ax.set_ylabel(labels[row])
    axes[-1].set_xlabel("time")
    shown = f"{len(traced)} of {bodies} bodies" if bodies > len(traced) else f"{bodies} bodies"
    axes[0].set_title(f"deformation invariants and volumes ({shown})")
    if bodies > len(traced):
        axes[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _save(fig, Path(path))


def body_outlines(x: np.ndarray, phi: np.ndarray, radius: np.ndarray, points: int = 64):
    """Ellipses x_K + phi_K (r_K u), |u| = 1, as polygons [N, points, 2] (n = 2)."""
    angle = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1)  # [P, 2]
    return x[:, None, :] + np.einsum("kia,pa->kpi", phi, circle) * radius[:, None, None]


def _axis_segments(x, phi, radius):
    tip = x + phi[:, :, 0] * radius[:, None]
    return np.stack([x, tip], axis=1)


def _limits(trajectory: Trajectory, frames, drawn):
    low = np.full(2, np.inf)
    high = np.full(2, -np.inf)
    for k in frames:
        x, phi = np.asarray(trajectory.x[k])[drawn], np.asarray(trajectory.phi[k])[drawn]
        reach = np.linalg.norm(phi, ord=2, axis=(-2, -1)) * trajectory.radius[drawn]
        low = np.minimum(low, np.min(x - reach[:, None], axis=0))
        high = np.maximum(high, np.max(x + reach[:, None], axis=0))
    pad = 0.05 * max(float(np.max(high - low)), 1e-9)
    return low - pad, high + pad


def _draw(ax, trajectory: Trajectory, frame: int, low, high, drawn):
    x, phi = np.asarray(trajectory.x[frame])[drawn], np.asarray(trajectory.phi[frame])[drawn]
    radius = trajectory.radius[drawn]
    shapes = PolyCollection(body_outlines(x, phi, radius), facecolors="C0",
                            edgecolors="k", alpha=0.55, linewidths=0.8)
    axes = LineCollection(_axis_segments(x, phi, radius), colors="C3", linewidths=1.2)
    ax.add_collection(shapes)
    ax.add_collection(axes)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")
    ax.set_title(f"t = {trajectory.time[frame]:.4g} (step {int(trajectory.step[frame])})",
                 fontsize=9)
    return shapes, axes


def plot_bodies(trajectory: Trajectory, path: str | Path) -> Path:
    """First and last frame of a 2D trajectory, bodies as ellipses phi(disc) (n = 2 only)."""
    if trajectory.n != 2:
        raise ValueError(f"bodies can be drawn for n = 2 only (got n = {trajectory.n})")
    drawn = _sample(trajectory.bodies, DRAWN_BODIES)
    frames = (0, trajectory.frames - 1)
    low, high = _limits(trajectory, frames, drawn)
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    for ax, frame in zip(axes, frames, strict=True):
        _draw(ax, trajectory, frame, low, high, drawn)
    sample = (f" ({len(drawn)} of {trajectory.bodies} bodies)"
              if len(drawn) < trajectory.bodies else "")
    fig.suptitle(f"bodies: images of their discs under phi; red: phi e_1{sample}")
    fig.tight_layout()
    return _save(fig, Path(path))


def animate_bodies(trajectory: Trajectory, path: str | Path, fps: int = 20) -> Path:
    """GIF (Pillow) or MP4 (ffmpeg) of a 2D trajectory, chosen by the suffix of ``path``."""
    from matplotlib import animation

    if trajectory.n != 2:
        raise ValueError(f"animations need n = 2 (got n = {trajectory.n})")
    path = Path(path)
    if path.suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise ValueError("MP4 needs ffmpeg on PATH; install it or use --animate gif")
        writer = animation.FFMpegWriter(fps=fps)
    elif path.suffix == ".gif":
        writer = animation.PillowWriter(fps=fps)
    else:
        raise ValueError(f"animation file must end in .gif or .mp4 (got {path.name})")
    drawn = _sample(trajectory.bodies, DRAWN_BODIES)
    low, high = _limits(trajectory, range(trajectory.frames), drawn)
    fig, ax = plt.subplots(figsize=(5, 5))
    shapes, axes = _draw(ax, trajectory, 0, low, high, drawn)
    radius = trajectory.radius[drawn]

    def update(frame):
        x = np.asarray(trajectory.x[frame])[drawn]
        phi = np.asarray(trajectory.phi[frame])[drawn]
        shapes.set_verts(body_outlines(x, phi, radius))
        axes.set_segments(_axis_segments(x, phi, radius))
        ax.set_title(f"t = {trajectory.time[frame]:.4g}", fontsize=9)
        return shapes, axes

    movie = animation.FuncAnimation(fig, update, frames=trajectory.frames, blit=False)
    movie.save(path, writer=writer, dpi=80)
    plt.close(fig)
    return path


def plot_all(trajectory: Trajectory, folder: str | Path, *, animate: str | None = None,
             fps: int = 20) -> list[Path]:
    """Write every plot into ``folder``; returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if trajectory.frames == 0:
        raise ValueError("the trajectory has no frames to plot")
    paths = [
        plot_energy(trajectory, folder / "energy.png"),
        plot_momenta(trajectory, folder / "momenta.png"),
        plot_deformation(trajectory, folder / "deformation.png"),
    ]
    if trajectory.n == 2:
        paths.append(plot_bodies(trajectory, folder / "bodies.png"))
        if animate:
            paths.append(animate_bodies(trajectory, folder / f"bodies.{animate}", fps=fps))
    elif animate:
        raise ValueError(f"--animate needs n = 2 (got n = {trajectory.n})")
    return paths
