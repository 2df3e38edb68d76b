"""A compiled tracker of a run's energy and constraint residual, shared by the constrained and
non-holonomic test files (each copy of a constrained H costs about a second to compile), and a
counter of a jitted function's compilations (the run drivers' tests)."""

from __future__ import annotations

import logging
from contextlib import contextmanager

import jax
import jax.numpy as jnp
from jax import lax


def energy_and_residual_tracker(system, step, residual):
    """Jitted (state, dt, steps) -> (final, max |E - E0|, max residual, (E0, E_end)) of
    ``step(state, dt)`` with ``system.hamiltonian`` and ``residual(state)`` (a scalar).

    The loop runs steps + 1 times: each iteration measures the state it starts from (energy,
    residual) and steps it, and the last iteration's step is discarded; so E0 and E_end come
    from the compiled graph (an eager H, op by op, costs more) with one copy of H and of the
    residual in it (each copy adds to the compilation)."""

    @jax.jit
    def evolve(state, dt, steps):
        def body(k, carry):
            s, e0, _, emax, rmax = carry
            e = system.hamiltonian(s)
            e0 = jnp.where(k == 0, e, e0)
            emax = jnp.maximum(emax, jnp.abs(e - e0))
            res = residual(s)
            after = step(s, dt)
            s = jax.tree.map(lambda a, b: jnp.where(k < steps, a, b), after, s)
            return s, e0, e, emax, jnp.maximum(rmax, res)

        zero = jnp.zeros(())
        final, e0, end, emax, rmax = lax.fori_loop(0, steps + 1, body,
                                                   (state, zero, zero, zero, zero))
        return final, emax, rmax, (e0, end)

    return evolve


@contextmanager
def compilations(function_name: str):
    """The XLA compilations of the jitted function ``function_name`` inside the block: a list
    (filled as they happen) of their lines in JAX's compile log (``jax.log_compiles``)."""
    seen = []

    class Catch(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith(f"Compiling jit({function_name})"):
                seen.append(message)

    handler = Catch(level=logging.DEBUG)
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles():
            yield seen
    finally:
        logger.removeHandler(handler)
