"""``affinebody phonons CONFIG.toml``: dispersion relations, density of states, sound speeds and
elastic constants of the crystal in the config's periodic box (:mod:`affinebody.phonons` does
the mechanics; this module reads ``[phonons]`` and the flags, writes the JSON document and the
plots, docs/phonons.md)."""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from affinebody._json import json_text
from affinebody.cli.common import enable_x64, not_finite_as, one_line_errors


def _error(message: str):
    from affinebody.config import ConfigError

    return ConfigError(message)


def check_phonons(config) -> None:
    """Refuse, before building anything, a config whose crystal has no harmonic spectrum."""
    if config.system.box is None:
        raise _error("phonons need a periodic box: set system.box (the crystal is the box "
                     "repeated)")
    if config.constraints.rotationless is not None:
        raise _error("phonons: constraints.rotationless is non-holonomic; the harmonic "
                     "analysis needs holonomic coordinates (remove [constraints])")
    if config.kinetic.internal == "af-af" and config.n >= 2:
        raise _error("kinetic.internal = 'af-af' (72) has an indefinite kinetic metric for "
                     "n >= 2 (A Tr(Omega^2) takes both signs), so D(k) u = omega^2 M u has no "
                     "frequencies: choose af-is, is-af or another positive-definite model")
    section = config.phonons
    for name in ("cells", "mesh"):
        value = None if section is None else getattr(section, name)
        if value is not None and (len(value) != config.n or min(value) < 1):
            raise _error(f"phonons.{name} must be {config.n} positive integers (got {value})")


def crystal_of(config, built, relax: bool | None = None):
    """The :class:`affinebody.phonons.Crystal` of a built config at its equilibrium: relaxed
    when ``phonons.relax`` (or ``relax``) is true; ConfigError with the residual force otherwise
    when the given state is not an equilibrium (``phonons.tolerance``)."""
    from affinebody import phonons

    section = config.phonons
    tolerance = 1e-6 if section is None else section.tolerance
    relax = (section is not None and section.relax) if relax is None else relax
    check_phonons(config)
    cells = None if section is None else section.cells
    try:
        crystal = phonons.make_crystal(built.system, np.asarray(built.state.x),
                                       np.asarray(built.state.phi), config.system.box, cells)
        phonons.bonds(crystal)  # refuses terms that a crystal cannot have
        if relax and section is not None and section.relax_cell:
            crystal = phonons.relax_cell(crystal, tolerance=min(tolerance, 1e-9))
        elif relax:
            crystal = phonons.relax(crystal, tolerance=min(tolerance, 1e-9))
        residual = phonons.residual_forces(crystal)
    except np.linalg.LinAlgError:
        raise  # (a ValueError too) not finite: said by compute, not_finite_as
    except ValueError as err:
        raise _error(str(err)) from None
    worst = float(np.abs(residual).max()) if residual.size else 0.0
    if worst > tolerance:
        body, dof = np.unravel_index(int(np.abs(residual).argmax()), residual.shape)
        what = "x" if dof < config.n else "phi"
        raise _error(f"initial: the crystal is not an equilibrium (largest residual force "
                     f"{worst:.3g} > phonons.tolerance = {tolerance:g}, body "
                     f"{int(crystal.basis[body])}, {what}): set phonons.relax = true or start "
                     f"at an equilibrium")
    return crystal, worst


def k_points_bytes(crystal, path_points: int, mesh_sizes) -> tuple[float, float]:
    """Bytes the k points of a document take, estimated before any is computed: (the path's:
    each point's eigenvectors, one complex matrix of the cell's degrees of freedom, and its
    frequencies as NumPy and as JSON numbers; the DOS mesh's: its index arrays and the
    frequencies, ``phonons.mesh``, ``phonons.solve``)."""
    size = len(crystal.basis) * crystal.dof
    return (path_points * (16.0 * size * size + 80 * size),
            float(np.prod(np.asarray(mesh_sizes, dtype=float))) * (40 * crystal.n + 8 * size))


def _check_k_points(crystal, labels, points: int, sizes, dos: bool) -> None:
    """Refuse, before computing, a path or mesh that cannot fit in memory (both figures)."""
    from affinebody import phonons
    from affinebody.config import refuse_beyond_memory

    corners = len(phonons.path_labels(crystal.n, labels))
    path_bytes, mesh_bytes = k_points_bytes(crystal, max(corners - 1, 1) * points, sizes)
    mesh_bytes = mesh_bytes if dos else 0.0
    if mesh_bytes > path_bytes:
        what, fix = f"phonons.mesh = {list(sizes)} (or --mesh)", "use a coarser mesh"
    else:
        what, fix = f"phonons.points = {points} (or --points)", "use fewer points"
    refuse_beyond_memory(path_bytes + mesh_bytes, what, fix)


def compute(config, built, path=None, mesh=None, points=None, relax=None, dos=True) -> dict:
    """The phonon document of a config (what ``--json`` writes, module docstring)."""
    with not_finite_as("the crystal's force constants or kinetic metric could not be "
                       "diagonalised", "they are not finite in float64 when a potential or "
                       "kinetic parameter is too large; use moderate numbers (units in which "
                       "they are near 1)"):
        return _compute(config, built, path, mesh, points, relax, dos)


def _compute(config, built, path, mesh, points, relax, dos) -> dict:
    from affinebody import phonons

    clock = time.perf_counter()
    crystal, residual = crystal_of(config, built, relax)
    section = config.phonons
    labels = path or (None if section is None else section.path)
    points = points or (50 if section is None else section.points)
    default = {1: 40, 2: 20}.get(config.n, 12)
    sizes = mesh or (None if section is None else section.mesh) or [default] * config.n
    if len(sizes) != config.n or min(sizes) < 1:
        raise _error(f"phonons.mesh must be {config.n} positive integers (got {list(sizes)})")
    _check_k_points(crystal, labels, points, sizes, dos)
    try:
        fc = phonons.force_constants(crystal)
        k, distance, ticks = phonons.path(crystal, labels, points)
    except np.linalg.LinAlgError:
        raise
    except ValueError as err:
        raise _error(str(err)) from None
    spectrum = phonons.solve(fc, k)
    doc = {
        "k": k.tolist(),
        "distance": distance.tolist(),
        "ticks": [[label, d] for label, d in ticks],
        "omega": spectrum.omega.tolist(),
        "omega_squared": spectrum.omega2.tolist(),
        "imaginary": int(np.sum(spectrum.imaginary)),
        # long-wave figures (sound speeds, elastic constants) describe a stable crystal only
        "stable": not bool(np.any(spectrum.imaginary)),
        "character": {"names": list(phonons.CHARACTERS), "shares": spectrum.character.tolist()},
        "units": {"k": "1/length (Cartesian)", "omega": "angular frequency; imaginary "
                  "frequencies (omega^2 < 0) as -sqrt(-omega^2)"},
        "crystal": {"n": crystal.n, "cells": list(crystal.cells),
                    "lattice": crystal.lattice.tolist(),
                    "lattice_vectors": crystal.vectors.T.tolist(),  # rows: a_j (Cartesian)
                    "bodies_per_cell": len(crystal.basis),
                    "dof_per_body": crystal.dof, "group": built.system.group,
                    "residual_force": residual,
                    "relaxed": bool(relax if relax is not None else
                                    (section is not None and section.relax))},
    }
    if dos:
        km, weights = phonons.mesh(crystal, sizes)
        omega_mesh = phonons.solve(fc, km, vectors=False).omega
        grid, density = phonons.density_of_states(omega_mesh, weights)
        doc["dos"] = {"mesh": list(sizes), "omega": grid.tolist(), "density": density.tolist(),
                      "imaginary_fraction": float(np.sum(weights[:, None] * (omega_mesh < 0))
                                                  / (np.sum(weights) * omega_mesh.shape[1]))}
    eye = np.eye(crystal.n)
    directions = [eye[j] for j in range(crystal.n)]
    if crystal.n > 1:
        directions.append(np.ones(crystal.n) / np.sqrt(crystal.n))
    doc["sound_speeds"] = [{"direction": d.tolist(),
                            "speeds": phonons.sound_speeds(fc, d).tolist()} for d in directions]
    constants, residual_fit = phonons.elastic_constants(fc)
    doc["elastic_constants"] = {"voigt": constants.tolist(),
                                "order": [list(p) for p in phonons.voigt_pairs(crystal.n)],
                                "fit_residual": residual_fit}
    doc["seconds"] = time.perf_counter() - clock
    return doc


def plot(doc: dict, path: Path) -> None:
    """Dispersion along the path (colour: internal share) beside the density of states."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_dos = "dos" in doc
    fig, axes = plt.subplots(1, 2 if has_dos else 1, figsize=(9 if has_dos else 6, 4.5),
                             sharey=True, squeeze=False,
                             gridspec_kw={"width_ratios": [3, 1] if has_dos else [1]})
    ax = axes[0, 0]
    distance = np.asarray(doc["distance"])
    omega = np.asarray(doc["omega"])
    shares = np.asarray(doc["character"]["shares"])
    internal = 1.0 - shares[..., 0]
    for branch in range(omega.shape[1]):
        ax.scatter(distance, omega[:, branch], c=internal[:, branch], s=2, cmap="coolwarm",
                   vmin=0, vmax=1)
    for _, d in doc["ticks"]:
        ax.axvline(d, color="0.8", lw=0.5)
    ax.set_xticks([d for _, d in doc["ticks"]])
    ax.set_xticklabels(["Γ" if label == "G" else label for label, _ in doc["ticks"]])
    ax.set_xlim(distance[0], distance[-1])
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_ylabel("ω (imaginary < 0)")
    ax.set_title("dispersion (red: internal, blue: translational)")
    if has_dos:
        axd = axes[0, 1]
        axd.plot(doc["dos"]["density"], doc["dos"]["omega"], color="k", lw=1)
        axd.set_xlabel("DOS")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


@click.command("phonons")
@click.argument("config_path", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="directory for phonons.json and dispersion.png (default: next to the config)")
@click.option("--path", "path_", default=None,
              help="high-symmetry path, e.g. G-X-M-G (overrides phonons.path)")
@click.option("--mesh", default=None, help="DOS mesh, e.g. 20 or 20,20,20 (overrides phonons.mesh)")
@click.option("--points", type=int, default=None, help="k points per path segment")
@click.option("--relax/--no-relax", default=None, help="relax positions and shapes first")
@click.option("--json", "as_json", is_flag=True, help="print the JSON document on stdout")
@click.option("--no-plot", is_flag=True, help="skip the figure")
@one_line_errors
def phonons_command(config_path, output, path_, mesh, points, relax, as_json, no_plot):
    """Dispersion relations of the crystal of CONFIG_PATH's periodic box: the n acoustic and
    the internal (affine) branches, DOS, sound speeds and elastic constants."""
    enable_x64()
    from affinebody.config import MOST_PATH_POINTS, build, load_config

    config = load_config(config_path)
    labels = None if path_ is None else [p for p in path_.replace(",", "-").split("-") if p]
    sizes = None
    if mesh is not None:
        try:
            sizes = [int(v) for v in mesh.split(",")]
        except ValueError:
            raise _error(f"--mesh must be integers like 20 or 20,20,20 (got {mesh!r})") from None
        if len(sizes) == 1:
            sizes = sizes * config.n
    if points is not None and not 2 <= points <= MOST_PATH_POINTS:
        raise _error(f"--points must be between 2 and {MOST_PATH_POINTS} (got {points})")
    check_phonons(config)
    built = build(config)
    doc = compute(config, built, labels, sizes, points, relax)
    out = output or config_path.parent
    out.mkdir(parents=True, exist_ok=True)
    (out / "phonons.json").write_text(json_text(doc), encoding="utf-8")
    if not no_plot:
        plot(doc, out / "dispersion.png")
    if as_json:
        click.echo(json_text(doc))
        return
    crystal = doc["crystal"]
    click.echo(f"crystal: n = {crystal['n']}, {crystal['bodies_per_cell']} bodies per cell, "
               f"{crystal['dof_per_body']} dof per body, cells {crystal['cells']}, residual "
               f"force {crystal['residual_force']:.2g}")
    omega = np.asarray(doc["omega"])
    click.echo(f"{omega.shape[1]} branches on {omega.shape[0]} path points; omega in "
               f"[{omega.min():.6g}, {omega.max():.6g}]; imaginary modes: {doc['imaginary']}"
               + ("" if doc["stable"] else " (UNSTABLE: the long-wave figures below describe "
                                           "no stable crystal)"))
    for item in doc["sound_speeds"]:
        click.echo(f"sound speeds along {np.round(item['direction'], 4).tolist()}: "
                   f"{', '.join(f'{v:.6g}' for v in item['speeds'])}")
    c = np.asarray(doc["elastic_constants"]["voigt"])
    click.echo(f"elastic constants (Voigt): {np.array2string(c, precision=5)}")
    click.echo(f"wrote {out / 'phonons.json'}" + ("" if no_plot else
                                                  f" and {out / 'dispersion.png'}"))


__all__ = ["check_phonons", "compute", "crystal_of", "k_points_bytes", "phonons_command", "plot"]
