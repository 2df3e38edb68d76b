"""Consistency of the barostat and the pressure tensor with interactions (issue 15, item 5):
an NPT run at P0 gives <V>; an NVT run at that V gives <P> = P0 within the errors.

16 bodies in 2D (d'Alembert translations, af-is internal motion) with a soft repulsion in the
affine distance D (75), a dilatation and a St Venant-Kirchhoff one-body energy; the centres'
momenta are thermostatted by an exact Ornstein-Uhlenbeck step (the thermostat hook of
``affinebody.barostat.run``); isotropic stochastic cell rescaling. Errors are from 20 blocks.
Too long for the test suite (about a minute of integration on one core).

Run: ``.venv/bin/python benchmarks/npt_consistency.py [--steps 100000]``
Measured (2026-11-24, 2-core machine shared with other jobs, 100000 steps each):
NPT <V> = 43.26 +- 0.71; NVT at V = 43.26: <P> = 0.4799 +- 0.0037 (P0 = 0.5). Two NVT runs
(V = 42.86: <P> = 0.4945; V = 43.26: 0.4799) give dP/dV = -0.037, so the NPT volume's own
error (+- 0.71) is +- 0.026 in P: the two ensembles agree within it.
"""

from __future__ import annotations

import argparse
import time

from affinebody._checks import enable_x64

enable_x64()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from affinebody import barostat, pressure  # noqa: E402
from affinebody.integrators import get_integrator  # noqa: E402
from affinebody.kinetic import AffineIsotropic, DAlembertTranslational, KineticEnergy  # noqa: E402
from affinebody.potentials import (  # noqa: E402
    Cutoff,
    Dilatation,
    PairPotential,
    StVenantKirchhoff,
    total_potential,
)
from affinebody.space import orthorhombic  # noqa: E402
from affinebody.state import State  # noqa: E402

KT, P0, GAMMA, DT, EVERY = 1.0, 0.5, 2.0, 0.005, 20


def thermostat(system, state, key, dt):
    """Exact OU step of the centres' momenta (unit mass) at KT."""
    c = jnp.exp(-GAMMA * dt)
    return state._replace(p=c * state.p + jnp.sqrt((1 - c * c) * KT)
                          * jax.random.normal(key, state.p.shape))


def blocked(values, blocks=20):
    v = np.asarray(values)[: len(values) // blocks * blocks].reshape(blocks, -1).mean(axis=1)
    return v.mean(), v.std(ddof=1) / np.sqrt(blocks)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    steps = parser.parse_args().steps
    space = orthorhombic((6.0, 6.0))
    pair = PairPotential(lambda r, D: 2.0 * jnp.exp(-D * D), ("r", "D"), Cutoff(1.95, 1.7),
                         space)
    system_pot = total_potential([pair, Dilatation(3.0), StVenantKirchhoff(0.5, 1.0)])
    from affinebody.system import HamiltonianSystem

    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0), AffineIsotropic(0.5)),
                               system_pot)
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2) * 1.5 + 0.5
    state = State(jnp.asarray(grid), jnp.broadcast_to(jnp.eye(2), (16, 2, 2)) + 0.0,
                  jnp.asarray(rng.normal(size=(16, 2))),
                  jnp.asarray(0.3 * rng.normal(size=(16, 2, 2))))
    baro = barostat.c_rescale(P0, 2, tau=0.5, compressibility=0.2, temperature=KT)
    start = time.perf_counter()
    npt = barostat.run(system, state, space, baro, DT, steps, seed=1, every=EVERY,
                       thermostat=thermostat)
    assert npt.failed_step is None
    skip = len(npt.times) // 10
    volume, volume_error = blocked(npt.observables["volume"][skip:])
    print(f"NPT at P0 = {P0}: <V> = {volume:.4g} +- {volume_error:.2g} "
          f"({time.perf_counter() - start:.1f} s)")
    scale = np.sqrt(volume / np.linalg.det(npt.cells[-1]))
    last = npt.final_state
    nvt_state = last._replace(x=last.x * scale, p=last.p / scale)
    boxed = system.replace(cell=jnp.asarray(npt.cells[-1] * scale))
    method = get_integrator("strang")

    @jax.jit
    def nvt(s):
        def step(carry, k):
            s = method.step(boxed, carry, DT)
            return thermostat(boxed, s, jax.random.fold_in(jax.random.PRNGKey(5), k), DT), None

        def chunk(s, k):
            s, _ = lax.scan(step, s, k * EVERY + jnp.arange(EVERY))
            return s, jnp.trace(pressure.pressure_tensor(boxed, s, space)) / 2

        return lax.scan(chunk, s, jnp.arange(steps // EVERY))[1]

    start = time.perf_counter()
    values = np.asarray(nvt(nvt_state))[steps // EVERY // 20:]
    mean, error = blocked(values)
    print(f"NVT at V = {volume:.4g}: <P> = {mean:.4g} +- {error:.2g} (target {P0}; "
          f"{time.perf_counter() - start:.1f} s)")


if __name__ == "__main__":
    main()
