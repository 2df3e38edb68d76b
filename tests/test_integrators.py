"""Integrators: exact geodesics, conservation laws, convergence order, symplecticity, groups.

Long runs (10^4 and 10^5 steps) are one jitted ``lax.fori_loop`` each on tiny systems.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp

from affinebody import kinetic as kin
from affinebody import observables as obs
from affinebody import potentials as pot
from affinebody.groups import expm, is_member, project_algebra
from affinebody.integrators import INTEGRATORS, get_integrator
from affinebody.simulate import IntegrationStopped, run
from affinebody.state import State
from affinebody.system import HamiltonianSystem

RNG = np.random.default_rng(2024)


def random_state(seed, bodies=2, n=2, spread=0.3, momentum=0.5, group="GL+"):
    rng = np.random.default_rng(seed)
    a = spread * rng.normal(size=(bodies, n, n))
    if group in ("SL", "SO", "R+SO"):
        phi = expm(project_algebra(jnp.asarray(a), group))
    else:
        phi = jnp.asarray(np.eye(n) + a)
    return State(
        x=jnp.asarray(rng.normal(size=(bodies, n))),
        phi=phi,
        p=jnp.asarray(momentum * rng.normal(size=(bodies, n))),
        pi=jnp.asarray(momentum * rng.normal(size=(bodies, n, n))),
    )


def tracker(system, integrator, quantities=()):
    """Jitted (state, dt, steps) -> (final state, max|E - E0|, max |q - q0| per quantity, E0).

    E0 comes from the compiled graph (an eager constrained H, op by op, costs seconds)."""
    method = get_integrator(integrator)

    @jax.jit
    def evolve(state, dt, steps):
        e0 = system.hamiltonian(state)
        q0 = [q(state) for q in quantities]

        def body(_, carry):
            s, emax, qmax = carry
            s = method.step(system, s, dt)
            emax = jnp.maximum(emax, jnp.abs(system.hamiltonian(s) - e0))
            qmax = [jnp.maximum(m, jnp.max(jnp.abs(q(s) - a)))
                    for m, q, a in zip(qmax, quantities, q0, strict=True)]
            return s, emax, qmax

        init = (state, jnp.zeros(()), [jnp.zeros(()) for _ in quantities])
        return *lax.fori_loop(0, steps, body, init), e0

    return evolve


def reference_solution(system, state, t_end):
    """Hamilton's equations by autodiff, integrated by scipy's DOP853 at rtol 1e-13."""
    flat, unravel = ravel_pytree(state)
    field = jax.jit(lambda z: ravel_pytree(system.vector_field(unravel(z)))[0])
    sol = solve_ivp(lambda t, z: np.asarray(field(jnp.asarray(z))), (0.0, t_end),
                    np.asarray(flat), method="DOP853", rtol=1e-13, atol=1e-13)
    return unravel(jnp.asarray(sol.y[:, -1]))


def max_rel(a: State, b: State) -> float:
    fa, _ = ravel_pytree(a)
    fb, _ = ravel_pytree(b)
    return float(jnp.max(jnp.abs(fa - fb)) / jnp.max(jnp.abs(fb)))


# ------------------------------------------------------------------ exact geodesics

GEODESIC_MODELS = {
    "af-is (left-invariant)": kin.AffineIsotropic(I=2.0, A=0.6, B=0.4),
    "is-af (right-invariant)": kin.IsotropicAffine(I=1.5, A=-0.5, B=0.7),
    "af-af (both)": kin.AffineAffine(A=1.3, B=0.4),
}


@pytest.mark.parametrize("name", list(GEODESIC_MODELS))
def test_free_body_follows_exact_geodesic_at_any_step_size(name):
    """One step of size T, or 7 steps, equal the DOP853 solution of Hamilton's equations."""
    system = HamiltonianSystem(
        kin.KineticEnergy(kin.DAlembertTranslational(1.7), GEODESIC_MODELS[name]))
    state = random_state(5, bodies=1, n=3, spread=0.2, momentum=0.4)
    t_end = 2.5
    reference = reference_solution(system, state, t_end)
    strang = get_integrator("strang")
    big = jax.jit(lambda s, h: strang.step(system, s, h))
    one_step = big(state, t_end)
    seven = state
    for _ in range(7):
        seven = big(seven, t_end / 7)
    assert max_rel(one_step, reference) < 1e-10
    assert max_rel(seven, one_step) < 1e-12


# ------------------------------------------------------------------ conservation laws

def affine_system():
    """Spatially affine: af-is kinetic terms, binary potential of D (75) and M_a (30)."""
    affine_pair = pot.PairPotential(
        lambda D, M1, M2: 0.3 * (D - 1.0) ** 2 + 0.5 * (M1 - 2.0) ** 2 + 0.2 * (M2 - 2.0) ** 2,
        ("D", "M1", "M2"))
    kinetic = kin.KineticEnergy(kin.AffineTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    return HamiltonianSystem(kinetic, affine_pair)


def euclidean_system():
    """Spatially Euclidean: d'Alembert translation, is-af internal, potential of r and K_a."""
    pair = pot.PairPotential(lambda r, K1, K2: 0.5 * (r - 1.0) ** 2 + 0.1 * (K1 - 2.0) ** 2
                             + 0.05 * (K2 - 2.0) ** 2, ("r", "K1", "K2"))
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                kin.IsotropicAffine(2.0, 0.5, 0.3))
    return HamiltonianSystem(kinetic, pot.total_potential([pair, pot.Dilatation(1.0)]))


def material_system():
    """Materially isotropic: is-af internal energy, elastic + dilatation + M_a potentials."""
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                kin.IsotropicAffine(2.0, 0.5, 0.3))
    potential = pot.total_potential([pot.HarmonicInvariants(0.7), pot.StVenantKirchhoff(0.3, 0.5),
                                     pot.Dilatation(1.0)])
    return HamiltonianSystem(kinetic, potential)


@pytest.mark.parametrize(
    "make_system, quantities",
    [
        (affine_system, (obs.linear_momentum, obs.affine_momentum)),
        (euclidean_system, (obs.linear_momentum, obs.angular_momentum)),
        (material_system, (obs.linear_momentum, obs.vorticity)),
    ],
    ids=["affine: p and J", "euclidean: p and J - J^T", "material: p and vorticity"],
)
def test_momentum_maps_conserved_to_round_off_over_1e4_steps(make_system, quantities):
    system = make_system()
    state = random_state(11, bodies=2, n=2, spread=0.25, momentum=0.6)
    # yoshida4: conservation holds for every composition of exact sub-flows
    evolve = tracker(system, "yoshida4", quantities)
    # dt = 0.002: a purely affine system has no confinement of the volumes (the paper's
    # point about (78)-(81)); by t = 200 both bodies collapse to det phi ~ 1e-12, and the
    # terms of J grow far beyond J itself, so we stop at t = 20
    dt = 0.002 if make_system is affine_system else 0.02
    final, energy_error, deviations, _ = evolve(state, dt, 10_000)
    assert bool(jnp.all(jnp.isfinite(final.phi)))
    for q, deviation in zip(quantities, deviations, strict=True):
        scale = float(jnp.max(jnp.abs(q(state))))
        assert scale > 0.1, q.__name__
        assert float(deviation) / scale < 1e-11, (q.__name__, float(deviation) / scale)
    # ... while the energy, not a momentum map, is only conserved to O(dt^4)
    assert 1e-15 < float(energy_error) < 1e-4


def test_energy_error_bounded_over_1e5_steps():
    """Strang, dt = 0.05, 10^5 steps (t = 5000): the error oscillates, it does not drift."""
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    potential = pot.total_potential([
        pot.Dilatation(2.0), pot.StVenantKirchhoff(0.5, 1.0),
        pot.ExternalHarmonic(1.0), pot.HarmonicInvariants(0.5),
    ])
    system = HamiltonianSystem(kinetic, potential)
    state = random_state(3, bodies=2, n=2, spread=0.2, momentum=0.5)
    evolve = tracker(system, "strang")
    e0 = float(system.hamiltonian(state))
    mid, err_first, _, _ = evolve(state, 0.05, 10_000)
    final, err_rest, _, _ = evolve(mid, 0.05, 90_000)
    drift_rest = abs(float(system.hamiltonian(final)) - e0)
    err_first, err_rest = float(err_first) / e0, float(err_rest) / e0
    assert 1e-6 < err_first < 1e-2
    # the last 9 x 10^4 steps stay within a small multiple of the first 10^4 steps' band
    assert err_rest < 3.0 * err_first
    assert drift_rest / e0 < 3.0 * err_first


def order_system():
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    potential = pot.total_potential([pot.Dilatation(1.0), pot.StVenantKirchhoff(0.3, 0.5),
                                     pot.ExternalHarmonic(0.5)])
    return HamiltonianSystem(kinetic, potential)


#: Step sizes in each registered integrator's asymptotic range on order_system (a new integrator
#: must add its own here: the contract below runs over the whole registry).
STEP_SIZES = {
    "strang": (0.1, 0.05, 0.025),
    "yoshida4": (0.1, 0.05, 0.025),
    "suzuki4": (0.2, 0.1, 0.05),
    "yoshida6": (0.2, 0.1, 0.05),
    "implicit-midpoint": (0.1, 0.05, 0.025),
    "nonholonomic-rattle": None,  # rotationless systems only: tests/test_nonholonomic.py
}


@pytest.mark.parametrize("name", list(INTEGRATORS))
def test_energy_error_converges_at_the_declared_order(name):
    """Contract over integrators.INTEGRATORS: the energy error of each integrator that accepts
    the system converges at the order it declares; one that does not accept it refuses it in
    one line before computing anything."""
    method = INTEGRATORS[name]
    system = order_system()
    dts = STEP_SIZES[name]
    if dts is None:
        with pytest.raises(ValueError) as refused:
            method.check(system)
        assert "\n" not in str(refused.value) and name in str(refused.value)
        return
    method.check(system)
    state = random_state(4, bodies=2, n=2, spread=0.2, momentum=0.5)
    evolve = tracker(system, name)
    t_end = 4.0
    errors = [float(evolve(state, dt, int(round(t_end / dt)))[1]) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert min(errors) > 1e-13, errors  # round-off must not dominate
    assert abs(slope - method.order) < 0.3, (slope, errors)


def test_integrators_are_time_reversible_and_symplectic():
    system = order_system()
    state = random_state(6, bodies=1, n=2, spread=0.2, momentum=0.5)
    for name in ("strang", "implicit-midpoint"):
        method = INTEGRATORS[name]
        step = lambda s, h, method=method: method.step(system, s, h)
        back = jax.jit(lambda s, step=step: step(step(s, 0.1), -0.1))(state)
        assert max_rel(back, state) < 1e-12, name
        # compositions of symplectic maps (yoshida4/6, suzuki4) are symplectic as well
        assert symplecticity_defect(lambda s, step=step: step(s, 0.1), state) < 1e-11, name


def canonical_coordinates(state: State):
    """(q, P) with q_k, P_k conjugate: (x, phi[i,a]) and (p, pi[a,i]) = (p, pi^T[i,a])."""
    q = jnp.concatenate([state.x.ravel(), state.phi.ravel()])
    p = jnp.concatenate([state.p.ravel(), jnp.swapaxes(state.pi, -1, -2).ravel()])
    return jnp.concatenate([q, p])


def from_canonical(z, like: State) -> State:
    nx, nphi = like.x.size, like.phi.size
    x, phi = z[:nx].reshape(like.x.shape), z[nx:nx + nphi].reshape(like.phi.shape)
    p = z[nx + nphi:2 * nx + nphi].reshape(like.p.shape)
    pi_t = z[2 * nx + nphi:].reshape(like.pi.shape)
    return State(x, phi, p, jnp.swapaxes(pi_t, -1, -2))


def symplecticity_defect(step_map, state) -> float:
    """max |M^T Omega M - Omega| for the Jacobian M of the one-step map in canonical coordinates.

    M column by column from one compiled jvp (jacfwd would vmap the same jvp, which batches the
    while_loop of an implicit step into a larger graph to compile).
    """
    z0 = canonical_coordinates(state)
    f = lambda z: canonical_coordinates(step_map(from_canonical(z, state)))
    column = jax.jit(lambda v: jax.jvp(f, (z0,), (v,))[1])
    m = jnp.stack([column(e) for e in jnp.eye(z0.size)], axis=-1)
    d = z0.size // 2
    omega = jnp.block([[jnp.zeros((d, d)), jnp.eye(d)], [-jnp.eye(d), jnp.zeros((d, d))]])
    return float(jnp.max(jnp.abs(m.T @ omega @ m - omega)))


def test_implicit_midpoint_on_a_model_without_exact_splitting():
    """af-J (anisotropic J) has no exact drift: implicit midpoint is symplectic and order 2."""
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                kin.AffineJ(jnp.asarray([[2.0, 0.3], [0.3, 1.0]])))
    system = HamiltonianSystem(kinetic, pot.total_potential([pot.Dilatation(1.0),
                                                            pot.StVenantKirchhoff(0.3, 0.5)]))
    state = random_state(8, bodies=1, n=2, spread=0.2, momentum=0.4)
    method = INTEGRATORS["implicit-midpoint"]
    assert symplecticity_defect(lambda s: method.step(system, s, 0.05), state) < 1e-10
    evolve = tracker(system, "implicit-midpoint")
    errors = [float(evolve(state, dt, int(round(2.0 / dt)))[1]) for dt in (0.04, 0.02)]
    assert abs(np.log2(errors[0] / errors[1]) - 2.0) < 0.3, errors


# ------------------------------------------------------------------ constrained groups

@pytest.mark.parametrize("group", ["SL", "SO", "R+SO"])
def test_constrained_motion_stays_on_the_group_to_round_off(group):
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineIsotropic(2.0, 0.5, 0.3))
    potential = pot.total_potential([pot.StVenantKirchhoff(0.3, 0.5), pot.HarmonicInvariants(0.1),
                                     pot.ExternalHarmonic(0.5)])
    system = HamiltonianSystem(kinetic, potential, group=group)
    state = system.check(random_state(9, bodies=2, n=3, spread=0.3, momentum=0.5, group=group))
    evolve = tracker(system, "strang", (obs.linear_momentum,))
    final, energy_error, _, e0 = evolve(state, 0.02, 10_000)
    assert bool(jnp.all(is_member(final.phi, group, tol=1e-12)))
    if group == "SL":
        assert float(jnp.max(jnp.abs(jnp.linalg.det(final.phi) - 1.0))) < 1e-12
    sigma_hat = final.pi @ final.phi
    assert float(jnp.max(jnp.abs(sigma_hat - project_algebra(sigma_hat, group)))) < 1e-12
    # the constrained dynamics is Hamiltonian: bounded energy error, converging at order 2
    # (projected kicks + subgroup drifts; a wrong momentum projection would not converge)
    assert float(energy_error) / float(e0) < 1e-3
    coarse, fine = (float(evolve(state, dt, int(round(10.0 / dt)))[1]) for dt in (0.04, 0.02))
    assert abs(np.log2(coarse / fine) - 2.0) < 0.3, (coarse, fine)


def test_group_and_model_mismatch_is_refused():
    dalembert = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(jnp.eye(2)))
    anisotropic = kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                    kin.AffineJ(jnp.asarray([[2.0, 0.3], [0.3, 1.0]])))
    # d'Alembert on SL (RATTLE) and anisotropic af-J on SO (Lie-group splitting) are accepted;
    # tests/test_constraints.py checks their motion.
    HamiltonianSystem(dalembert, None, group="SL").check(random_state(1, bodies=1, n=2, group="SL"))
    HamiltonianSystem(anisotropic, None, group="SO").check(
        random_state(1, bodies=1, n=2, group="SO"))
    with pytest.raises(ValueError, match="not in SL"):
        HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                            kin.AffineAffine(1.0)), None, group="SL").check(
            random_state(1, bodies=1, n=2))
    with pytest.raises(ValueError, match="implicit-midpoint"):
        run(HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                                kin.AffineAffine(1.0)), None, group="SL"),
            random_state(1, bodies=1, n=2, group="SL"), 0.1, 2, "implicit-midpoint")
    with pytest.raises(ValueError, match="system.group"):
        HamiltonianSystem(dalembert, None, group="GL-")


# ------------------------------------------------------------------ leaving GL+

def dalembert_crossing_state():
    """Body 1 has det(phi0 + t xi0) = (1 - t/1.05)(1 - t/2): it reaches det phi = 0 at t = 1.05."""
    phi = jnp.stack([jnp.eye(2), jnp.eye(2)])
    xi = jnp.stack([0.1 * jnp.eye(2), -jnp.diag(jnp.asarray([1 / 1.05, 0.5]))])
    return State(jnp.zeros((2, 2)), phi, jnp.zeros((2, 2)), jnp.swapaxes(xi, -1, -2))


def test_unconfined_dalembert_leaves_gl_plus_and_the_run_stops():
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(jnp.eye(2)))
    state = dalembert_crossing_state()
    with pytest.raises(IntegrationStopped) as info:
        run(HamiltonianSystem(kinetic), state, 0.1, 20, every=5)
    report = info.value.report
    assert (report.step, report.body) == (11, 1)
    assert "body 1 left GL+(n): det phi crossed 0 at step 11" in str(info.value)
    assert 'group = "L"' in str(info.value)
    frames = info.value.trajectory
    assert frames.times[-1] == pytest.approx(1.0)
    assert float(np.linalg.det(frames.final_state.phi[1])) > 0
    # on L(n, R) the motion continues through det phi = 0: det is the polynomial in t
    trajectory = run(HamiltonianSystem(kinetic, group="L"), state, 0.1, 15, every=5,
                     observers=("volumes",))
    t = trajectory.times
    expected = (1 - t / 1.05) * (1 - t / 2)
    np.testing.assert_allclose(trajectory.observables["volumes"][:, 1], expected, atol=1e-14)
    assert trajectory.observables["volumes"][-1, 1] < 0


def test_non_finite_state_stops_with_step_body_and_reason():
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(jnp.eye(2)))
    state = State(jnp.zeros((2, 2)), jnp.stack([jnp.eye(2)] * 2),
                  jnp.asarray([[0.0, 0.0], [1.0, 0.0]]), jnp.zeros((2, 2, 2)))
    # sqrt(1 - x_1) has no real value beyond x_1 = 1: body 1 gets there near t = 1
    singular = pot.OneBodyPotential(lambda x1: 1e-3 * jnp.sqrt(1.0 - x1), ("x1",))
    with pytest.raises(IntegrationStopped) as info:
        run(HamiltonianSystem(kinetic, singular), state, 0.1, 40)
    report = info.value.report
    assert report.body == 1 and 10 <= report.step <= 11
    assert "potential too stiff or singular" in report.reason
    # a stiff but regular potential with a too large step: the other diagnosis
    stiff = pot.ExternalHarmonic(1e4)
    with pytest.raises(IntegrationStopped) as info:
        run(HamiltonianSystem(kinetic, stiff), state, 0.05, 2000)
    assert "time step too large" in info.value.report.reason


def test_run_frames_match_manual_steps_and_observers():
    system = order_system()
    state = random_state(12, bodies=2, n=2)
    trajectory = run(system, state, 0.05, 12, "yoshida4", every=4,
                     observers={"E": "energy", "spin": obs.affine_spin})
    method = INTEGRATORS["yoshida4"]
    step = jax.jit(lambda s: method.step(system, s, 0.05))
    manual = state
    for _ in range(8):
        manual = step(manual)
    frame = jax.tree.map(lambda a: a[2], trajectory.states)
    assert max_rel(frame, manual) < 1e-13
    np.testing.assert_allclose(trajectory.times, [0.0, 0.2, 0.4, 0.6], atol=1e-15)
    np.testing.assert_allclose(trajectory.observables["spin"][2], obs.affine_spin(manual),
                               rtol=1e-12)
    np.testing.assert_allclose(trajectory.observables["E"][2], system.hamiltonian(manual),
                               rtol=1e-13)
    with pytest.raises(ValueError, match="every"):
        run(system, state, 0.05, 12, every=5)


def test_carrying_the_forces_from_step_to_step_gives_the_same_steps():
    """Splitting.advance reuses the last kick's forces for the next step's first kick ("first
    same as last"): the same steps as recomputing them in every step, to round-off (the two
    are compiled differently, so the last bit may differ)."""
    from affinebody.integrators import YOSHIDA4

    system, state = _fsal_system()
    step = jax.jit(lambda s: YOSHIDA4.step(system, s, 0.01))
    advance = jax.jit(lambda s, f: YOSHIDA4.advance(system, s, f, 0.01))
    recomputed = jax.jit(system.forces)  # compiled once: eager, its first call costs more
    reference = state
    for _ in range(5):
        reference = step(reference)
    carried, forces = state, recomputed(state)
    for _ in range(5):
        carried, _, forces = advance(carried, forces)
    assert np.max(np.abs(np.asarray(carried.pi - state.pi))) > 1e-3  # the forces acted
    for a, b in zip(carried, reference, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)
    for a, b in zip(forces, recomputed(carried), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("name", ["strang", "yoshida4"])
def test_a_force_pass_with_more_gives_the_same_step_and_its_last_extra(name):
    """Splitting.advance(force_pass=f): f's forces drive the step as system.forces' do (one
    stage for Strang, a scan over stages for Yoshida), and the extra returned is that of the
    last evaluation, at the new configuration (a barostat takes its virial from it)."""
    system, state = _fsal_system()
    method = get_integrator(name)
    potential = jax.jit(system.potential_energy)

    def force_pass(system, s, neighbors):
        return system.forces(s, neighbors), (system.potential_energy(s), s.x[0])

    plain = jax.jit(lambda s, f: method.advance(system, s, f, 0.01))
    more = jax.jit(lambda s, f: method.advance(system, s, f, 0.01, force_pass=force_pass))
    forces = jax.jit(system.forces)(state)
    new, _, new_forces = plain(state, forces)
    same, tracked, same_forces, (energy, x0) = more(state, forces)
    assert tracked is None
    for a, b in zip((*same, *same_forces), (*new, *new_forces), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)
    assert np.max(np.abs(np.asarray(new.x - state.x))) > 1e-4  # the step moved the bodies
    np.testing.assert_allclose(float(energy), float(potential(new)), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(x0), np.asarray(new.x[0]), rtol=1e-13)


def _fsal_system():
    from affinebody.kinetic import AffineIsotropic, DAlembertTranslational, KineticEnergy
    from affinebody.potentials import Dilatation, PairPotential, total_potential
    from affinebody.system import HamiltonianSystem

    rng = np.random.default_rng(4)
    kinetic = KineticEnergy(DAlembertTranslational(mass=1.0),
                            AffineIsotropic(I=1.0, A=0.2, B=0.1))
    potential = total_potential([
        PairPotential.from_expression("exp(-D**2) * (M1 - 2)**2 + exp(-r)", n=2),
        Dilatation(stiffness=3.0),
    ])
    system = HamiltonianSystem(kinetic, potential, group="GL+")
    state = State(x=rng.normal(size=(4, 2)), phi=np.eye(2) + 0.1 * rng.normal(size=(4, 2, 2)),
                  p=0.3 * rng.normal(size=(4, 2)), pi=0.3 * rng.normal(size=(4, 2, 2)))
    return system, system.check(state)
