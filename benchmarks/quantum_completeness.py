"""Benchmark: completeness of the n = 2 af-is spectrum of issue 20.

af-is, I = 1, A = 0.2, B = 0.1, hbar = 1, V = 0.5 (q1 + q2)^2 - 24 Q1 Q2 / (Q1 + Q2)^2: a
harmonic well in ln det phi plus an attractive well in the shear x = q1 - q2, whose lowest level
per shell max(|s|, |k|) is not monotone. The exact spectrum is the closed form (the sigma
oscillator plus the Poeschl-Teller levels of the shear operator, docs/theory/two-polar.md; the
same closed form is checked against finite volumes in tests/test_quantum_completeness.py).

For K = 30 and 60 at the default basis (24) and at basis 40, and for K = 60 with max_spin = 80:
time, shells searched, blocks skipped by their bound, whether the list is certified, the
number of unconverged states (NaN in their place), the worst error of the converged ones, and
the number of genuine levels among the K lowest that are missing or replaced (must be 0).

Run: OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/quantum_completeness.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import numpy as np

from affinebody.quantum import spectra as sp
from affinebody.quantum.config import compile_potential

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_quantum_completeness import SHEAR_WELL, shear_well_exact  # noqa: E402


def main() -> None:
    exact = np.array([E for E, _, _ in shear_well_exact(max_shell=90, top=3.0)])
    V = compile_potential(SHEAR_WELL, 2)
    print(f"{'K':>3} {'basis':>5} {'max_spin':>8} {'time s':>7} {'shells':>6} {'skipped':>7} "
          f"{'certified':>9} {'unknown':>7} {'worst err':>9} {'wrong':>5}")
    for K, basis, max_spin in [(30, 24, 40), (60, 24, 40), (60, 24, 80), (30, 40, 40),
                               (60, 40, 80)]:
        t0 = time.perf_counter()
        s = sp.solve("af-is", 2, V, 1.0, I=1.0, A=0.2, B=0.1, levels=K,
                     settings=sp.Settings(basis_size=basis, max_spin=max_spin))
        elapsed = time.perf_counter() - t0
        got = np.array(s.energies(K))
        known = ~np.isnan(got)
        worst = float(np.max(np.abs(got[known] - exact[:K][known]))) if known.any() else np.nan
        wrong = int(np.sum(np.abs(got[known] - exact[:K][known]) > 1e-6)) + (K - len(got))
        print(f"{K:>3} {basis:>5} {max_spin:>8} {elapsed:>7.1f} "
              f"{s.settings['shells_searched']:>6} {s.settings['sectors_pruned']:>7} "
              f"{s.certified!s:>9} {int((~known).sum()):>7} {worst:>9.1e} {wrong:>5}")


if __name__ == "__main__":
    main()
