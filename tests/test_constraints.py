"""Holonomic constraints: bodies on SL, UL, SO, O, R+SO, R+O under every kinetic model.

Every check integrates with the library's splitting integrators (``integrators``), whose drifts
on a subgroup come from ``affinebody.constraints`` (exact flows, Lie-group splittings, RATTLE).
Long runs are one jitted ``lax.fori_loop`` on tiny systems.
"""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax
from scipy.integrate import solve_ivp

from affinebody import constraints
from affinebody import kinetic as kin
from affinebody import potentials as pot
from affinebody.groups import expm, is_member, project_algebra
from affinebody.integrators import INTEGRATORS
from affinebody.state import State
from affinebody.system import HamiltonianSystem
from tracking import energy_and_residual_tracker

J3 = jnp.asarray([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.5]])
ELASTIC = pot.total_potential([pot.StVenantKirchhoff(0.3, 0.5), pot.ExternalHarmonic(0.5)])
NEGATIVE_COMPONENT = ("UL", "O", "R+O")  # start these with det phi < 0


@dataclass(frozen=True)
class Orientation:
    """V = k sum_K phi_K[2, 2] + x^2/2: a heavy-top-like field that depends on the rotation."""

    k: float = 0.8

    def energy(self, x, phi):
        return self.k * jnp.sum(phi[..., 2, 2], axis=-1) + 0.5 * jnp.sum(x * x, axis=(-2, -1))


def group_state(seed, group, bodies=2, n=3, spread=0.3, momentum=0.5):
    rng = np.random.default_rng(seed)
    phi = expm(project_algebra(jnp.asarray(spread * rng.normal(size=(bodies, n, n))), group))
    if group in NEGATIVE_COMPONENT:
        phi = phi.at[..., :, 0].multiply(-1.0)
    return State(jnp.asarray(rng.normal(size=(bodies, n))), phi,
                 jnp.asarray(momentum * rng.normal(size=(bodies, n))),
                 jnp.asarray(momentum * rng.normal(size=(bodies, n, n))))


def make_system(internal, group, potential=ELASTIC):
    return HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0), internal),
                             potential, group)


def tracker(system, integrator="strang"):
    """Jitted (state, dt, steps) -> (final, max |E - E0|, max constraint residual, (E0, E_end))
    of ``integrator`` (the energies at both ends from the compiled graph too: the same H
    evaluated eagerly, op by op, costs more than the compilation)."""
    method = INTEGRATORS[integrator]
    return energy_and_residual_tracker(
        system, lambda s, dt: method.step(system, s, dt),
        lambda s: jnp.max(jnp.abs(constraints.constraint_residual(s.phi, system.group))))


def stepper(system, integrator="strang"):
    """Jitted (state, dt, steps) -> final state: ``tracker`` without the per-step energy and
    residual (a smaller graph to compile, for tests that only compare final states)."""
    method = INTEGRATORS[integrator]

    @jax.jit
    def evolve(state, dt, steps):
        return lax.fori_loop(0, steps, lambda _, s: method.step(system, s, dt), state)

    return evolve


def in_algebra_defect(state, group) -> float:
    sigma_hat = state.pi @ state.phi
    return float(jnp.max(jnp.abs(sigma_hat - project_algebra(sigma_hat, group))))


# ------------------------------------------------------------------ exact flows keep the group

@pytest.mark.parametrize("group, internal", [
    ("SL", kin.IsotropicAffine(2.0, 0.5, 0.3)),
    ("UL", kin.AffineAffine(1.3, 0.4)),
    ("SO", kin.AffineAffine(-1.3, 0.4)),
    ("O", kin.IsotropicAffine(2.0, 0.5, 0.3)),
    ("R+SO", kin.IsotropicAffine(1.5, -0.5, 0.7)),
    ("R+O", kin.AffineIsotropic(2.0, 0.5, 0.3)),
])
def test_algebra_preserving_exact_flows_stay_on_every_subgroup(group, internal):
    """is-af, af-af, af-is map g into g: their exact drifts + projected kicks stay on G."""
    system = make_system(internal, group)
    assert all(constraints.drift_mode(t) == "exact"
               for t in (system.kinetic.translational, internal))
    state = system.check(group_state(1, group))
    final, energy_error, residual, (e0, _) = tracker(system)(state, 0.02, 1000)
    assert float(residual) < 1e-12  # round-off accumulated over 1000 products of expm
    assert bool(jnp.all(is_member(final.phi, group, tol=1e-12)))
    np.testing.assert_array_equal(np.sign(np.linalg.det(final.phi)),
                                  np.sign(np.linalg.det(state.phi)))  # component kept
    assert in_algebra_defect(final, group) < 1e-12
    assert float(energy_error) / abs(float(e0)) < 1e-3


# ------------------------------------------------------------------ RATTLE and Lie-group drifts

@pytest.mark.parametrize("group, internal", [
    ("SL", kin.DAlembert(J3)),
    ("UL", kin.DAlembert(J3)),
    ("O", kin.DAlembert(J3)),
    ("R+SO", kin.DAlembert(J3)),
    ("R+O", kin.DAlembert(J3)),
    ("SL", kin.AffineJ(J3)),
    ("UL", kin.HAffine(J3)),
    ("R+SO", kin.HAffine(J3)),
], ids=lambda v: v if isinstance(v, str) else type(v).__name__)
def test_constrained_drift_residual_round_off_energy_bounded_order_two(group, internal):
    """d'Alembert (RATTLE) and af-J / H-af (Lie-group splitting) on every subgroup."""
    system = make_system(internal, group)
    expected = "rattle" if isinstance(internal, kin.DAlembert) else "lie-group"
    assert constraints.drift_mode(internal) == expected
    state = system.check(group_state(2, group))
    evolve = tracker(system)
    mid, first_error, residual_first, (start, _) = evolve(state, 0.04, 500)
    final, later_error, residual_later, (_, end) = evolve(mid, 0.04, 1000)
    e0 = abs(float(start))
    # the constraint holds to round-off at every step (RATTLE solves it to round-off each
    # step; the splitting multiplies 2 dim(g) - 1 exponentials per step, whose round-off adds
    # up over the 1500 steps); the component of phi is kept
    tolerance = 2e-14 if expected == "rattle" else 1e-12
    assert max(float(residual_first), float(residual_later)) < tolerance
    np.testing.assert_array_equal(np.sign(np.linalg.det(final.phi)),
                                  np.sign(np.linalg.det(state.phi)))
    # bounded energy error: the later 1000 steps stay in the band of the first 500 ...
    drift = abs(float(end) - float(start))
    assert 1e-9 < float(first_error) / e0 < 1e-2
    assert drift < 3.0 * float(first_error) + 1e-12
    # ... and it converges at order 2 (a wrong restricted Hamiltonian would not converge)
    coarse, fine = (float(evolve(state, dt, int(round(4.0 / dt)))[1]) for dt in (0.04, 0.02))
    assert abs(np.log2(coarse / fine) - 2.0) < 0.35, (coarse, fine)


def canonical(state: State) -> jax.Array:
    """(q, P) in canonical coordinates: (x, phi[i,a]) and (p, pi^T[i,a])."""
    return jnp.concatenate([state.x.ravel(), state.phi.ravel(), state.p.ravel(),
                            jnp.swapaxes(state.pi, -1, -2).ravel()])


@pytest.mark.parametrize("group, internal", [
    ("SL", kin.DAlembert(J3)), ("SO", kin.AffineJ(J3)),
], ids=lambda v: v if isinstance(v, str) else type(v).__name__)
def test_step_map_is_symplectic_on_the_constrained_phase_space(group, internal):
    """omega(M u, M w) = omega(u, w) for tangent vectors u, w of T*G (Frobenius representatives).

    Chart of T*G at z: phi exp(sum a_k E_k), Sigma_hat + sum b_k E_k (E_k a basis of g), x + dx,
    p + dp. The canonical 2-form restricted to these states is the symplectic form of T*G.
    """
    system = make_system(internal, group, Orientation())
    state = system.check(group_state(3, group, bodies=1))
    basis = constraints.algebra_basis(group, 3)
    d = basis.shape[0]
    sigma_hat = state.pi @ state.phi

    def chart(c):
        a, b, dx, dp = c[:d], c[d:2 * d], c[2 * d:2 * d + 3], c[2 * d + 3:]
        phi = state.phi @ expm(jnp.einsum("k,kij->ij", a, basis))
        pi = (sigma_hat + jnp.einsum("k,kij->ij", b, basis)) @ jnp.linalg.inv(phi)
        return State(state.x + dx, phi, state.p + dp, pi)

    step = INTEGRATORS["strang"]
    zero = jnp.zeros(2 * d + 6)

    @jax.jit
    def columns(tangent):
        """One column of each Jacobian (chart, and step after chart) at c = 0, and the step of
        chart(0) = state: one compilation, evaluated per basis vector (a jvp, which jacfwd
        would vmap over the while_loop of RATTLE's Newton solve: a larger graph)."""
        def both(c):
            start = chart(c)
            return start, step.step(system, start, 0.1)

        (_, out), (d_start, d_out) = jax.jvp(both, (zero,), (tangent,))
        return canonical(d_start), canonical(d_out), out

    cols = [columns(e) for e in jnp.eye(zero.size)]
    before = jnp.stack([c[0] for c in cols], axis=-1)
    after = jnp.stack([c[1] for c in cols], axis=-1)
    dim = before.shape[0] // 2
    zeros, eye = jnp.zeros((dim, dim)), jnp.eye(dim)
    omega = jnp.block([[zeros, eye], [-eye, zeros]])
    form_before = before.T @ omega @ before
    form_after = after.T @ omega @ after
    assert float(jnp.min(jnp.abs(jnp.linalg.eigvalsh(form_before @ form_before.T)))) > 1e-3
    assert float(jnp.max(jnp.abs(form_after - form_before))) < 1e-11
    # the map leaves the manifold of Frobenius representatives on G (to round-off)
    out = cols[0][2]  # the step of chart(0), i.e. of state (to round-off)
    assert in_algebra_defect(out, group) < 1e-13


# ------------------------------------------------------------------ the rigid limit

def hat(w):
    return jnp.asarray([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def vee(a):
    return np.asarray([a[2, 1], a[0, 2], a[1, 0]])


def euler_reference(rotation0, omega_body0, inertia, t_end):
    """Euler's equations dM/dt = M x w, dR/dt = R hat(w), w = I^-1 M, by DOP853 at 1e-13."""
    inverse = np.linalg.inv(inertia)

    def field(_, y):
        r, m = y[:9].reshape(3, 3), y[9:]
        w = inverse @ m
        return np.concatenate([(r @ np.asarray(hat(w))).ravel(), np.cross(m, w)])

    y0 = np.concatenate([np.asarray(rotation0).ravel(), inertia @ omega_body0])
    y = solve_ivp(field, (0.0, t_end), y0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    return y[:9].reshape(3, 3), inverse @ y[9:]


def test_rigid_limit_equals_euler_equations_with_inertia_tr_j_minus_j():
    """d'Alembert J on SO(3) (RATTLE) and af-J J on SO(3) (Lie-group splitting) are the rigid body
    with inertia tensor Tr(J) Id - J (from the second moment J of (8)): Euler's equations."""
    rng = np.random.default_rng(7)
    rotation0 = expm(hat(jnp.asarray(rng.normal(size=3))))
    omega_body0 = np.asarray([0.7, -1.1, 0.4])
    inertia = float(jnp.trace(J3)) * np.eye(3) - np.asarray(J3)
    t_end = 2.0
    ref_rotation, ref_omega = euler_reference(rotation0, omega_body0, inertia, t_end)
    for internal in (kin.DAlembert(J3), kin.AffineJ(J3)):
        system = make_system(internal, "SO", None)
        xi0 = rotation0 @ hat(jnp.asarray(omega_body0))
        state = system.check(State(jnp.zeros((1, 3)), rotation0[None], jnp.zeros((1, 3)),
                                   internal.legendre(rotation0[None], xi0[None])))
        # the velocity of the lifted momentum, compiled once per model (eagerly, the metric
        # lift's solve is hundreds of one-op compilations)
        velocity = jax.jit(lambda s, kinetic=system.kinetic: kinetic.inverse_legendre(
            constraints.metric_lift(kinetic.hamiltonian, s, "SO")).xi[0])
        errors = {}
        for name, dts in (("strang", (0.02, 0.01)), ("yoshida4", (0.1, 0.05))):
            evolve = stepper(system, name)
            for dt in dts:
                final = evolve(state, dt, int(round(t_end / dt)))
                omega = vee(np.asarray(final.phi[0].T @ velocity(final)))
                errors[name, dt] = max(float(np.max(np.abs(final.phi[0] - ref_rotation))),
                                       float(np.max(np.abs(omega - ref_omega))))
        label = type(internal).__name__
        assert errors["strang", 0.01] < 2e-4, (label, errors)
        assert abs(np.log2(errors["strang", 0.02] / errors["strang", 0.01]) - 2) < 0.3, errors
        # RATTLE and the splitting are symmetric on T*SO(3): Yoshida's composition is order 4
        assert abs(np.log2(errors["yoshida4", 0.1] / errors["yoshida4", 0.05]) - 4) < 0.5, errors


def test_is_af_and_af_is_on_rotations_are_the_spherical_body_with_moment_i_minus_a():
    """(73), (74) restricted to SO(3) coincide with d'Alembert's J = (I - A) Id (paper, after (74)).

    Checked as equal restricted Hamiltonians on T*SO(3) and as equal motions in a rotation-
    dependent potential, the three systems integrated by different schemes (exact flows vs RATTLE).
    """
    i, a, b = 2.0, 0.6, 0.3
    models = {"is-af": kin.IsotropicAffine(i, a, b), "af-is": kin.AffineIsotropic(i, a, b),
              "dalembert": kin.DAlembert((i - a) * jnp.eye(3))}
    systems = {k: make_system(m, "SO", Orientation()) for k, m in models.items()}
    states = [systems["dalembert"].check(group_state(s, "SO", bodies=2)) for s in (4, 5, 6)]
    # the restricted T of each system, compiled once (three states of one shape) instead of
    # eagerly (its metric lift is hundreds of one-op compilations)
    kinetic_energies = {k: jax.jit(s.kinetic_energy) for k, s in systems.items()}
    for state in states:
        energies = [float(t(state)) for t in kinetic_energies.values()]
        np.testing.assert_allclose(energies, energies[0], rtol=1e-13)
    # a wrong moment is detected: I + A instead of I - A
    wrong = make_system(kin.DAlembert((i + a) * jnp.eye(3)), "SO", Orientation())
    assert abs(float(jax.jit(wrong.kinetic_energy)(states[0])) / energies[0] - 1) > 0.1
    finals = {}
    evolves = {key: stepper(system) for key, system in systems.items()}
    for dt in (0.02, 0.01):
        for key in systems:
            finals[key, dt] = evolves[key](states[0], dt, int(round(2.0 / dt))).phi
    for key in ("is-af", "af-is"):
        gaps = [float(jnp.max(jnp.abs(finals[key, dt] - finals["dalembert", dt])))
                for dt in (0.02, 0.01)]
        assert gaps[1] < 1e-3 and gaps[1] < 0.4 * gaps[0], (key, gaps)


# ------------------------------------------------------------------ API and refusals

def test_bases_and_residuals_of_every_subgroup():
    for group, dim in (("SL", 8), ("UL", 8), ("SO", 3), ("O", 3), ("R+SO", 4), ("R+O", 4)):
        basis, complement = (constraints.algebra_basis(group, 3),
                             constraints.complement_basis(group, 3))
        assert basis.shape[0] == dim and complement.shape[0] == 9 - dim
        everything = jnp.concatenate([basis, complement]).reshape(9, 9)
        np.testing.assert_allclose(everything @ everything.T, np.eye(9), atol=1e-14)
        np.testing.assert_allclose(project_algebra(basis, group), basis, atol=1e-14)
        phi = group_state(8, group).phi
        assert float(jnp.max(jnp.abs(constraints.constraint_residual(phi, group)))) < 1e-14
        assert constraints.constraint_residual(phi, group).shape[-1] == 9 - dim
        off = constraints.constraint_residual(phi @ (jnp.eye(3) + 0.01 * complement[0]), group)
        assert float(jnp.max(jnp.abs(off))) > 1e-3


def test_every_internal_model_has_a_constrained_drift_and_unknown_terms_are_probed():
    tensor = jnp.eye(9).reshape(3, 3, 3, 3)
    models = (kin.DAlembert(J3), kin.AffineJ(J3), kin.HAffine(J3), kin.LeftInvariant(tensor),
              kin.RightInvariant(tensor), kin.AffineAffine(1.0), kin.IsotropicAffine(2.0, 0.5),
              kin.AffineIsotropic(2.0, 0.5))
    assert {type(m) for m in models} == set(kin.MODELS.values())
    modes = [constraints.drift_mode(m) for m in models]
    assert modes == ["rattle"] + ["lie-group"] * 4 + ["exact"] * 3

    @dataclass(frozen=True)
    class Odd:  # flows straight in L(n): neither invariant nor d'Alembert
        def hamiltonian(self, phi, pi):
            return 0.5 * jnp.sum(pi * pi, axis=(-2, -1))

        def flow(self, state, h):
            return state._replace(phi=state.phi + h * jnp.swapaxes(state.pi, -1, -2))

    system = HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0), Odd()),
                               None, "SL")
    with pytest.raises(ValueError, match="no constrained drift"):
        system.check(group_state(1, "SL", n=2))
