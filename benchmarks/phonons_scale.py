"""Benchmark (issue 17): phonons of a 3D crystal with 8 bodies per primitive cell, on one core.

The crystal: a 4 x 4 x 4 simple cubic lattice of af-is bodies in a periodic box of edge 4, with
``phonons.cells = [2, 2, 2]``, so the primitive cell holds 8 bodies (96 branches: 8 x (3 + 9)
degrees of freedom); Morse in r (r_cut 1.5, i.e. first and second neighbours), the affine pair
term exp(-D^2/4) (M1 - 3)^2, a dilatation and a St Venant-Kirchhoff shape potential. Work:
force constants, 2500 path points (G-X-M-G-R-X, 500 per segment) with eigenvectors and
characters, a 20^3 mesh (8000 k, eigenvalues only) and its DOS, sound speeds and elastic
constants. Target: under 30 s in total (compilation included).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/phonons_scale.py (first the whole
``affinebody phonons`` command on one core, then the split of its work by phase)

``--box-sides 8 16 22 46`` instead times the whole command on boxes of side^3 bodies of one
crystal (the simple cubic lattice of ``run_scale.py``'s config, no jitter: one body per
primitive cell), with its peak memory: the work on the box (finding the primitive cell, the
sublattices, the equilibrium check) must grow like N, the phonon work not at all.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

CONFIG = """
[system]
n = 3
bodies = 64
box = [4.0, 4.0, 4.0]

[kinetic]
internal = "af-is"
I = 0.5
A = 0.1
B = 0.05

[[potential]]
kind = "morse"
depth = 1.0
alpha = 3.0
r0 = 1.0
r_cut = 1.5

[[potential]]
kind = "pair"
expr = "0.5 * exp(-D**2 / 4) * (M1 - 3)**2"
r_cut = 1.5

[[potential]]
kind = "dilatation"
stiffness = 5.0

[[potential]]
kind = "elastic"
lam = 0.5
mu = 1.0

[initial]
generator = "lattice"
spacing = 1.0

[run]
dt = 0.005
steps = 1

[phonons]
cells = [2, 2, 2]
path = ["G", "X", "M", "G", "R", "X"]
points = 500
mesh = [20, 20, 20]
"""


def command() -> None:
    """The whole ``affinebody phonons`` command on one core: what users run (start-up, build,
    compilation, the path and mesh, JSON and the figure)."""
    import resource
    import shutil
    import subprocess
    import sys

    exe = shutil.which("affinebody") or str(Path(sys.executable).parent / "affinebody")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.toml"
        path.write_text(CONFIG, encoding="utf-8")
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        clock = time.perf_counter()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run(["taskset", "-c", "0", exe, "phonons", str(path), "-o", tmp],
                       check=True, capture_output=True, env=env)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        print(f"affinebody phonons, whole command on one core: "
              f"{time.perf_counter() - clock:.1f} s wall, {cpu:.1f} s CPU (the wall time on a "
              f"free core: the command is pinned to one)  [target < 30 s]; load average "
              f"{os.getloadavg()[0]:.1f}")


def box_sizes(sides: list[int]) -> None:
    """The whole ``affinebody phonons`` command on growing boxes of one crystal (one core)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run_scale import AFFINEBODY, pinned, timed, write_config

    print("| bodies in the box | whole command (s) | peak RSS (GiB) |")
    print("|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for side in sides:
            path = write_config(Path(tmp), side, steps=10, every=10)
            text = path.read_text().replace("jitter = 0.03", "jitter = 0.0")
            path.write_text(text.replace("phi_noise = 0.05", "phi_noise = 0.0"))
            wall, out, peak, _ = timed(pinned("0", [*AFFINEBODY, "phonons", str(path), "-o", tmp,
                                                 "--mesh", "4", "--points", "10"]))
            if "wrote" not in out:
                raise SystemExit(f"affinebody phonons failed at side {side}: {out[-400:]}")
            print(f"| {side**3} | {wall:.1f} | {peak / 2**20:.2f} |", flush=True)


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--box-sides", type=int, nargs="*", default=None,
                        help="time the whole command on boxes of side^3 bodies instead")
    args = parser.parse_args()
    if args.box_sides:
        box_sizes(args.box_sides)
        return
    command()
    print("where the time goes (the same work through the library calls of the command):")
    from affinebody._xla import pin_to_one_cpu

    pin_to_one_cpu()
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    from affinebody._checks import enable_x64

    enable_x64()
    import numpy as np

    from affinebody import phonons
    from affinebody.config import build, check_config, parse_config

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.toml"
        path.write_text(CONFIG, encoding="utf-8")
        config = check_config(parse_config(CONFIG, str(path)))
    clock = time.perf_counter()
    built = build(config)
    print(f"  build (config, initial energy)                {time.perf_counter() - clock:7.2f} s")
    laps = {}
    clock = time.perf_counter()
    start, cpu = clock, time.process_time()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        laps[name] = now - clock
        print(f"  {name:45s} {now - clock:7.2f} s", flush=True)
        clock = now

    crystal = phonons.make_crystal(built.system, np.asarray(built.state.x),
                                   np.asarray(built.state.phi), config.system.box,
                                   config.phonons.cells)
    residual = float(np.abs(phonons.residual_forces(crystal)).max())
    lap("crystal, residual")
    fc = phonons.force_constants(crystal)
    lap("force constants")
    k, _, _ = phonons.path(crystal, ["G", "X", "M", "G", "R", "X"], config.phonons.points)
    spectrum = phonons.solve(fc, k)
    lap(f"path ({len(k)} k, vectors + characters)")
    km, weights = phonons.mesh(crystal, config.phonons.mesh)
    mesh = phonons.solve(fc, km, vectors=False)
    phonons.density_of_states(mesh.omega, weights)
    lap(f"mesh ({int(weights.sum())} k, {len(km)} by time reversal) + DOS")
    speeds = phonons.sound_speeds(fc, [1.0, 0.0, 0.0])
    voigt, fit = phonons.elastic_constants(fc)
    lap("sound speeds, elastic constants")
    total = time.perf_counter() - start
    cpu = time.process_time() - cpu
    print(f"bodies per cell {len(crystal.basis)}, branches {spectrum.omega2.shape[1]}, "
          f"bonds {len(phonons.bonds(crystal)[0])}, residual force {residual:.2g}")
    print(f"total (after build) {total:.2f} s wall, {cpu:.2f} s CPU  [target < 30 s]")
    d0 = fc.dynamical_matrix(np.zeros(3))
    uniform = np.zeros((d0.shape[0], 3))
    for a in range(len(crystal.basis)):
        uniform[a * crystal.dof:a * crystal.dof + 3] = np.eye(3)
    print(f"acoustic sum rule: |D(0) T| / |D(0)| = "
          f"{np.abs(d0 @ uniform).max() / np.abs(d0).max():.1e} (T: the uniform translations)")
    print(f"imaginary modes on the path: {int(np.sum(spectrum.imaginary))}, on the mesh: "
          f"{int(np.sum(mesh.imaginary))}; sound speeds along x: {np.round(speeds, 5)}; "
          f"C11, C12, C44 = {voigt[0, 0]:.5g}, {voigt[0, 1]:.5g}, {voigt[3, 3]:.5g} "
          f"(fit residual {fit:.1e})")


if __name__ == "__main__":
    main()
