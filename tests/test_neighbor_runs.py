"""Runs with a neighbour list (simulate.run(..., neighbors=...)): the list is carried through
the compiled loop, updated after every drift, reallocated after an overflow, and the motion is
the all-pairs motion to round-off: periodic 3D systems with the demo's affine pair potential
(cut-off on r), bodies that stretch under a cut-off on the affine distance D of eq. (75)
(the reach grows), a capacity too small for the run (reallocation), runs chained through
``trajectory.neighbors``, energy conservation unchanged, and the path a GPU runs (JAX kernels,
no host round trip) against the CPU's host kernels."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import kinetic as kin
from affinebody import neighbors as nb
from affinebody import pair_kernels as pk
from affinebody.potentials import (
    Cutoff,
    Dilatation,
    PairPotential,
    StVenantKirchhoff,
    total_potential,
)
from affinebody.simulate import energy_error, run
from affinebody.space import free_space, orthorhombic
from affinebody.state import State
from affinebody.system import HamiltonianSystem
from tracking import compilations

DEMO = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"
SIDE, SPACING, R_CUT, SKIN = 4, 1.3, 1.6, 0.2
BOX = orthorhombic((SIDE * SPACING,) * 3)
DT, STEPS, EVERY = 0.01, 200, 10
KINETIC = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(0.3 * jnp.eye(3)))


def periodic_system() -> tuple[HamiltonianSystem, State]:
    """64 bodies on a simple cubic lattice in a periodic box, thermal momenta; the demo pair
    potential plus one-body confinement of phi (the demo's model, with a d'Alembert drift).
    Rest distance 1.3: the 6 nearest neighbours are within r_cut + skin = 1.8, the 12 next
    ones (1.84) just outside, so the pair count grows as soon as the lattice melts a little."""
    pair = PairPotential.from_expression(DEMO, 3, cutoff=Cutoff(R_CUT), box=BOX)
    potential = total_potential([pair, Dilatation(5.0), StVenantKirchhoff(0.5, 1.0)])
    rng = np.random.default_rng(7)
    grid = np.stack(np.meshgrid(*[np.arange(SIDE)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = SPACING * grid + 0.01 * rng.normal(size=grid.shape)
    phi = np.eye(3) + 0.05 * rng.normal(size=(len(grid), 3, 3))
    p = 0.6 * rng.normal(size=x.shape)
    p -= p.mean(axis=0)
    state = State(jnp.asarray(x), jnp.asarray(phi), jnp.asarray(p),
                  jnp.asarray(0.05 * rng.normal(size=phi.shape)))
    return HamiltonianSystem(KINETIC, potential), state


@functools.cache
def all_pairs_run():
    system, state = periodic_system()
    return run(system, state, DT, STEPS, every=EVERY, observers=("energy", "potential_energy"))


def assert_same_motion(trajectory, reference, atol=1e-10):
    np.testing.assert_allclose(trajectory.times, reference.times, rtol=0, atol=1e-12)
    for a, b in zip(trajectory.states, reference.states, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=atol)
    for key, value in reference.observables.items():
        np.testing.assert_allclose(trajectory.observables[key], value, rtol=0,
                                   atol=atol * max(1.0, np.max(np.abs(value))))


def test_run_with_the_list_is_the_all_pairs_run_and_conserves_energy_as_well():
    system, state = periodic_system()
    reference = all_pairs_run()
    assert reference.neighbors is None and reference.neighbor_rebuilds == 0
    # two chained runs of 100 steps: the second continues with the first one's list
    # room for the pair count to grow as the lattice melts (no reallocation here)
    roomy = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN, capacity_factor=3.0)
    first = run(system, state, DT, STEPS // 2, every=EVERY,
                observers=("energy", "potential_energy"), neighbors=roomy)
    spec, _ = first.neighbors
    second = run(system, first.final_state, DT, STEPS // 2, every=EVERY,
                 observers=("energy", "potential_energy"), neighbors=first.neighbors)
    assert second.neighbors[0] == spec  # the same compiled loop, no reallocation
    assert first.neighbor_reallocations == second.neighbor_reallocations == 0
    assert first.neighbor_rebuilds >= 1 and second.neighbor_rebuilds >= 1
    # the list is a real saving: far fewer pairs than N(N-1)/2
    bodies = state.x.shape[0]
    assert int(second.neighbors[1].count) < bodies * (bodies - 1) // 8
    chained = type(first)(
        times=np.concatenate([first.times, second.times[1:] + first.times[-1]]),
        states=State(*(np.concatenate([a, b[1:]]) for a, b in
                       zip(first.states, second.states, strict=True))),
        observables={k: np.concatenate([first.observables[k], second.observables[k][1:]])
                     for k in first.observables},
    )
    assert_same_motion(chained, reference)
    # energy conservation: bounded Strang error, the same with and without the list
    error, error_ref = energy_error(chained), energy_error(reference)
    assert np.max(error) < 2e-3
    assert np.max(error) == pytest.approx(np.max(error_ref), rel=1e-6)
    assert np.max(np.abs(np.diff(reference.observables["potential_energy"]))) > 0.1  # real motion


def count_force_passes(monkeypatch) -> dict:
    """Counts the host pair kernel's passes with gradients (one per force evaluation)."""
    passes = {"gradients": 0}
    fused = pk._host_fused

    def counted(g, source, gradients, virial, *args, **kwargs):
        passes["gradients"] += bool(gradients)
        return fused(g, source, gradients, virial, *args, **kwargs)

    monkeypatch.setattr(pk, "_host_fused", counted)
    return passes


def test_a_capacity_too_small_for_the_run_is_reallocated_transparently(monkeypatch):
    """... and the run compiles its loop once per list: the steps after a reallocation run
    through the program of the run's length, so a run that goes on with the list it returned
    (as ``affinebody run``'s next chunk does) compiles nothing."""
    system, state = periodic_system()
    probe_spec, probe = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN)
    assert int(probe.count) == 3 * state.x.shape[0]  # nearest neighbours only, at the start
    # exactly the pairs of the start: the list overflows once the lattice melts
    tight = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN, capacity=int(probe.count),
                        cell_capacity=probe_spec.cell_capacity)
    passes = count_force_passes(monkeypatch)
    with compilations("_simulate") as compiled:
        trajectory = run(system, state, DT, STEPS, every=EVERY,
                         observers=("energy", "potential_energy"), neighbors=tight)
        assert trajectory.stop is None
        reallocations = trajectory.neighbor_reallocations
        assert reallocations >= 1
        if pk.host_kernel_in_use():
            # one force pass per step, each call's initial forces, and per reallocation at
            # most the frame whose step overflowed: the frames after it in that call are
            # not computed (they had been: 453 passes here, against 223)
            assert passes["gradients"] <= STEPS + (1 + reallocations) + EVERY * reallocations
        assert len(compiled) <= 1 + trajectory.neighbor_reallocations  # one per list
        more = run(system, trajectory.final_state, DT, STEPS, every=EVERY,
                   observers=("energy", "potential_energy"), neighbors=trajectory.neighbors)
    assert more.neighbor_reallocations == 0
    assert len(compiled) <= 1 + trajectory.neighbor_reallocations  # nothing new
    spec, last = trajectory.neighbors
    assert spec.capacity > int(probe.count) and int(last.overflow) == 0
    assert int(last.count) > int(probe.count)  # more pairs in range than at the start
    assert_same_motion(trajectory, all_pairs_run())


def refuse_to_reallocate(*args, **kwargs):
    raise nb.NeighborListOverflow("no room for this list (test)")


def test_a_list_that_cannot_be_reallocated_stops_the_run_and_keeps_its_frames(monkeypatch):
    """The one overflow policy (``simulate.ListRestarts``, also barostat.run's: see
    tests/test_npt_neighbors.py): where the list cannot be reallocated the run stops at the
    step that overflowed, says why and what to do, and keeps every frame before it (those of
    the all-pairs run) and the last good state, as for any other stop."""
    from affinebody import simulate

    system, state = periodic_system()
    probe_spec, probe = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN)
    # room for the pairs of the first ~150 steps (the lattice melts): it overflows mid-run
    tight = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN,
                        capacity=int(probe.count) + 200, cell_capacity=probe_spec.cell_capacity)
    monkeypatch.setattr(nb, "reallocate", refuse_to_reallocate)
    trajectory = run(system, state, DT, STEPS, every=EVERY,
                     observers=("energy", "potential_energy"), neighbors=tight,
                     on_stop="return")
    stop = trajectory.stop
    assert stop is not None and stop.reason == "neighbour list overflow"
    assert stop.body == -1  # no one body's stop
    assert "no room for this list (test)" in stop.message
    assert stop.message.endswith(simulate.OVERFLOW_FIX)
    assert trajectory.neighbor_reallocations == 0
    reference = all_pairs_run()
    nominal = np.isin(np.round(trajectory.times / DT), np.round(reference.times / DT))
    frames = int(nominal.sum())
    assert 5 <= frames < len(reference.times)  # it ran, and stopped before the end
    assert np.all(trajectory.times[:frames] < stop.step * DT)
    assert trajectory.times[-1] == pytest.approx((stop.step - 1) * DT)  # the last good state
    cut = lambda a: a[:frames]  # noqa: E731
    assert_same_motion(type(trajectory)(cut(trajectory.times), jax.tree.map(cut, trajectory.states),
                                        {k: cut(v) for k, v in trajectory.observables.items()}),
                       type(reference)(cut(reference.times), jax.tree.map(cut, reference.states),
                                       {k: cut(v) for k, v in reference.observables.items()}))
    with pytest.raises(simulate.IntegrationStopped, match="could not be reallocated"):
        run(system, state, DT, STEPS, every=EVERY, observers=("energy", "potential_energy"),
            neighbors=tight)


def test_a_stop_after_a_rebuild_keeps_a_list_and_observables_of_the_last_good_state():
    """The loop does not hold the previous list back with the previous state (that cost two
    copies of the list per step): a step that fails has already replaced the list with one
    for its own discarded state. With no skin every step rebuilds, so the failing one did;
    the frame that holds the last good state (in the middle of a chunk) must still have its
    observables of that state, all pairs, and the run must return a list valid for it."""
    system, state = periodic_system()
    stopped = stop_after_a_rebuild(system, state)
    assert_a_list_and_observables_of_the_last_good_state(system, stopped)


#: Frame intervals of :func:`stop_after_a_rebuild`, the first that puts its failing step
#: inside a chunk (not first in it) taken.
FRAME_INTERVALS = (4, 5, 8)  # divisors of the 40 steps


def stop_after_a_rebuild(system, state):
    """A run whose step fails (dt too large: det phi of a body crosses 0 near step 28; which
    step depends on rounding), with frames every few steps such that the last good state is
    held by the failing chunk's own frame."""
    every_step = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", 0.0, capacity_factor=3.0)
    dt = 0.15

    def stopped_run(every):
        return run(system, state, dt, 40, every=every, observers=("energy", "potential_energy"),
                   neighbors=every_step, on_stop="return")

    step = stopped_run(40).stop.step  # the step that fails does not depend on the frames
    every = next(e for e in FRAME_INTERVALS if step % e != 1)
    stopped = stopped_run(every)
    assert stopped.stop.step == step
    return stopped, every


def assert_a_list_and_observables_of_the_last_good_state(system, stopped_every, dt=0.15):
    stopped, every = stopped_every
    step = stopped.stop.step
    assert stopped.neighbor_rebuilds == step - 1  # every kept step rebuilt, the failed one too
    assert step % every != 1  # the last good state is held by the failing chunk's own frame
    assert stopped.times[-1] == pytest.approx((step - 1) * dt)
    last = jax.tree.map(lambda a: jnp.asarray(a[-1]), stopped.states)
    assert stopped.observables["energy"][-1] == pytest.approx(
        float(system.hamiltonian(last)), rel=1e-12)  # all pairs, no list
    spec, kept = stopped.neighbors
    assert int(kept.overflow) == 0 and not bool(nb.needs_rebuild(spec, kept, last.x, last.phi))
    assert float(system.potential_energy(last, kept)) == pytest.approx(
        float(system.potential_energy(last)), rel=1e-12)


def test_a_list_for_the_kept_state_that_overflows_is_reallocated_by_run(monkeypatch):
    """Where the list built in the loop for the state a failed step keeps does not fit the
    run's capacities (here made to overflow), ``run`` reallocates it and computes that
    frame's observables again: still those of the last good state, with a list valid for
    it."""
    from affinebody import simulate

    system, state = periodic_system()
    built = simulate.list_for_kept_state
    overflowed = lambda spec, kept: built(spec, kept)._replace(  # noqa: E731
        overflow=jnp.asarray(nb.PAIR_OVERFLOW, jnp.int32), count=jnp.asarray(0, jnp.int32))
    monkeypatch.setattr(simulate, "list_for_kept_state", overflowed)
    jax.clear_caches()  # the loop compiled with the patch, and only this test's
    try:
        stopped = stop_after_a_rebuild(system, state)
    finally:
        jax.clear_caches()
    assert_a_list_and_observables_of_the_last_good_state(system, stopped)


def test_stretching_bodies_with_an_affine_cut_off_rebuild_and_match_all_pairs():
    # free space, cut-off on D: the reach D_cut max_K s_max(phi_K) grows as the bodies stretch
    # (d'Alembert internal motion, phi(t) ~ phi_0 + t xi, xi = stretching along random axes)
    # (a soft affine pair term in M1 and D, weak enough for the stretching to stay moderate)
    d_cut, skin, steps = 1.5, 0.3, 150
    potential = PairPotential.from_expression(
        "0.05*exp(-D**2/4)*(M1 - 3)**2 + 0.2*exp(-2*r**2)", 3, cutoff=Cutoff(d_cut, variable="D"))
    system = HamiltonianSystem(KINETIC, potential)
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = 1.1 * grid + 0.02 * rng.normal(size=grid.shape)
    axes = np.linalg.qr(rng.normal(size=(len(grid), 3, 3)))[0]
    xi = axes @ np.diag([0.4, 0.1, -0.2]) @ np.swapaxes(axes, -1, -2)
    phi = np.eye(3) + 0.02 * rng.normal(size=(len(grid), 3, 3))
    pi = np.swapaxes(0.3 * xi, -1, -2)  # pi = J xi^T
    state = State(jnp.asarray(x), jnp.asarray(phi), jnp.zeros_like(jnp.asarray(x)),
                  jnp.asarray(pi))
    reference = run(system, state, DT, steps, every=EVERY)
    # room for the reach to grow without outgrowing the cells: rebuilds only
    roomy = nb.allocate(free_space(), state.x, state.phi, d_cut, "D", skin, reach_headroom=1.5,
                        capacity_factor=4.0)
    stretched = run(system, state, DT, steps, every=EVERY, neighbors=roomy)
    reach0 = float(roomy[1].reach)
    reach1 = float(nb.spatial_reach(d_cut, "D", jnp.asarray(stretched.final_state.phi)))
    # a list stays valid for a reach growth of at most the skin: >= 2 rebuilds were needed
    assert reach1 - reach0 > 2 * skin
    assert stretched.neighbor_reallocations == 0 and stretched.neighbor_rebuilds >= 2
    assert_same_motion(stretched, reference)


def test_neighbour_lists_refuse_what_they_cannot_serve():
    system, state = periodic_system()
    with pytest.raises(ValueError, match="splitting integrators"):
        run(system, state, DT, 10, integrator="implicit-midpoint", neighbor_skin=SKIN)
    no_cut = HamiltonianSystem(KINETIC, PairPotential.from_expression("exp(-r**2)", 3))
    with pytest.raises(ValueError, match="needs a cut-off"):
        run(no_cut, state, DT, 10, neighbor_skin=SKIN)
    with pytest.raises(ValueError, match="not both"):
        run(system, state, DT, 10, neighbor_skin=SKIN,
            neighbors=nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN))
    other = nb.allocate(BOX, state.x, state.phi, 1.0, "r", SKIN)  # a cut-off too short
    with pytest.raises(ValueError, match="does not fit"):
        run(system, state, DT, 10, neighbors=other)


def test_the_accelerator_path_gives_the_host_kernels_motion(monkeypatch):
    """What a GPU runs (the JAX pair kernel and list build, the exact af-is drift in JAX, tiny
    matrix products written elementwise: no host round trip in the loop) is the motion the CPU
    host kernels give (the fused Numba pair kernel, list build and drift), to round-off: the
    same run of the periodic system with an af-is drift, once each way. The JAX kernel's
    passes over pairs run as XLA programs, or as the GPU's Triton kernels (in Pallas'
    interpreter: inside the compiled loop, its list rebuilds and the gradient's custom rule)."""
    import jax

    from affinebody import _host, _linalg, pair_kernels

    system, state = periodic_system()
    system = system.replace(kinetic=kin.KineticEnergy(
        kin.DAlembertTranslational(1.0), kin.AffineIsotropic(0.3, 0.05, 0.02)))
    monkeypatch.setattr(kin, "HOST_DRIFT_MIN_BODIES", 1)  # 64 bodies take the host drift too
    calls = []
    host_callback = _host.callback
    monkeypatch.setattr(_host, "callback", lambda f, *a, **k: calls.append(f) or host_callback(
        f, *a, **k))
    lists = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", SKIN, capacity_factor=3.0)
    observers = ("energy", "potential_energy")
    host = run(system, state, DT, 60, every=EVERY, observers=observers, neighbors=lists)
    assert len(calls) >= 3  # pair kernel, list build, drift: traced into the loop
    # the accelerator path on this CPU, compiled afresh (the jit caches key on neither switch)
    monkeypatch.setattr(_host, "in_use", lambda: False)
    monkeypatch.setattr(pair_kernels, "_host_in_use", lambda: False)
    monkeypatch.setattr(_linalg, "fused_products", lambda: True)
    for program in ("xla", "triton-interpret"):
        monkeypatch.setattr(pair_kernels, "pair_program", lambda *args, p=program: p)
        jax.clear_caches()
        calls.clear()
        try:
            accelerator = run(system, state, DT, 60, every=EVERY, observers=observers,
                              neighbors=lists)
        finally:
            jax.clear_caches()  # nothing compiled with the switches flipped outlives this test
        assert calls == []
        assert host.neighbor_rebuilds >= 1
        assert accelerator.neighbor_rebuilds == host.neighbor_rebuilds
        assert_same_motion(accelerator, host, atol=1e-11)
    assert np.max(np.abs(np.asarray(host.final_state.phi - state.phi))) > 1e-2  # real motion


def test_a_sweep_sample_that_stops_after_a_rebuild_ends_as_the_all_pairs_sample(monkeypatch):
    """A sweep sample (``sweep.follow``, the run driver's step in a while loop) does not hold
    the previous list back either: the sample that fails right after a rebuild (no skin) gets
    a list for the state it keeps, so its final energy is the all-pairs sample's; and where
    that list does not fit (made to overflow here) the sample reports an overflow, which its
    caller answers by repeating it with a reallocated list."""
    import jax

    from affinebody import simulate, sweep
    from affinebody.integrators import get_integrator

    system, state = periodic_system()
    spec, every_step = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", 0.0,
                                   capacity_factor=3.0)
    # dt far too large: a body leaves GL+ at step 5 (at smaller dt the motion first turns
    # chaotic, and the list's round-off and all pairs' part ways before the stop)
    follow = jax.jit(lambda listed: sweep.follow(
        system, state, 0.2, 1e6, steps=40, method=get_integrator("strang"), watch_det=True,
        spec=spec if listed is not None else None, neighbors=listed))
    listed, all_pairs = follow(every_step), follow(None)
    assert int(all_pairs["code"]) == int(simulate.Stop.LEFT_GROUP)
    for key in ("code", "steps_done"):
        assert int(listed[key]) == int(all_pairs[key])
    assert float(listed["final_energy"]) == pytest.approx(float(all_pairs["final_energy"]),
                                                          rel=1e-10)
    built = simulate.list_for_kept_state
    monkeypatch.setattr(simulate, "list_for_kept_state",
                        lambda s, kept, *cell: built(s, kept, *cell)._replace(
                            overflow=jnp.asarray(nb.PAIR_OVERFLOW, jnp.int32)))
    refit = jax.jit(lambda listed: sweep.follow(
        system, state, 0.2, 1e6, steps=40, method=get_integrator("strang"), watch_det=True,
        spec=spec, neighbors=listed))(every_step)
    assert int(refit["code"]) == int(simulate.Stop.OVERFLOW)
    assert int(refit["overflow"]) == nb.PAIR_OVERFLOW


def test_a_thermal_sample_that_stops_after_a_rebuild_sums_what_the_all_pairs_sample_sums():
    """A thermostatted NVT sample (``sweep.thermal_sample``) does not hold the previous list
    back either: once a step failed the sample's measurements are no longer counted, so
    nothing reads the discarded step's list. With no skin every step rebuilds; the sample that
    leaves GL+ at step 11 (dt far too large) counts the same measurements, with the same sums,
    as the all-pairs sample (the same thermostat noise)."""
    import jax

    from affinebody import simulate, sweep
    from affinebody.integrators import get_integrator
    from affinebody.thermostats import Langevin

    system, state = periodic_system()
    spec, every_step = nb.allocate(BOX, state.x, state.phi, R_CUT, "r", 0.0,
                                   capacity_factor=3.0)
    sample = jax.jit(lambda listed: sweep.thermal_sample(
        system, state, 0.1, np.uint32(3), 0.5, steps=40, every=4, equilibration=0,
        method=get_integrator("strang"), thermostat=Langevin(0.5, 1.0, 0), watch_det=True,
        spec=spec if listed is not None else None, neighbors=listed))
    listed, all_pairs = sample(every_step), sample(None)
    assert int(all_pairs["code"]) == int(simulate.Stop.LEFT_GROUP)
    assert int(all_pairs["steps_done"]) == 10 and int(all_pairs["measurements"]) == 2
    for key in ("code", "steps_done", "measurements"):
        assert int(listed[key]) == int(all_pairs[key])
    sums, reference = np.asarray(listed["sums"]), np.asarray(all_pairs["sums"])
    finite = np.isfinite(reference)  # no box pressure without a space: nan in both
    np.testing.assert_array_equal(np.isfinite(sums), finite)
    np.testing.assert_allclose(sums[finite], reference[finite], rtol=1e-10, atol=1e-10)
