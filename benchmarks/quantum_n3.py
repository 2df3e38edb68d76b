"""Benchmark: n = 3 quantum spectra over every SO(3) x SO(3) sector (j, j').

1. The R^9 oscillator (d'Alembert, J = Id, V = Tr G / 2, hbar = 1): the lowest 220 states
   (N = 0..3: 1 + 9 + 45 + 165) through `spectra.solve` with sectors = "all": time, peak
   memory, the largest |E - (N + 9/2)| and whether every multiplicity is C(N + 8, 8).
2. An anharmonic rotation-invariant body, V = r^2/2 + 0.8 exp(-r^2/2) with r = |phi|: the
   lowest 30 states against an independent R^9 radial solver (sinc DVR of the radial equation
   for hyperspherical harmonics of degree l, degeneracy C(l+8, 8) - C(l+6, 8)), for growing
   basis degree: time, peak memory, max error.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/quantum_n3.py
"""

from __future__ import annotations

from math import comb

import numpy as np
from quantum_spectra import measure  # time and tracemalloc peak, as for n = 2
from scipy import linalg

from affinebody.quantum import spectra as sp


def radial_reference(V, count: int, h: float = 0.05, R: float = 10.0) -> np.ndarray:
    """Lowest ``count`` R^9 states of -Lap/2 + V(|x|), with multiplicity, by sinc DVR."""
    i = np.arange(1, int(R / h) + 1)
    d = i[:, None] - i[None, :]
    T = np.where(d == 0, np.pi**2 / 3 - 1 / (2 * i[:, None] ** 2),
                 2.0 * (-1.0) ** d * (1 / np.where(d == 0, 1, d) ** 2
                                      - 1 / (i[:, None] + i[None, :]) ** 2))
    r = h * i
    states = []
    for ell in range(8):
        E = linalg.eigvalsh(T / (2 * h * h) + np.diag((ell + 3) * (ell + 4) / (2 * r**2) + V(r)),
                            subset_by_index=[0, 5])
        dim = comb(ell + 8, 8) - (comb(ell + 6, 8) if ell >= 2 else 0)
        states += [e for e in E for _ in range(dim)]
    return np.sort(states)[:count]


def main() -> None:
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
    ref = radial_reference(Vr, count)
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
    main()
