"""Does a large all-pairs 3D run finish on an unpinned multi-core process?

jaxlib 0.10 on CPU could deadlock (idle process, forever) when two batched LAPACK kernels
(getrf/trsm behind jnp.linalg.inv/solve/det over large vmapped batches) ran at once on a
two-thread XLA intra-op pool (see ``affinebody/_xla.py``). The library now uses the closed
forms of ``affinebody._linalg`` for its n <= 3 matrices, so a step contains no LAPACK call.

This script runs ``simulate.run`` on 125 bodies (5 x 5 x 5 lattice, n = 3) with the demo's
affine pair potential (r, D, M1) over all 7750 pairs, WITHOUT pinning the process to one core,
``--repeats`` times, each in a fresh subprocess with a timeout, and reports for each: finished
or timed out (a hang), wall time, and how many LAPACK custom calls the compiled step holds.

Run: ``.venv/bin/python benchmarks/lapack_free_run.py [--repeats 5] [--timeout 300]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

SIDE, SPACING, DT, STEPS, EVERY = 5, 1.3, 0.005, 200, 50
DEMO = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"
LAPACK_MARKERS = ("lapack", "getrf", "trsm", "potrf", "gesdd", "syevd")


def child(internal: str) -> None:
    """One run in this process (no pinning): prints the affinity, LAPACK calls and the time."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from affinebody import kinetic as kin
    from affinebody.integrators import get_integrator
    from affinebody.potentials import Dilatation, PairPotential, StVenantKirchhoff, total_potential
    from affinebody.simulate import run
    from affinebody.state import State
    from affinebody.system import HamiltonianSystem

    internal_term = (kin.AffineIsotropic(2.0, 0.5, 0.3) if internal == "af-is"
                     else kin.DAlembert(0.3 * jnp.eye(3)))
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), internal_term)
    potential = total_potential([PairPotential.from_expression(DEMO, 3), Dilatation(5.0),
                                 StVenantKirchhoff(0.5, 1.0)])
    system = HamiltonianSystem(kinetic, potential)
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*[np.arange(SIDE)] * 3, indexing="ij"), -1).reshape(-1, 3)
    phi = np.eye(3) + 0.05 * rng.normal(size=(len(grid), 3, 3))
    state = State(jnp.asarray(SPACING * grid + 0.01 * rng.normal(size=grid.shape)),
                  jnp.asarray(phi), jnp.asarray(0.3 * rng.normal(size=grid.shape)),
                  jnp.asarray(0.05 * rng.normal(size=phi.shape)))
    step = jax.jit(lambda s: get_integrator("strang").step(system, s, DT))
    hlo = step.lower(state).compile().as_text().lower()
    lapack = sum(any(m in line for m in LAPACK_MARKERS)
                 for line in hlo.splitlines() if "custom-call" in line or "custom_call" in line)
    t0 = time.perf_counter()
    trajectory = run(system, state, DT, STEPS, every=EVERY, observers=("energy",))
    wall = time.perf_counter() - t0
    drift = float(np.max(np.abs(trajectory.observables["energy"]
                                - trajectory.observables["energy"][0])))
    print(f"cpus={len(os.sched_getaffinity(0))} lapack_calls_in_step={lapack} "
          f"run_s={wall:.1f} energy_drift={drift:.2e}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--timeout", type=float, default=300.0)
    parser.add_argument("--internal", choices=("af-is", "dalembert"), default="af-is",
                        help="internal kinetic energy: af-is (its drift uses expm) or dalembert")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.internal)
        return
    print(f"{SIDE ** 3} bodies, n=3, {SIDE ** 3 * (SIDE ** 3 - 1) // 2} pairs, {STEPS} Strang "
          f"steps, {args.internal} kinetic energy, unpinned ({len(os.sched_getaffinity(0))} "
          f"CPUs), timeout {args.timeout:.0f} s")
    finished = 0
    for k in range(args.repeats):
        t0 = time.perf_counter()
        try:
            out = subprocess.run([sys.executable, __file__, "--child", "--internal",
                                  args.internal], capture_output=True,
                                 text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(f"run {k + 1}: TIMED OUT after {time.perf_counter() - t0:.0f} s (hang)")
            continue
        total = time.perf_counter() - t0
        if out.returncode:
            print(f"run {k + 1}: FAILED (rc={out.returncode})\n{out.stderr[-2000:]}")
            continue
        finished += 1
        print(f"run {k + 1}: finished in {total:.1f} s  {out.stdout.strip()}")
    print(f"{finished}/{args.repeats} finished")


if __name__ == "__main__":
    main()
