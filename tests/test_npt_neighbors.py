"""Neighbour lists that follow a box a barostat deforms (docs/pressure.md): over a list built in
a strained cell, the pair energy, forces and virial are the all-pairs ones (n = 2 and 3,
orthorhombic and triclinic; the compiled host kernel and the JAX kernel); a list built in one
cell and kept while the rebuild rule says so still holds every pair in range after the box and
the bodies moved; an NPT run with a list repeats the all-pairs run to round-off while the box
shrinks and the list is rebuilt."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import barostat, pressure
from affinebody import neighbors as nb
from affinebody import pair_kernels as pk
from affinebody.kinetic import DAlembert, DAlembertTranslational, KineticEnergy
from affinebody.potentials import Cutoff, Dilatation, PairPotential, total_potential
from affinebody.space import triclinic
from affinebody.state import State
from affinebody.system import HamiltonianSystem

CELLS = {
    (2, "triclinic"): [[4.2, 1.1], [0.0, 3.9]],
    (3, "orthorhombic"): [[4.2, 0.0, 0.0], [0.0, 3.9, 0.0], [0.0, 0.0, 4.4]],
    (3, "triclinic"): [[4.2, 0.9, -0.6], [0.0, 3.9, 0.7], [0.0, 0.0, 4.4]],
}
R_CUT, SKIN = 1.3, 0.2


def pair_function(r, D, K1):
    """Depends on u through r and D (75), and on the shapes through K1 and D."""
    return jnp.exp(-D * D) * (1.0 + 0.3 * K1) + 0.5 / r**2


def setup(n, kind, bodies=30, seed=0):
    rng = np.random.default_rng(seed)
    space = triclinic(CELLS[(n, kind)])
    x = rng.uniform(-0.5, 1.5, (bodies, n)) @ space.matrix.T  # spread over images
    phi = np.eye(n) + 0.2 * rng.normal(size=(bodies, n, n))
    phi[np.linalg.det(phi) < 0, 0] *= -1
    pair = PairPotential(pair_function, ("r", "D", "K1"), Cutoff(R_CUT, 1.0), space)
    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0), DAlembert(np.eye(n))),
                               total_potential([pair, Dilatation(0.7)]))
    return system, jnp.asarray(x), jnp.asarray(phi), space, pair, rng


def strain(rng, n, scale):
    """A box deformation mu: shrinks by `scale` and shears (upper triangle, as the barostat)."""
    return scale * np.eye(n) + 0.04 * np.triu(rng.normal(size=(n, n)), 1)


@jax.jit
def _forces(system, state, lists):
    return system.potential_energy(state, lists), system.forces(state, lists)


@pytest.mark.parametrize("n, kind", list(CELLS))
def test_list_in_a_strained_cell_gives_the_all_pairs_energy_forces_and_virial(n, kind):
    system, x, phi, space, pair, rng = setup(n, kind)
    mu = strain(rng, n, 0.93)
    cell = jnp.asarray(mu @ space.matrix)
    x = x @ mu.T  # the barostat's move: centres with the box, fixed shapes
    state = State(x, phi, jnp.zeros_like(x), jnp.zeros_like(phi))
    spec, lists = nb.allocate(space, x, phi, R_CUT, "r", SKIN, cell=cell)
    in_range = nb.brute_force_pairs(triclinic(np.asarray(cell)), np.asarray(x), R_CUT)
    assert len(in_range) > 20
    assert set(map(tuple, in_range)) <= set(map(tuple, nb.pairs_of(lists)))
    boxed = system.replace(cell=cell)
    energy, (g_x, g_phi) = boxed.potential_energy(state), boxed.forces(state)
    energy_l, (g_x_l, g_phi_l) = _forces(boxed, state, lists)  # the host kernel on a CPU
    scale = float(jnp.max(jnp.abs(g_x)))
    np.testing.assert_allclose(energy_l, energy, rtol=1e-12)
    np.testing.assert_allclose(g_x_l, g_x, atol=1e-12 * scale)
    np.testing.assert_allclose(g_phi_l, g_phi, atol=1e-12 * scale)
    # the JAX kernel (a GPU's) with the same cell, restricted to the pair term
    e_pair, gx_pair, gphi_pair = pk.energy_and_gradients(pair, space, x, phi, lists.i, lists.j,
                                                         lists.count, cell=cell)
    all_pairs = jax.grad(lambda y, p: jnp.sum(pair.pair_energies(y, p, cell)), argnums=(0, 1))
    ref_x, ref_phi = all_pairs(x, phi)
    np.testing.assert_allclose(gx_pair, ref_x, atol=1e-12 * scale)
    np.testing.assert_allclose(gphi_pair, ref_phi, atol=1e-12 * scale)
    np.testing.assert_allclose(e_pair, jnp.sum(pair.pair_energies(x, phi, cell)), rtol=1e-12)
    virial = pressure.virial(boxed, state, space)
    np.testing.assert_allclose(pressure.virial(boxed, state, space, lists), virial,
                               atol=1e-12 * float(jnp.max(jnp.abs(virial))))


def test_a_kept_list_holds_every_pair_in_range_while_the_box_and_the_bodies_move():
    """The rebuild rule |A| rho + 2 max |m_K| <= rho(build) + skin (docs/pressure.md): for
    random box strains and displacements, whenever it says "keep", every pair now in range is
    in the list; and a strain large enough makes it rebuild."""
    system, x, phi, space, pair, rng = setup(3, "triclinic", bodies=60, seed=1)
    cell0 = jnp.asarray(space.matrix)
    spec, lists = nb.allocate(space, x, phi, R_CUT, "r", SKIN, cell=cell0)
    kept = 0
    for trial in range(40):
        mu = strain(rng, 3, 1.0 + rng.uniform(-0.12, 0.08))
        cell = jnp.asarray(mu @ space.matrix)
        moved = x @ mu.T + rng.uniform(0, 0.1) * rng.normal(size=x.shape) / np.sqrt(3)
        if bool(nb.needs_rebuild(spec, lists, moved, phi, cell)):
            continue
        kept += 1
        in_range = nb.brute_force_pairs(triclinic(np.asarray(cell)), np.asarray(moved), R_CUT)
        assert set(map(tuple, in_range)) <= set(map(tuple, nb.pairs_of(lists))), trial
    assert 5 <= kept < 40
    squeezed = jnp.asarray(0.8 * np.eye(3)) @ cell0
    assert bool(nb.needs_rebuild(spec, lists, x @ (0.8 * jnp.eye(3)), phi, squeezed))


def test_npt_run_with_a_list_repeats_the_all_pairs_run_while_the_box_shrinks():
    n = 2
    space = triclinic([[4.0, 0.5], [0.0, 3.8]])
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(5), np.arange(5), indexing="ij"), -1).reshape(-1, n)
    x = (grid / 5 + 0.02 * rng.normal(size=grid.shape)) @ space.matrix.T
    bodies = len(x)
    pair = PairPotential(pair_function, ("r", "D", "K1"), Cutoff(1.2, 0.9), space)
    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0),
                                             DAlembert(0.5 * np.eye(n))),
                               total_potential([pair, Dilatation(0.7)]))
    state = State(jnp.asarray(x), jnp.asarray(np.eye(n) + 0.05 * rng.normal(size=(bodies, n, n))),
                  jnp.asarray(0.5 * rng.normal(size=(bodies, n))), jnp.zeros((bodies, n, n)))
    b = barostat.c_rescale(0.5, n, tau=0.02, compressibility=1.0, temperature=1.0,
                           coupling="anisotropic")
    lists = nb.allocate(space, state.x, state.phi, 1.2, "r", 0.05, cell=space.matrix)
    args = (system, state, space, b, 0.005, 40)
    ref = barostat.run(*args, seed=3, every=10)
    run = barostat.run(*args, seed=3, every=10, neighbors=lists)
    assert ref.failed_step is None and run.failed_step is None
    volume = ref.observables["volume"]
    assert volume[-1] < 0.9 * volume[0]  # the box shrank: the list was rebuilt in it
    assert not np.array_equal(run.neighbors[1].cell, space.matrix)
    for a, b_ in ((run.states.x, ref.states.x), (run.states.phi, ref.states.phi),
                  (run.cells, ref.cells), (run.observables["pressure"],
                                            ref.observables["pressure"])):
        np.testing.assert_allclose(a, b_, rtol=0, atol=1e-11 * np.max(np.abs(b_)))
