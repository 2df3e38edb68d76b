"""Contracts every registered model honours, and the pytree convention the run driver needs.

The kinetic and potential batteries are parametrized over the registries
(``kinetic.MODELS``, ``kinetic.TRANSLATIONAL_MODELS``, ``potentials.POTENTIALS``): a model
gets every check by being registered.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from affinebody import config, runner, simulate

# --------------------------------------------------------------------------------------------
# One compiled loop per system structure


@pytest.fixture(scope="module")
def demo():
    return config.build(config.parse_config(runner.demo_config_text()))


def test_demo_system_is_an_array_pytree_and_two_runs_compile_once(demo):
    """The run driver passes the system as a traced argument of one cached jit only when it is
    an array pytree (hashable treedef: the potential is static; array leaves: the inertia)."""
    system, state = demo.system, demo.state
    assert simulate._is_array_pytree(system)
    assert system.potential is not None
    assert len(jax.tree.leaves(system)) == len(jax.tree.leaves(system.kinetic)) > 0
    before = simulate._simulate_jit._cache_size()
    first = simulate.run(system, state, 0.01, 2)
    after_first = simulate._simulate_jit._cache_size()
    # the same structure with other kinetic parameters (leaves) reuses the compiled loop
    scaled = system.replace(kinetic=jax.tree.map(lambda a: 1.5 * a, system.kinetic))
    second = simulate.run(scaled, state, 0.01, 2)
    assert after_first == before + 1
    assert simulate._simulate_jit._cache_size() == after_first
    # ... and really uses the new parameters: heavier bodies move less in the same time
    moved = [np.abs(np.asarray(t.final_state.x - state.x)).sum() for t in (first, second)]
    assert moved[1] < moved[0]
