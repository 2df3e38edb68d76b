"""Plots of a trajectory (matplotlib, Agg backend): energy, momentum maps, deformation, bodies.

- ``energy.png``: total, kinetic and potential energy, and the relative error |E - E0| / |E0|;
- ``momenta.png``: the momentum maps minus their initial values, component by component:
  total linear momentum P = sum_K p_K, affine momentum J = sum_K (x_K p_K^T + phi_K pi_K) and
  angular momentum J - J^T (paper eqs. (103), (108), (109); none for n = 1); in a periodic box
  the box breaks the rotation symmetry, so J - J^T changes physically and the figure says so;
- ``deformation.png``: trace invariants K_a = Tr(G^a) of the Green tensor G = phi^T phi (17),
  volumes det phi_K and relative volumes det phi_K / det phi_1 (79), one labelled line per body
  for at most :data:`TRACED_BODIES` bodies (evenly sampled) and the band between the smallest
  and largest value over all bodies;
- ``bodies.png``: first and last frame, each body drawn as the image of the ball of its drawing
  radius under phi: for n = 1 a rod [x - r|phi|, x + r|phi|] on the line, one row per body,
  with the image phi e_1 of the material axis in red (its sign, on GL(1)), for n = 2 an
  ellipse with the image of e_1 as a line, for n = 3 a shaded ellipsoid {x + phi a : |a| <= r}
  (at most :data:`DRAWN_BODIES` bodies in 1D and 2D and :data:`DRAWN_ELLIPSOIDS` in 3D,
  evenly sampled, for large systems);
- optionally ``bodies.gif`` / ``bodies.mp4``: the animation of the n = 2 bodies.

Every axis names its quantity and its unit, in the file's unit system (``units.UNIT_LABELS``:
sigma, tau, m, epsilon for reduced units). Every plot reads the trajectory one frame at a time
(``h5md.open_trajectory``), so memory is O(N) for any number of frames.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402

from affinebody.h5md import Trajectory  # noqa: E402
from affinebody.units import UNIT_LABELS  # noqa: E402

DPI = 110
#: Bodies drawn as individual lines in deformation.png (the band covers all of them).
TRACED_BODIES = 16
#: Bodies drawn as ellipses (rods for n = 1) in bodies.png and the animation.
DRAWN_BODIES = 5000
#: Bodies drawn as ellipsoids in the 3D bodies.png.
DRAWN_ELLIPSOIDS = 400
#: Names of the axes of components (n <= 3); larger n numbers them from 1.
AXES = "xyz"


def _unit(trajectory: Trajectory, kind: str) -> str:
    """" [unit]" of a quantity kind in the trajectory's unit system ("" if unknown)."""
    label = UNIT_LABELS.get(trajectory.units, {}).get(kind)
    return f" [{label}]" if label else ""


def _time(trajectory: Trajectory, frame: int) -> str:
    """"t = 2.5 τ (step 250)" of a frame, for titles."""
    label = UNIT_LABELS.get(trajectory.units, {}).get("time", "")
    return (f"t = {trajectory.time[frame]:.4g}{' ' + label if label else ''} "
            f"(step {int(trajectory.step[frame])})")


def _axis(n: int, a: int) -> str:
    return AXES[a] if n <= len(AXES) else str(a + 1)


def _sample(bodies: int, most: int) -> np.ndarray:
    """Evenly spaced body indices, at most ``most`` of them."""
    return np.unique(np.linspace(0, bodies - 1, min(bodies, most)).round().astype(int))


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_energy(trajectory: Trajectory, path: str | Path) -> Path:
    """Energies and the relative energy error |E(t) - E(0)| / |E(0)| versus time; in a
    thermostatted run the error of the effective energy (H minus the heat), the conserved
    quantity there."""
    t = trajectory.time
    obs = trajectory.observables
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.plot(t, obs["total_energy"], label="total E", color="k")
    top.plot(t, obs["kinetic_energy"], label="kinetic T", alpha=0.8)
    top.plot(t, obs["potential_energy"], label="potential V", alpha=0.8)
    conserved = "effective_energy" if "effective_energy" in obs else "total_energy"
    if conserved == "effective_energy":
        top.plot(t, obs[conserved], label="effective E (H − heat)", color="k", ls="--")
    top.set_ylabel(f"energy{_unit(trajectory, 'energy')}")
    top.legend(loc="best")
    e = obs[conserved]
    scale = max(abs(float(e[0])), np.finfo(float).tiny)
    error = np.abs(e - e[0]) / scale
    bottom.semilogy(t[1:], np.maximum(error[1:], 1e-17), color="C3")
    bottom.set_ylabel("|E - E(0)| / |E(0)|" if conserved == "total_energy"
                      else "effective E: relative error")
    bottom.set_xlabel(f"time{_unit(trajectory, 'time')}")
    top.set_title("energy: E = T + V and its relative error")
    fig.tight_layout()
    return _save(fig, Path(path))


def plot_pressure(trajectory: Trajectory, path: str | Path) -> Path:
    """The scalar pressure Tr P / n with the diagonal of the pressure tensor, and the volume,
    versus time (periodic runs; docs/pressure.md)."""
    t, obs, n = trajectory.time, trajectory.observables, trajectory.n
    tensor = np.asarray(obs["pressure"])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for a in range(n):
        top.plot(t, tensor[:, a, a], alpha=0.5, lw=0.8, label=f"P_{_axis(n, a) * 2}")
    top.plot(t, np.trace(tensor, axis1=1, axis2=2) / n, color="k", label="Tr P / n")
    labels = UNIT_LABELS.get(trajectory.units, {})
    length, energy = labels.get("length"), labels.get("energy")
    top.set_ylabel(f"pressure [{energy}/{length}^{n}]" if length and energy else "pressure")
    top.legend(loc="best")
    bottom.plot(t, obs["volume"], color="C2")
    bottom.set_ylabel(f"volume [{length}^{n}]" if length else "volume")
    bottom.set_xlabel(f"time{_unit(trajectory, 'time')}")
    top.set_title("pressure tensor and volume of the box")
    fig.tight_layout()
    return _save(fig, Path(path))


def plot_temperature(trajectory: Trajectory, path: str | Path) -> Path:
    """Translational and internal temperatures 2 T_tr/(N n) and 2 T_int/(N d) versus time
    (with the thermostat's kT when the config has one)."""
    t = trajectory.time
    obs = trajectory.observables
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(t, obs["translational_temperature"], label="translational 2 T_tr / (N n)", lw=1)
    ax.plot(t, obs["internal_temperature"], label="internal 2 T_int / (N d)", lw=1)
    ax.set_xlabel(f"time{_unit(trajectory, 'time')}")
    ax.set_ylabel(f"kT{_unit(trajectory, 'energy')}")
    ax.set_title("temperatures")
    ax.legend(loc="best")
    fig.tight_layout()
    return _save(fig, Path(path))


def _components(values: np.ndarray, symbol: str, skew: bool = False):
    """(label, series) of the entries of [T, n] or [T, n, n] arrays (upper triangle if skew),
    labelled by the symbol and axis names, e.g. P_x, J_xy."""
    n = values.shape[-1]
    if values.ndim == 2:
        return [(f"${symbol}_{{{_axis(n, a)}}}$", values[:, a]) for a in range(n)]
    return [(f"${symbol}_{{{_axis(n, a)}{_axis(n, b)}}}$", values[:, a, b])
            for a in range(n) for b in range(n) if not skew or a < b]


def plot_momenta(trajectory: Trajectory, path: str | Path) -> Path:
    """Changes of the momentum maps since t = 0 (conserved when V has the symmetry)."""
    t = trajectory.time
    obs = trajectory.observables
    periodic = trajectory.box is not None
    panels = [
        ("total linear momentum P = Σ p_K", "P", "ΔP", obs["linear_momentum"], False,
         "momentum"),
        ("affine momentum J = Σ (x_K p_Kᵀ + φ_K π_K)", "J", "ΔJ", obs["affine_momentum"], False,
         "action"),
        ("angular momentum L = J − Jᵀ", "L", "ΔL", obs["angular_momentum"], True, "action"),
    ]
    if trajectory.n == 1:  # J - J^T of a 1 x 1 J has no components: nothing to draw
        panels = panels[:2]
    fig, axes = plt.subplots(len(panels), 1, figsize=(7.5, 8.5 * len(panels) / 3), sharex=True)
    for ax, (title, symbol, ylabel, values, skew, kind) in zip(axes, panels, strict=True):
        values = np.asarray(values)
        change = values - values[:1]
        for label, series in _components(change, symbol, skew):
            ax.plot(t, series, label=label, lw=1)
        worst = float(np.max(np.abs(change))) if change.size else 0.0
        title = f"{title}: change since t = 0 (max {worst:.2e})"
        if skew and periodic:
            title += ("\nnot conserved in a periodic box, which breaks the rotation symmetry: "
                      "this change is physical, not an error")
        ax.set_title(title, fontsize=8.5)
        ax.set_ylabel(f"{ylabel}{_unit(trajectory, kind)}", fontsize=9)
        if values.shape[-1] <= 3:
            ax.legend(fontsize=7, ncol=3, loc="best")
    axes[-1].set_xlabel(f"time{_unit(trajectory, 'time')}")
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
        _, phi = trajectory.configuration(k)
        invariants = np.asarray(trace_invariants(phi))  # [N, n]
        volumes = np.linalg.det(phi)
        columns = [invariants[:, a] for a in range(n)] + [volumes, volumes / volumes[0]]
        series.append((np.stack([c[traced] for c in columns]),
                       np.stack([(np.min(c), np.max(c)) for c in columns])))
    lines = np.stack([s[0] for s in series])  # [T, n + 2, traced]
    bands = np.stack([s[1] for s in series])  # [T, n + 2, 2]
    labels = ([f"$K_{a + 1} = \\mathrm{{Tr}}\\,G^{{{a + 1}}}$" for a in range(n)]
              + [r"$\det\varphi_K$", r"$\det\varphi_K / \det\varphi_1$"])
    fig, axes = plt.subplots(n + 2, 1, figsize=(7.5, 2.1 * (n + 2) + 0.6), sharex=True)
    colors = [f"C{i % 10}" for i in range(len(traced))]
    for row, ax in enumerate(axes):
        if bodies > len(traced):
            ax.fill_between(t, bands[:, row, 0], bands[:, row, 1], color="0.85",
                            label=f"range over all {bodies} bodies")
        for i, body in enumerate(traced):
            ax.plot(t, lines[:, row, i], lw=0.9, color=colors[i], label=f"body {body + 1}")
        ax.set_ylabel(labels[row])
    axes[-1].set_xlabel(f"time{_unit(trajectory, 'time')}")
    shown = f"{len(traced)} of {bodies} bodies" if bodies > len(traced) else f"{bodies} bodies"
    axes[0].set_title(f"deformation of each body ({shown}): invariants of the Green tensor "
                      f"G = φᵀφ, volumes", fontsize=9)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=min(len(names), 6), fontsize=7,
               frameon=False)
    fig.tight_layout(rect=(0, 0.035 * (1 + (len(names) - 1) // 6), 1, 1))
    return _save(fig, Path(path))


def body_outlines(x: np.ndarray, phi: np.ndarray, radius: np.ndarray, points: int = 64):
    """Ellipses x_K + phi_K (r_K u), |u| = 1, as polygons [N, points, 2] (n = 2)."""
    angle = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1)  # [P, 2]
    return x[:, None, :] + np.einsum("kia,pa->kpi", phi, circle) * radius[:, None, None]


def _axis_segments(x, phi, radius):
    tip = x + phi[:, :, 0] * radius[:, None]
    return np.stack([x, tip], axis=1)


def _limits(trajectory: Trajectory, frames, drawn, cube: bool = False):
    """Axis limits (low, high) [n] around the drawn bodies of ``frames``, padded by 5%; with
    ``cube`` the same span on every axis (3D axes have no equal aspect of their own)."""
    low = np.full(trajectory.n, np.inf)
    high = np.full(trajectory.n, -np.inf)
    for k in frames:
        x, phi = (a[drawn] for a in trajectory.configuration(k))
        reach = np.linalg.norm(phi, ord=2, axis=(-2, -1)) * trajectory.radius[drawn]
        low = np.minimum(low, np.min(x - reach[:, None], axis=0))
        high = np.maximum(high, np.max(x + reach[:, None], axis=0))
    span = max(float(np.max(high - low)), 1e-9)
    if cube:
        centre = (low + high) / 2
        return centre - 0.525 * span, centre + 0.525 * span
    return low - 0.05 * span, high + 0.05 * span


def _draw(ax, trajectory: Trajectory, frame: int, low, high, drawn):
    x, phi = (a[drawn] for a in trajectory.configuration(frame))
    radius = trajectory.radius[drawn]
    shapes = PolyCollection(body_outlines(x, phi, radius), facecolors="C0",
                            edgecolors="k", alpha=0.55, linewidths=0.8)
    axes = LineCollection(_axis_segments(x, phi, radius), colors="C3", linewidths=1.2)
    ax.add_collection(shapes)
    ax.add_collection(axes)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")
    length = _unit(trajectory, "length")
    ax.set_xlabel(f"x{length}")
    ax.set_ylabel(f"y{length}")
    ax.set_title(_time(trajectory, frame), fontsize=9)
    return shapes, axes


def _draw_rods(ax, trajectory: Trajectory, frame: int, low, high, drawn):
    """n = 1: body K the rod x_K + phi_K a, |a| <= r_K, on the row K + 1, its material axis's
    image phi_K r_K e_1 from the centre in red (to the left where phi_K < 0)."""
    x, phi = (a[drawn] for a in trajectory.configuration(frame))
    radius = trajectory.radius[drawn]
    rows = (np.asarray(drawn) + 1.0)[:, None]
    half = np.abs(phi[:, :, 0]) * radius[:, None]
    ax.add_collection(LineCollection(
        np.stack([np.hstack([x - half, rows]), np.hstack([x + half, rows])], axis=1),
        colors="C0", linewidths=5, alpha=0.7))
    ax.add_collection(LineCollection(
        np.stack([np.hstack([x, rows]), np.hstack([x + phi[:, :, 0] * radius[:, None], rows])],
                 axis=1), colors="C3", linewidths=1.5))
    ax.plot(x[:, 0], rows[:, 0], "k|", markersize=9)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(0.3, trajectory.bodies + 0.7)
    ax.set_xlabel(f"x{_unit(trajectory, 'length')}")
    ax.set_ylabel("body")
    ax.set_title(_time(trajectory, frame), fontsize=9)


def plot_bodies(trajectory: Trajectory, path: str | Path) -> Path:
    """First and last frame of a 1D or 2D trajectory: bodies as ellipses phi(disc) (n = 2) or
    as rods phi([-r, r]) on the line, one row per body (n = 1)."""
    if trajectory.n not in (1, 2):
        raise ValueError(f"bodies are drawn by plot_bodies for n = 1 and 2 only (got "
                         f"n = {trajectory.n}; n = 3: plot_ellipsoids)")
    drawn = _sample(trajectory.bodies, DRAWN_BODIES)
    frames = (0, trajectory.frames - 1)
    low, high = _limits(trajectory, frames, drawn)
    if trajectory.n == 1:
        draw, shapes = _draw_rods, "bodies (n = 1): the rods x + φa, |a| ≤ r, one row per body"
        fig, axes = plt.subplots(1, 2, figsize=(10, 1.6 + 0.25 * min(len(drawn), 24)),
                                 sharey=True)
    else:
        draw, shapes = _draw, "bodies: the ellipses x + φa, |a| ≤ r"
        fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    for ax, frame in zip(axes, frames, strict=True):
        draw(ax, trajectory, frame, low, high, drawn)
    sample = (f" ({len(drawn)} of {trajectory.bodies} bodies)"
              if len(drawn) < trajectory.bodies else "")
    fig.suptitle(f"{shapes}; red: the image φe₁ of the material axis e₁{sample}", fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(path))


def ellipsoid_surface(x: np.ndarray, phi: np.ndarray, radius: np.ndarray, points: int = 16):
    """Surfaces x_K + phi_K (r_K u), |u| = 1, as grids [N, 3, points, 2 * points] (n = 3): the
    boundary of the ellipsoid {x + phi a : |a| <= r} that each body occupies."""
    polar = np.linspace(0.0, np.pi, points)
    azimuth = np.linspace(0.0, 2 * np.pi, 2 * points)
    sphere = np.stack([np.outer(np.sin(polar), np.cos(azimuth)),
                       np.outer(np.sin(polar), np.sin(azimuth)),
                       np.outer(np.cos(polar), np.ones_like(azimuth))])  # [3, P, 2P]
    return (x[:, :, None, None] + np.einsum("kia,apq->kipq", phi, sphere)
            * radius[:, None, None, None])


def plot_ellipsoids(trajectory: Trajectory, path: str | Path) -> Path:
    """First and last frame of a 3D trajectory, each body the shaded ellipsoid
    {x + phi a : |a| <= r} (matplotlib's 3D axes; n = 3 only)."""
    if trajectory.n != 3:
        raise ValueError(f"ellipsoids are drawn for n = 3 only (got n = {trajectory.n})")
    from matplotlib.colors import LightSource

    drawn = _sample(trajectory.bodies, DRAWN_ELLIPSOIDS)
    frames = (0, trajectory.frames - 1)
    low, high = _limits(trajectory, frames, drawn, cube=True)
    light = LightSource(azdeg=315, altdeg=45)
    length = _unit(trajectory, "length")
    fig = plt.figure(figsize=(11, 5.4))
    for column, frame in enumerate(frames):
        ax = fig.add_subplot(1, 2, column + 1, projection="3d")
        x, phi = (a[drawn] for a in trajectory.configuration(frame))
        surfaces = ellipsoid_surface(x, phi, trajectory.radius[drawn])
        for i, surface in enumerate(surfaces):
            ax.plot_surface(*surface, color=f"C{i % 10}", lightsource=light, shade=True,
                            linewidth=0, antialiased=False, rstride=1, cstride=1)
        ax.set(xlim=(low[0], high[0]), ylim=(low[1], high[1]), zlim=(low[2], high[2]))
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel(f"x{length}")
        ax.set_ylabel(f"y{length}")
        ax.set_zlabel(f"z{length}")
        ax.set_title(_time(trajectory, frame), fontsize=9)
    sample = (f" ({len(drawn)} of {trajectory.bodies} bodies)"
              if len(drawn) < trajectory.bodies else "")
    fig.suptitle(f"bodies: each the ellipsoid {{x + φa : |a| ≤ r}}{sample}")
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
        x, phi = (a[drawn] for a in trajectory.configuration(frame))
        shapes.set_verts(body_outlines(x, phi, radius))
        axes.set_segments(_axis_segments(x, phi, radius))
        ax.set_title(f"t = {trajectory.time[frame]:.4g}", fontsize=9)
        return shapes, axes

    movie = animation.FuncAnimation(fig, update, frames=trajectory.frames, blit=False)
    movie.save(path, writer=writer, dpi=80)
    plt.close(fig)
    return path


#: the observables :func:`plot_all` draws in every case (pressure, volume and the
#: temperatures only where the file has them)
PLOTTED_OBSERVABLES = ("total_energy", "kinetic_energy", "potential_energy", "linear_momentum",
                       "affine_momentum", "angular_momentum")


def plot_all(trajectory: Trajectory, folder: str | Path, *, animate: str | None = None,
             fps: int = 20) -> list[Path]:
    """Write every plot into ``folder``; returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if trajectory.frames == 0:
        raise ValueError("the trajectory has no frames to plot")
    missing = [name for name in PLOTTED_OBSERVABLES if name not in trajectory.observables]
    if missing:  # every affinebody run writes them: an edited or foreign file
        raise ValueError(f"the trajectory lacks the observables {', '.join(missing)} (every "
                         f"affinebody run writes them: plot a file affinebody run wrote)")
    if animate and trajectory.n != 2:
        raise ValueError(f"--animate needs n = 2 (got n = {trajectory.n})")
    if animate and not 1 <= fps <= 1000:
        raise ValueError(f"--fps must be a whole number of frames per second from 1 to 1000 "
                         f"(got {fps})")
    paths = [
        plot_energy(trajectory, folder / "energy.png"),
        plot_momenta(trajectory, folder / "momenta.png"),
        plot_deformation(trajectory, folder / "deformation.png"),
    ]
    if "pressure" in trajectory.observables and "volume" in trajectory.observables:
        paths.append(plot_pressure(trajectory, folder / "pressure.png"))
    if "internal_temperature" in trajectory.observables:  # files of earlier versions: none
        paths.append(plot_temperature(trajectory, folder / "temperature.png"))
    if trajectory.n in (1, 2):
        paths.append(plot_bodies(trajectory, folder / "bodies.png"))
        if animate:
            paths.append(animate_bodies(trajectory, folder / f"bodies.{animate}", fps=fps))
    elif trajectory.n == 3:
        paths.append(plot_ellipsoids(trajectory, folder / "bodies.png"))
    return paths


__all__ = [
    "DPI", "TRACED_BODIES", "DRAWN_BODIES", "DRAWN_ELLIPSOIDS", "AXES", "plot_energy",
    "plot_pressure", "plot_temperature", "plot_momenta", "plot_deformation", "body_outlines",
    "plot_bodies", "ellipsoid_surface", "plot_ellipsoids", "animate_bodies", "plot_all",
    "PLOTTED_OBSERVABLES"
]
