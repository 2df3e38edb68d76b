"""Benchmark: the lowest 30 levels of the n = 2 anharmonic d'Alembert body,
V = 0.5 Tr G + 0.1 (det phi - 1)^2, J = Id, hbar = 1, by the two-polar reduced solver and by
the independent Cartesian (R^4 Hermite Galerkin) solver, in one run: time, peak memory
(tracemalloc, numpy allocations) and accuracy against the largest basis of each.

Second table: the classical limit of af-is (74) on GL+(2) with V = x^2 + x^4 + sigma^2
(x = q1 - q2, sigma = q1 + q2), beta = 1: Z_quantum / Z_classical - 1 against hbar, the local
log-log slopes (-> 2) and the basis error estimate.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/quantum_spectra.py
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from affinebody.quantum import spectra as sp
from affinebody.quantum import thermal as th
from affinebody.quantum.n2 import auto_scale_lebesgue2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from oracles import cartesian_n2_levels  # noqa: E402  (the test oracle, not library code)

COUNT = 30


def potential(Q):
    return 0.5 * np.sum(Q**2, axis=-1) + 0.1 * (np.prod(Q, axis=-1) - 1) ** 2


def measure(fn):
    tracemalloc.start()
    t0 = time.perf_counter()
    value = fn()
    elapsed = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return value, elapsed, peak / 2**20


def main() -> None:
    reduced, cartesian = {}, {}
    scale = auto_scale_lebesgue2(potential, 1.0, 1.0)
    for size in (12, 16, 20, 28):
        settings = sp.Settings(basis_size=size, scale=scale)
        result, t, mem = measure(lambda s=settings: sp.solve(
            "dalembert", 2, potential, 1.0, inertia=1.0, levels=COUNT, settings=s))
        reduced[size] = (np.array(result.energies(COUNT)), t, mem)
        print(f"  (reduced, size {size}: {t:.1f} s)", file=sys.stderr, flush=True)
    for size in (12, 16, 20, 24):
        values, t, mem = measure(lambda s=size: cartesian_n2_levels(
            potential, 1.0, 1.0, COUNT, size=s, scale=scale))
        cartesian[size] = (values, t, mem)
        print(f"  (cartesian, size {size}: {t:.1f} s)", file=sys.stderr, flush=True)
    ref_r = reduced[max(reduced)][0]
    ref_c = cartesian[max(cartesian)][0]
    print(f"lowest {COUNT} levels, n = 2 anharmonic; scale {scale:.6f}")
    print("solver      size   time[s]   peak MB   max|E - E_ref(own)|   max|E - E_other_ref|")
    for name, table, own, other in (("reduced", reduced, ref_r, ref_c),
                                    ("cartesian", cartesian, ref_c, ref_r)):
        for size, (vals, t, mem) in table.items():
            n = min(len(vals), COUNT)
            print(f"{name:10s} {size:5d} {t:9.2f} {mem:9.1f}   "
                  f"{np.max(np.abs(vals[:n] - own[:n])):19.2e}   "
                  f"{np.max(np.abs(vals[:n] - other[:n])):19.2e}")
    print("levels (reduced, largest basis):", np.array2string(ref_r, precision=10))


def classical_limit() -> None:
    def v_x(x):
        return x**2 + x**4

    def v_sigma(s):
        return s**2

    def v_of_q(Q):
        q = np.log(Q)
        return v_x(q[..., 0] - q[..., 1]) + v_sigma(q[..., 0] + q[..., 1])

    print("\naf-is, I = 1, A = 0.2, B = 0.1, beta = 1: Z_q / Z_cl - 1")
    print("  hbar   sectors   time[s]         Z_q          Z_cl       Z_q/Z_cl-1   error/|diff|"
          "   slope")
    previous = None
    for hbar, size in ((0.5, 40), (0.35, 40), (0.25, 50), (0.18, 60), (0.13, 80), (0.1, 100)):
        zq, t, _ = measure(lambda h=hbar, n=size: th.partition_function_affine2(
            "af-is", v_x, v_sigma, h, 1.0, I=1.0, A=0.2, B=0.1, size=n))
        zc = th.classical_partition_function_affine2("af-is", v_of_q, hbar, 1.0, I=1.0, A=0.2,
                                                     B=0.1)
        rel = zq.value / zc - 1
        slope = "" if previous is None else (
            f"{np.log(abs(rel) / abs(previous[1])) / np.log(hbar / previous[0]):7.3f}")
        print(f"{hbar:6.3f} {zq.sectors:9d} {t:9.2f} {zq.value:12.6g} {zc:12.6g} {rel:12.5e} "
              f"{zq.error / abs(zq.value - zc):12.2e}   {slope}")
        previous = (hbar, rel)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args()  # --help: this text, not the benchmark
    main()
    classical_limit()
