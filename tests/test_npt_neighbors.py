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

CELLS = {  # the kernels take any cell as an operand: one orthorhombic and one triclinic case
    (2, "orthorhombic"): [[4.2, 0.0], [0.0, 3.9]],
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


def strain(rng, n, scale, shear=True):
    """A box deformation mu as the anisotropic barostat's: each edge shrinks by about
    ``scale``, and (``shear``) the upper triangle shears."""
    mu = np.diag(scale + 0.02 * rng.normal(size=n))
    return mu + 0.04 * np.triu(rng.normal(size=(n, n)), 1) if shear else mu


@jax.jit
def _list_and_all_pairs(system, state, space, lists):
    """(energy, dV/dx, dV/dphi, virial) over the list (the host kernel on a CPU), over all
    pairs, and the pair term's over the list with the JAX kernel, in one compilation."""
    def both(neighbors):
        return (system.potential_energy(state, neighbors), *system.forces(state, neighbors),
                pressure.virial(system, state, space, neighbors))

    pair = system.potential.terms[0]
    jax_kernel = pk.energy_and_gradients(pair, space, state.x, state.phi, lists.i, lists.j,
                                         lists.count, cell=system.cell)
    jax_kernel += (pk.pair_virial(pair, space, state.x, state.phi, lists.i, lists.j,
                                  lists.count, system.cell, chunk=64),)
    all_pairs = jax.value_and_grad(lambda y, p: jnp.sum(pair.pair_energies(y, p, system.cell)),
                                   argnums=(0, 1))(state.x, state.phi)
    return both(lists), both(None), jax_kernel, all_pairs


@pytest.mark.parametrize("n, kind", list(CELLS))
def test_list_in_a_strained_cell_gives_the_all_pairs_energy_forces_and_virial(n, kind):
    system, x, phi, space, pair, rng = setup(n, kind)
    mu = strain(rng, n, 0.93, shear=kind == "triclinic")
    cell = jnp.asarray(mu @ space.matrix)
    x = x @ mu.T  # the barostat's move: centres with the box, fixed shapes
    state = State(x, phi, jnp.zeros_like(x), jnp.zeros_like(phi))
    spec, lists = nb.allocate(space, x, phi, R_CUT, "r", SKIN, cell=cell)
    in_range = nb.brute_force_pairs(triclinic(np.asarray(cell)), np.asarray(x), R_CUT)
    assert len(in_range) > 20
    assert set(map(tuple, in_range)) <= set(map(tuple, nb.pairs_of(lists)))
    listed, reference, (e_jax, gx_jax, gphi_jax, w_jax), (e_pair, (gx_pair, gphi_pair)) = (
        _list_and_all_pairs(system.replace(cell=cell), state, space, lists))
    scale = float(jnp.max(jnp.abs(reference[1])))
    for value, expected in zip(listed, reference, strict=True):
        np.testing.assert_allclose(value, expected, rtol=0,
                                   atol=1e-12 * max(scale, float(jnp.max(jnp.abs(expected)))))
    np.testing.assert_allclose(e_jax, e_pair, rtol=1e-12)
    np.testing.assert_allclose(gx_jax, gx_pair, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(gphi_jax, gphi_pair, rtol=0, atol=1e-12 * scale)
    # the virial: host kernel (above, the one-body term has none) and JAX kernel agree
    np.testing.assert_allclose(w_jax, reference[3], rtol=0,
                               atol=1e-12 * float(jnp.max(jnp.abs(reference[3]))))


_needs_rebuild = jax.jit(nb.needs_rebuild, static_argnums=0)


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
        if bool(_needs_rebuild(spec, lists, moved, phi, cell)):
            continue
        kept += 1
        in_range = nb.brute_force_pairs(triclinic(np.asarray(cell)), np.asarray(moved), R_CUT)
        assert set(map(tuple, in_range)) <= set(map(tuple, nb.pairs_of(lists))), trial
    assert 5 <= kept < 40
    squeezed = jnp.asarray(0.8 * np.eye(3)) @ cell0
    assert bool(_needs_rebuild(spec, lists, x @ (0.8 * jnp.eye(3)), phi, squeezed))


def shrinking_box():
    """25 bodies in a 2D triclinic box that the c-rescale barostat below shrinks (P0 = 20):
    (system, state, space)."""
    n = 2
    space = triclinic([[4.0, 0.5], [0.0, 3.8]])
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(5), np.arange(5), indexing="ij"), -1).reshape(-1, n)
    x = (grid / 5 + 0.02 * rng.normal(size=grid.shape)) @ space.matrix.T
    bodies = len(x)
    pair = PairPotential(lambda r, D: jnp.exp(-D * D) + 0.5 / r**2, ("r", "D"),
                         Cutoff(1.2, 0.9), space)
    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0),
                                             DAlembert(0.5 * np.eye(n))), pair)
    state = State(jnp.asarray(x), jnp.asarray(np.eye(n) + 0.05 * rng.normal(size=(bodies, n, n))),
                  jnp.asarray(0.5 * rng.normal(size=(bodies, n))), jnp.zeros((bodies, n, n)))
    return system, state, space


@pytest.mark.parametrize("metropolis", [False, True])
def test_npt_run_with_a_list_repeats_the_all_pairs_run_while_the_box_shrinks(metropolis):
    """With the Metropolis test the moved state's energy and virial come from the list's
    pass (``pressure.energy_forces_virial``), without it from all pairs: the same moves
    accepted, the same motion."""
    n = 2
    system, state, space = shrinking_box()
    b = barostat.c_rescale(20.0, n, tau=1.0, compressibility=1.0, temperature=0.1,
                           metropolis=metropolis)
    lists = nb.allocate(space, state.x, state.phi, 1.2, "r", 0.05, cell=space.matrix)
    args = (system, state, space, b, 0.005, 30)
    ref = barostat.run(*args, seed=3, every=10)
    run = barostat.run(*args, seed=3, every=10, neighbors=lists)
    assert ref.failed_step is None and run.failed_step is None
    volume = ref.observables["volume"]
    assert volume[-1] < 0.8 * volume[0]  # the box shrank: the list was rebuilt in it (and
    assert run.neighbors[0].capacity > lists[0].capacity  # reallocated as the pairs grew)
    assert not np.array_equal(run.neighbors[1].cell, space.matrix)
    for a, b_ in ((run.states.x, ref.states.x), (run.states.phi, ref.states.phi),
                  (run.cells, ref.cells), (run.observables["pressure"],
                                            ref.observables["pressure"])):
        np.testing.assert_allclose(a, b_, rtol=0, atol=1e-11 * np.max(np.abs(b_)))
    if metropolis:
        np.testing.assert_array_equal(run.observables["rejected_moves"],
                                      ref.observables["rejected_moves"])
        assert ref.observables["rejected_moves"].sum() > 0


def test_an_npt_call_computes_no_frame_after_its_list_overflowed(monkeypatch):
    """The NPT loop skips the frames after a failed step (a ``lax.cond`` per frame, as the NVE
    loop): a list that overflows costs the rest of its frame and the steps redone from the
    frame before, not the rest of the call. Counted as the host kernel's gradient passes
    against a run whose list has room (no reallocation): at most one frame's passes more per
    reallocation (computing every frame of the call, they had been two more here)."""
    n, steps, every = 2, 60, 20
    system, state, space = shrinking_box()
    b = barostat.c_rescale(20.0, n, tau=1.0, compressibility=1.0, temperature=0.1)
    passes, reallocations = [], []
    scatter, reallocate = pk._host_scatter, nb.reallocate
    monkeypatch.setattr(pk, "_host_scatter", lambda *a, **k: passes.append(1) or scatter(*a, **k))
    monkeypatch.setattr(nb, "reallocate",
                        lambda *a, **k: reallocations.append(1) or reallocate(*a, **k))

    def counted(capacity_factor):
        passes.clear()
        reallocations.clear()
        lists = nb.allocate(space, state.x, state.phi, 1.2, "r", 0.05, cell=space.matrix,
                            capacity_factor=capacity_factor)
        out = barostat.run(system, state, space, b, 0.005, steps, seed=3, every=every,
                           neighbors=lists)
        assert out.failed_step is None
        return len(passes), len(reallocations), out

    roomy, none, reference = counted(6.0)
    tight, some, overflowed = counted(1.25)  # the box shrinks: more pairs than it holds
    assert none == 0 and some >= 1
    if pk.host_kernel_in_use():  # the passes are the host kernel's (Numba, CPU)
        per_step = (roomy - 1) / steps  # one pass for the initial forces
        assert per_step >= 1
        assert tight <= roomy + some * (per_step * every + 1)
    np.testing.assert_allclose(overflowed.states.x, reference.states.x, rtol=0,
                               atol=1e-11 * np.max(np.abs(reference.states.x)))


def test_an_npt_list_that_cannot_be_reallocated_stops_the_run_and_keeps_its_frames(
        monkeypatch):
    """The NPT run follows the NVE run's overflow policy (``simulate.ListRestarts``): where
    the list cannot be reallocated it stops at the step that overflowed with the frames
    before it (those of a run whose list had room) and says why, instead of raising and
    losing the call's frames (as it did)."""
    from affinebody import simulate

    n, steps, every = 2, 60, 20
    system, state, space = shrinking_box()
    b = barostat.c_rescale(20.0, n, tau=1.0, compressibility=1.0, temperature=0.1)

    def npt(capacity_factor):
        lists = nb.allocate(space, state.x, state.phi, 1.2, "r", 0.05, cell=space.matrix,
                            capacity_factor=capacity_factor)
        return barostat.run(system, state, space, b, 0.005, steps, seed=3, every=every,
                            neighbors=lists)

    reference = npt(6.0)
    assert reference.failed_step is None

    def refuse(*args, **kwargs):
        raise nb.NeighborListOverflow("no room for this list (test)")

    monkeypatch.setattr(nb, "reallocate", refuse)
    stopped = npt(1.25)  # the box shrinks: more pairs than the list holds
    assert stopped.failed_step is not None and 0 < stopped.failed_step <= steps
    assert "could not be reallocated: no room for this list (test)" in stopped.stop_reason
    assert stopped.stop_reason.endswith(simulate.OVERFLOW_FIX)
    before = int(np.sum(np.round(stopped.times / 0.005) < stopped.failed_step))
    assert before >= 1
    np.testing.assert_allclose(stopped.states.x[:before], reference.states.x[:before], rtol=0,
                               atol=1e-11 * np.max(np.abs(reference.states.x)))
    np.testing.assert_allclose(stopped.cells[:before], reference.cells[:before], rtol=1e-12)


def test_an_npt_run_that_stops_after_a_rebuild_ends_with_a_list_of_its_last_good_state(
        monkeypatch):
    """The NPT loop does not hold the previous list back with the previous state and cell
    (that cost a copy of the list per step): a step that fails has already replaced the list
    with one for its own discarded state. With no skin every step rebuilds; the step that
    fails here (dt too large: the box shrinks below twice the list's radius at step 12) is in
    the middle of a frame, so that frame (and those after it) holds the last good state,
    whose observables and list must be its own: the pressure of the last frame is the
    all-pairs pressure of that state in that cell, and the run returns a list built for
    them that holds every pair. Where the list built for it does not fit (made to overflow
    here), the run reallocates and repeats from the frame before, to the same end."""
    from affinebody import simulate

    n, every, dt_too_large = 2, 8, 0.08
    system, state, space = shrinking_box()
    b = barostat.c_rescale(20.0, n, tau=1.0, compressibility=1.0, temperature=0.1)
    lists = nb.allocate(space, state.x, state.phi, 1.2, "r", 0.0, cell=space.matrix,
                        capacity_factor=3.0)

    def stopped():
        return barostat.run(system, state, space, b, dt_too_large, 64, seed=3, every=every,
                            neighbors=lists)

    def assert_last_good_state(out):
        step = out.failed_step
        assert step is not None and step % every not in (0, 1)  # stops inside a frame
        assert out.stop_reason.startswith("the box shrank below twice")
        last = jax.tree.map(lambda a: jnp.asarray(a[-1]), out.states)
        cell = jnp.asarray(out.cells[-1])
        boxed = system.replace(cell=cell)
        np.testing.assert_allclose(out.observables["pressure"][-1],
                                   pressure.pressure_tensor(boxed, last, space), rtol=1e-12,
                                   atol=1e-12 * np.max(np.abs(out.observables["pressure"][-1])))
        spec, kept = out.neighbors
        assert int(kept.overflow) == 0
        np.testing.assert_array_equal(kept.cell, cell)  # built for that state in that cell
        np.testing.assert_array_equal(kept.reference_x, last.x)
        in_range = nb.brute_force_pairs(triclinic(np.asarray(cell)), np.asarray(last.x), 1.2)
        assert set(map(tuple, in_range)) <= set(map(tuple, nb.pairs_of(kept)))
        return out

    plain = assert_last_good_state(stopped())
    built = simulate.list_for_kept_state
    first = lists[0].capacity

    def overflowing(spec, kept, *cell):  # the run's first capacities are too small for it
        out = built(spec, kept, *cell)
        if spec.capacity != first:
            return out
        return out._replace(overflow=jnp.asarray(nb.PAIR_OVERFLOW, jnp.int32),
                            count=jnp.asarray(spec.capacity + 1, jnp.int32))

    monkeypatch.setattr(simulate, "list_for_kept_state", overflowing)
    jax.clear_caches()  # the loop compiled with the patch, and only this test's
    try:
        refit = assert_last_good_state(stopped())
    finally:
        jax.clear_caches()
    assert refit.neighbors[0].capacity > first and refit.failed_step == plain.failed_step
    np.testing.assert_allclose(refit.states.x, plain.states.x, rtol=0,
                               atol=1e-12 * np.max(np.abs(plain.states.x)))
    np.testing.assert_allclose(refit.cells, plain.cells, rtol=1e-12)
