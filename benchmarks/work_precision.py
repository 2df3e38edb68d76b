"""Work-precision: relative energy error vs wall time, our splittings against scipy's DOP853/RK45.

Same system, same run: N = 2 affine bodies in n = 2 (af-is internal + d'Alembert translational
kinetic energy; dilatation, St Venant-Kirchhoff, external harmonic and binary M_a potentials),
integrated to T = 20. Our integrators run through ``simulate.run``, the driver of ``affinebody
run`` (compile time excluded, reported once); scipy integrates the same autodiff vector field
(jitted, called from Python).
Error: max over the run of |E(t) - E(0)| / |E(0)| (sampled every 0.5 time units for scipy).

Run: ``.venv/bin/python benchmarks/work_precision.py``
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

from affinebody import kinetic as kin  # noqa: E402
from affinebody import potentials as pot  # noqa: E402
from affinebody.simulate import energy_error, run  # noqa: E402
from affinebody.state import State  # noqa: E402
from affinebody.system import HamiltonianSystem  # noqa: E402

T_END = 20.0


def make_problem():
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    potential = pot.total_potential([pot.Dilatation(1.0), pot.StVenantKirchhoff(0.3, 0.5),
                                     pot.ExternalHarmonic(0.5), pot.HarmonicInvariants(0.2)])
    rng = np.random.default_rng(4)
    state = State(jnp.asarray(rng.normal(size=(2, 2))),
                  jnp.asarray(np.eye(2) + 0.2 * rng.normal(size=(2, 2, 2))),
                  jnp.asarray(0.5 * rng.normal(size=(2, 2))),
                  jnp.asarray(0.5 * rng.normal(size=(2, 2, 2))))
    return HamiltonianSystem(kinetic, potential), state


def ours(system, state, name, dts):
    """Our integrator through the product's driver, ``simulate.run`` (energy every step);
    each setting is run twice and the second, already compiled, run is timed."""
    rows, compile_s = [], 0.0
    for dt in dts:
        steps = int(round(T_END / dt))
        t0 = time.perf_counter()
        run(system, state, dt, steps, integrator=name, every=1, observers=("energy",))
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        trajectory = run(system, state, dt, steps, integrator=name, every=1,
                         observers=("energy",))
        wall = time.perf_counter() - t0
        compile_s = max(compile_s, first - wall)
        rows.append((name, f"dt={dt:g}", steps, wall, float(np.max(energy_error(trajectory)))))
    return rows, compile_s


def scipy_runs(system, state, method, rtols):
    flat, unravel = ravel_pytree(state)
    field = jax.jit(lambda z: ravel_pytree(system.vector_field(unravel(z)))[0])
    energy = jax.jit(lambda z: system.hamiltonian(unravel(z)))
    field(flat).block_until_ready()
    e0 = float(energy(flat))
    rows = []
    t_eval = np.linspace(0.0, T_END, 41)
    for rtol in rtols:
        t0 = time.perf_counter()
        sol = solve_ivp(lambda t, z: np.asarray(field(jnp.asarray(z))), (0.0, T_END),
                        np.asarray(flat), method=method, rtol=rtol, atol=rtol * 1e-2,
                        t_eval=t_eval)
        wall = time.perf_counter() - t0
        err = max(abs(float(energy(jnp.asarray(z))) - e0) / abs(e0) for z in sol.y.T)
        rows.append((method, f"rtol={rtol:g}", sol.nfev, wall, err))
    return rows


def main():
    system, state = make_problem()
    rows, compiles = [], {}
    for name, dts in (("strang", (0.05, 0.02, 0.01, 0.005)),
                      ("yoshida4", (0.1, 0.05, 0.02, 0.01)),
                      ("yoshida6", (0.2, 0.1, 0.05, 0.025))):
        r, compiles[name] = ours(system, state, name, dts)
        rows += r
    rows += scipy_runs(system, state, "DOP853", (1e-6, 1e-8, 1e-10, 1e-12))
    rows += scipy_runs(system, state, "RK45", (1e-4, 1e-6, 1e-8))
    print(f"Work-precision, N=2 bodies, n=2, T={T_END:g} "
          f"(compile s: {', '.join(f'{k} {v:.1f}' for k, v in compiles.items())})\n")
    print("| method | setting | steps / f-evals | wall s | max rel. energy error |")
    print("|---|---|---|---|---|")
    for method, setting, work, wall, err in rows:
        print(f"| {method} | {setting} | {work} | {wall:.3f} | {err:.2e} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args()  # --help: this text, not the benchmark
    main()
