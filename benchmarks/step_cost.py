"""Step cost vs the number of bodies N (n = 3): wall time per Strang / Yoshida-4 step.

System: af-is internal + d'Alembert translational kinetic energy, one-body dilatation and St
Venant-Kirchhoff potentials and a binary Morse-in-r + M_a potential over all N(N-1)/2 pairs, so
the kick is O(N^2) and the drift O(N). 200 steps per measurement in one jitted ``lax.fori_loop``,
compile time excluded.

Run: ``.venv/bin/python benchmarks/step_cost.py``
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from affinebody import kinetic as kin  # noqa: E402
from affinebody import potentials as pot  # noqa: E402
from affinebody.integrators import get_integrator  # noqa: E402
from affinebody.state import State  # noqa: E402
from affinebody.system import HamiltonianSystem  # noqa: E402

STEPS = 200


def main():
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    pair = pot.PairPotential(
        lambda r, M1: (1 - jnp.exp(-(r - 1.5))) ** 2 + 0.1 * (M1 - 3.0) ** 2, ("r", "M1"))
    potential = pot.total_potential([pot.Dilatation(1.0), pot.StVenantKirchhoff(0.3, 0.5), pair])
    system = HamiltonianSystem(kinetic, potential)
    print(f"Step cost, n=3, {STEPS} steps per measurement (CPU: {jax.devices()[0].device_kind})\n")
    print("| N | pairs | strang us/step | yoshida4 us/step | compile s (strang) |")
    print("|---|---|---|---|---|")
    for bodies in (2, 8, 32, 64):
        rng = np.random.default_rng(bodies)
        side = int(np.ceil(bodies ** (1 / 3)))
        grid = np.stack(np.meshgrid(*[np.arange(side)] * 3), -1).reshape(-1, 3)[:bodies]
        state = State(jnp.asarray(1.5 * grid + 0.05 * rng.normal(size=(bodies, 3))),
                      jnp.asarray(np.eye(3) + 0.05 * rng.normal(size=(bodies, 3, 3))),
                      jnp.asarray(0.1 * rng.normal(size=(bodies, 3))),
                      jnp.asarray(0.1 * rng.normal(size=(bodies, 3, 3))))
        cells = []
        compile_s = 0.0
        for name in ("strang", "yoshida4"):
            method = get_integrator(name)
            run = jax.jit(lambda s, method=method: lax.fori_loop(
                0, STEPS, lambda _, z: method.step(system, z, 0.01), s))
            t0 = time.perf_counter()
            jax.block_until_ready(run(state))
            if name == "strang":
                compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            jax.block_until_ready(run(state))
            cells.append(1e6 * (time.perf_counter() - t0) / STEPS)
        pairs = bodies * (bodies - 1) // 2
        print(f"| {bodies} | {pairs} | {cells[0]:.1f} | {cells[1]:.1f} | {compile_s:.1f} |")


if __name__ == "__main__":
    main()
