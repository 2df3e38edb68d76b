"""Benchmark: n = 3 quantum spectra over every SO(3) x SO(3) sector (j, j').

1. The R^9 oscillator (d'Alembert, J = Id, V = Tr G / 2, hbar = 1): the lowest 220 states
   (N = 0..3: 1 + 9 + 45 + 165) through `spectra.solve` with sectors = "all": time, peak
   memory, the largest |E - (N + 9/2)| and whether every multiplicity is C(N + 8, 8).
2. An anharmonic rotation-invariant body, V = r^2/2 + 0.8 exp(-r^2/2) with r = |phi|: the
   lowest 30 states against an independent R^9 radial solver (sinc DVR of the radial equation
   for hyperspherical harmonics of degree l, degeneracy C(l+8, 8) - C(l+6, 8)), for growing
   basis degree: time, peak memory, max error.

3. The 60 lowest states through the command users run, ``affinebody spectrum CONFIG --levels 60
   --json`` (a subprocess on one core, OPENBLAS_NUM_THREADS=1), in the hyperspherical-harmonic x
   Laguerre basis (``quantum.radial_size``, n3.harmonic_block): V = r^2/2 + 0.8 exp(-r^2/2)
   against the independent R^9 radial solver (tests/oracles.py), and V + 0.5 det(phi)^2
   exp(-r^2/2), which depends on the Q_a separately, against the same method at a much larger
   basis (harmonic degree 18, 22 radial functions: a resolution reference, not an independent
   solver). Reported: whole command (start-up included), the start-up alone (a process
   importing what the command imports, :func:`startup`), the worst error, whether the list
   is certified complete.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/quantum_n3.py [--all]
(without --all only part 3; --all adds parts 1 and 2, the Gaussian x polynomial basis)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from math import comb
from pathlib import Path

import numpy as np
from quantum_spectra import measure  # time and tracemalloc peak, as for n = 2

from affinebody._checks import enable_x64
from affinebody.quantum import spectra as sp
from affinebody.quantum.config import compile_potential

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from oracles import r9_radial_states  # noqa: E402  (the test oracle, not library code)

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
BUMP = "0.5*trG + 0.8*exp(-trG/2)"
NON_RADIAL = "0.5*trG + 0.8*exp(-trG/2) + 0.5*det**2*exp(-trG/2)"
CONFIG = """[system]
n = 3
[quantum]
kinetic = "dalembert"
inertia = 1.0
potential = "{potential}"
basis_size = {degree}
radial_size = {radial}
tolerance = 1e-9
"""


def bump_radial(r):
    return 0.5 * r**2 + 0.8 * np.exp(-(r**2) / 2)


def command(args: list[str]) -> tuple[str, float]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    out = subprocess.run([AFFINEBODY, *args], capture_output=True, text=True, env=env, check=True)
    return out.stdout, time.perf_counter() - t0


def startup() -> float:
    """Wall time of a process that imports what `affinebody spectrum` imports and turns on JAX's
    float64 mode (``spectrum --help`` imports none of it)."""
    code = ("import affinebody.cli, affinebody.quantum.cli as cli, affinebody.quantum.config, "
            "affinebody.quantum.spectra; cli.enable_x64()")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    return time.perf_counter() - t0


def sixty_levels() -> None:
    K = 60
    started = startup()
    print(f"60 lowest states by `affinebody spectrum CONFIG --levels {K} --json` (one core); "
          f"start-up alone {started:.2f} s")
    print("potential                          degree x radial   command[s]   max error   "
          "reference            certified")
    enable_x64()
    cases = [(BUMP, 6, 18, "R^9 radial solver",
              lambda: r9_radial_states(bump_radial, K, h=0.02, max_degree=6, per_degree=4)),
             (NON_RADIAL, 14, 16, "degree 18 x 22", lambda: np.array(sp.solve(
                 "dalembert", 3, compile_potential(NON_RADIAL, 3), 1.0, inertia=1.0, levels=K,
                 settings=sp.Settings(basis_size=18, radial_size=22, check_shrink=2,
                                      tolerance=1e-8)).energies(K)))]
    with tempfile.TemporaryDirectory() as tmp:
        for text, degree, radial, name, reference in cases:
            path = Path(tmp) / "n3.toml"
            path.write_text(CONFIG.format(potential=text, degree=degree, radial=radial))
            out, elapsed = command(["spectrum", str(path), "--levels", str(K), "--json"])
            data = json.loads(out)
            E = np.array(data["energies"], float)
            error = np.max(np.abs(E - reference()[:K]))
            print(f"{text:34s} {degree:6d} x {radial:<6d} {elapsed:12.2f} {error:11.1e}   "
                  f"{name:20s} {data['complete']}")


def main() -> None:
    sixty_levels()
    if "--all" not in sys.argv:
        return
    print()
    print("R^9 oscillator, lowest 220 states (N = 0..3), every sector")
    print("degree   time[s]   peak MB   max|E - (N + 9/2)|   multiplicities")

    def oscillator(Q):
        return 0.5 * np.sum(Q**2, -1)
    for degree in (4, 6):
        s, t, mem = measure(lambda d=degree: sp.solve(
            "dalembert", 3, oscillator, 1.0, inertia=1.0, levels=220,
            settings=sp.Settings(basis_size=d, scale=1.0, check_shrink=2)))
        E = np.array(s.energies(220))
        N = np.round(E - 4.5).astype(int)
        mult = [lv.multiplicity for lv in s.levels]
        ok = mult == [comb(n + 8, 8) for n in range(len(mult))]
        # a level counts as converged only if the nested basis (degree - 2) holds it too
        print(f"{degree:6d} {t:9.2f} {mem:9.1f}   {np.max(np.abs(E - N - 4.5)):18.2e}   "
              f"{mult} {'= C(N+8,8)' if ok else 'WRONG'} for the converged N <= {len(mult) - 1}")

    def Vr(r):
        return 0.5 * r**2 + 0.8 * np.exp(-(r**2) / 2)

    def V(Q):
        return Vr(np.sqrt(np.sum(Q**2, -1)))
    count = 30
    ref = r9_radial_states(Vr, count, h=0.05)
    print(f"\nV = r^2/2 + 0.8 exp(-r^2/2), lowest {count} states vs the R^9 radial solver")
    print("degree   time[s]   peak MB   max|E - E_radial|   sectors solved")
    for degree in (6, 8, 10, 12):
        s, t, mem = measure(lambda d=degree: sp.solve(
            "dalembert", 3, V, 1.0, inertia=1.0, levels=count,
            settings=sp.Settings(basis_size=d, scale=1.0, check_shrink=2, tolerance=1e-2)))
        E = np.array(s.energies(count))
        solved = len({k[1:3] for k in s.blocks})
        print(f"{degree:6d} {t:9.2f} {mem:9.1f}   {np.max(np.abs(E - ref[:len(E)])):17.2e}   "
              f"{solved}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--all", action="store_true",
                        help="also the R^9 oscillator and the anharmonic body (tables 1, 2)")
    parser.parse_args()  # --help: this text, not the benchmark
    main()
