"""Non-holonomic rotationless motion: (40) Omega symmetric and (41) Omega_hat symmetric.

The trajectories come from the library's discrete Lagrange-d'Alembert integrator
(``integrators.INTEGRATORS["nonholonomic-rattle"]``); the references are the continuous
Lagrange-d'Alembert equations (``nonholonomic.lagrange_dalembert_field``) solved by scipy's DOP853,
and closed forms of the kinematics (Lie brackets, the Baker-Campbell-Hausdorff formula).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp

from affinebody import kinetic as kin
from affinebody import nonholonomic as nh
from affinebody import potentials as pot
from affinebody.groups import expm, project_algebra
from affinebody.integrators import INTEGRATORS, step_function
from affinebody.polar import polar
from affinebody.simulate import run
from affinebody.state import State
from affinebody.system import HamiltonianSystem
from tracking import energy_and_residual_tracker

J3 = jnp.asarray([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.5]])
POTENTIAL = pot.total_potential([pot.StVenantKirchhoff(0.3, 0.5), pot.Dilatation(1.0),
                                 pot.ExternalHarmonic(0.5)])
NHR = INTEGRATORS["nonholonomic-rattle"]


def make_system(internal, group="GL+", rotationless="spatial", potential=POTENTIAL):
    return HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0), internal),
                             potential, group, rotationless)


def random_state(seed, group="GL+", bodies=2, n=3):
    rng = np.random.default_rng(seed)
    algebra = "SL" if group in ("SL", "UL") else "GL"
    phi = expm(project_algebra(jnp.asarray(0.3 * rng.normal(size=(bodies, n, n))), algebra))
    return State(jnp.asarray(rng.normal(size=(bodies, n))), phi,
                 jnp.asarray(0.5 * rng.normal(size=(bodies, n))),
                 jnp.asarray(0.5 * rng.normal(size=(bodies, n, n))))


def tracker(system):
    """Jitted (state, dt, steps) -> (final, max |E - E0|, max constraint residual, (E0, E_end))
    of the non-holonomic RATTLE step."""
    return energy_and_residual_tracker(
        system, lambda s, dt: NHR.step(system, s, dt),
        lambda s: nh.residuals(system.kinetic, s, system.rotationless, system.group))


INTERNAL = {"dalembert": kin.DAlembert(J3), "af-is": kin.AffineIsotropic(2.0, 0.5, 0.3)}


@functools.cache
def case(internal, group, kind):
    """(system, tracker) for INTERNAL[internal] on ``group`` under the constraint ``kind``: one
    compiled tracker per system for the whole module (a non-holonomic RATTLE step takes seconds
    to compile; several tests integrate the same system)."""
    system = make_system(INTERNAL[internal], group, kind)
    return system, tracker(system)


def reference(system, state, t_end):
    """The continuous Lagrange-d'Alembert equations by DOP853 at rtol 1e-12."""
    flat, unravel = ravel_pytree(state)
    field = jax.jit(lambda z: ravel_pytree(nh.lagrange_dalembert_field(system, unravel(z)))[0])
    sol = solve_ivp(lambda t, z: np.asarray(field(jnp.asarray(z))), (0.0, t_end),
                    np.asarray(flat), method="DOP853", rtol=1e-12, atol=1e-12)
    return unravel(jnp.asarray(sol.y[:, -1]))


def max_abs(a: State, b: State) -> float:
    return float(jnp.max(jnp.abs(ravel_pytree(a)[0] - ravel_pytree(b)[0])))


# ------------------------------------------------------------------ dynamics

@pytest.mark.parametrize("internal, group, kind", [
    ("dalembert", "GL+", "spatial"),
    ("dalembert", "SL", "material"),
    ("af-is", "SL", "spatial"),
], ids=["dalembert-GL+-(40)", "dalembert-SL-(41)", "af-is-SL-(40)"])
def test_constraint_at_round_off_and_energy_bounded(internal, group, kind):
    system, evolve = case(internal, group, kind)
    state = system.check(random_state(1, group))
    assert float(nh.residuals(system.kinetic, state, kind, group)) < 1e-14
    mid, first_error, first_res, (e0, _) = evolve(state, 0.05, 150)
    final, later_error, later_res, (_, end) = evolve(mid, 0.05, 450)
    e0 = float(e0)
    assert max(float(first_res), float(later_res)) < 1e-13
    if group == "SL":
        assert float(jnp.max(jnp.abs(jnp.linalg.det(final.phi) - 1.0))) < 1e-13
    # ideal, time-independent constraints: energy is conserved; the scheme's error is bounded
    assert 1e-9 < float(first_error) / e0 < 1e-2
    drift = abs(float(end) - e0)
    assert drift < 3.0 * float(first_error)
    # time-reversible: a step back returns the state
    one = evolve(state, 0.05, 1)[0]
    assert max_abs(evolve(one, -0.05, 1)[0], state) < 1e-12


@pytest.mark.parametrize("internal, kind", [
    ("dalembert", "material"), ("af-is", "spatial"),
], ids=["dalembert-(41)", "af-is-(40)"])
def test_converges_at_order_two_to_the_continuous_lagrange_dalembert_motion(internal, kind):
    system, evolve = case(internal, "GL+", kind)
    state = system.check(random_state(2))
    t_end = 1.0
    exact = reference(system, state, t_end)
    # the reference itself keeps the constraint and the energy (ideal constraints)
    assert float(nh.residuals(system.kinetic, exact, kind)) < 1e-9
    assert abs(float(system.hamiltonian(exact) - system.hamiltonian(state))) < 1e-9
    errors = [max_abs(evolve(state, dt, int(round(t_end / dt)))[0], exact) for dt in (0.05, 0.025)]
    assert abs(np.log2(errors[0] / errors[1]) - 2.0) < 0.3, errors
    assert errors[1] < 3e-2  # |state| ~ 1


@pytest.mark.parametrize("kind", nh.ROTATIONLESS)
def test_energy_is_conserved_and_constraint_kept_by_the_continuous_equations(kind):
    """dH/dt = <grad H, f> = 0 and d/dt C(phi, v) = 0 at random admissible states."""
    cases = ((kin.DAlembert(J3), "SL"), (kin.AffineIsotropic(2.0, 0.5, 0.3), "GL+"))
    for internal, group in cases:
        system = make_system(internal, group, kind)
        state = system.check(random_state(3, group))
        f = nh.lagrange_dalembert_field(system, state)
        d_energy = jax.jvp(system.hamiltonian, (state,), (f,))[1]
        scale = float(jnp.max(jnp.abs(ravel_pytree(f)[0])))
        assert abs(float(d_energy)) < 1e-12 * scale

        def constraint(s, system=system, group=group):
            xi = system.kinetic.inverse_legendre(s).xi
            return nh.velocity_constraint(s.phi, xi, kind, group)

        assert float(jnp.max(jnp.abs(jax.jvp(constraint, (state,), (f,))[1]))) < 1e-12 * scale


def test_spatial_and_material_rotationless_motions_differ_from_the_same_initial_data():
    """phi0 = Id and a symmetric velocity are admissible for (40) and (41); the motions differ."""
    internal = INTERNAL["dalembert"]
    n = 3
    rng = np.random.default_rng(4)
    s0 = rng.normal(size=(2, n, n))  # two bodies (the shape the other tests compile for)
    xi0 = jnp.asarray(0.5 * (s0 + np.swapaxes(s0, -1, -2)))
    phi0 = jnp.stack([jnp.eye(n)] * 2)
    state = State(jnp.zeros((2, n)), phi0, jnp.zeros((2, n)), internal.legendre(phi0, xi0))
    finals = {}
    for kind in nh.ROTATIONLESS:
        system, evolve = case("dalembert", "GL+", kind)
        checked = system.check(state)
        assert max_abs(checked, state) < 1e-14  # admissible for both constraints
        finals[kind] = evolve(checked, 0.02, 100)[0]
    gap = float(jnp.max(jnp.abs(finals["spatial"].phi - finals["material"].phi)))
    assert gap > 1e-2  # O(h^2) integration error is ~1e-5 here
    # each motion violates the other constraint: the constraints are not equivalent
    spatial_v = internal.inverse_legendre(finals["spatial"].phi, finals["spatial"].pi)
    material_v = internal.inverse_legendre(finals["material"].phi, finals["material"].pi)
    assert float(jnp.max(jnp.abs(nh.velocity_constraint(finals["spatial"].phi, spatial_v,
                                                        "material")))) > 1e-2
    assert float(jnp.max(jnp.abs(nh.velocity_constraint(finals["material"].phi, material_v,
                                                        "spatial")))) > 1e-2


# ------------------------------------------------------------------ non-integrability

def test_admissible_fields_are_not_involutive():
    """[X_S1, X_S2] = [S2, S1] phi (40) and phi [S1, S2] (41): skew, hence not admissible."""
    rng = np.random.default_rng(5)
    phi = jnp.asarray(np.eye(3) + 0.3 * rng.normal(size=(3, 3)))
    a, b = rng.normal(size=(2, 3, 3))
    s1, s2 = jnp.asarray(a + a.T), jnp.asarray(b + b.T)
    for kind in nh.ROTATIONLESS:
        for s in (s1, s2):
            field = nh.admissible_field(phi, s, kind)
            assert float(jnp.max(jnp.abs(nh.velocity_constraint(phi, field, kind)))) < 1e-13
        bracket = nh.field_bracket(phi, s1, s2, kind)
        expected = (s2 @ s1 - s1 @ s2) @ phi if kind == "spatial" else phi @ (s1 @ s2 - s2 @ s1)
        np.testing.assert_allclose(bracket, expected, atol=1e-12)
        assert float(jnp.max(jnp.abs(nh.velocity_constraint(phi, bracket, kind)))) > 1.0


@pytest.mark.parametrize("kind", nh.ROTATIONLESS)
def test_a_closed_loop_of_admissible_motions_ends_in_a_net_rotation(kind):
    rng = np.random.default_rng(6)
    phi0 = jnp.asarray(np.eye(3) + 0.2 * rng.normal(size=(3, 3)))
    a, b = rng.normal(size=(2, 3, 3))
    angles = []
    for eps in (0.1, 0.05):
        s1, s2 = eps * jnp.asarray(a + a.T), eps * jnp.asarray(b + b.T)
        legs, phi_end, u = nh.rotationless_loop(phi0, s1, s2, kind)
        # every leg is admissible: a constant symmetric Omega (40) resp. Omega_hat (41)
        assert float(jnp.max(jnp.abs(legs - jnp.swapaxes(legs, -1, -2)))) < 1e-14
        # the loop closes in the deformation: G (40) or C (41) is back to its initial value
        if kind == "spatial":
            np.testing.assert_allclose(phi_end.T @ phi_end, phi0.T @ phi0, atol=1e-12)
            np.testing.assert_allclose(phi_end, u @ phi0, atol=1e-12)
        else:
            inv0, inv1 = jnp.linalg.inv(phi0), jnp.linalg.inv(phi_end)
            np.testing.assert_allclose(inv1.T @ inv1, inv0.T @ inv0, atol=1e-12)
            np.testing.assert_allclose(phi_end, phi0 @ u, atol=1e-12)
        # ... and ends in a net rotation, to leading order exp([s2, s1]) (40), exp([s1, s2]) (41)
        np.testing.assert_allclose(u.T @ u, np.eye(3), atol=1e-13)
        bracket = s2 @ s1 - s1 @ s2 if kind == "spatial" else s1 @ s2 - s2 @ s1
        generator = 0.5 * (u - u.T)  # = bracket + O(eps^3)
        assert float(jnp.max(jnp.abs(generator - bracket))) < 0.2 * float(
            jnp.max(jnp.abs(bracket)))
        angles.append(float(jnp.arccos(jnp.clip((jnp.trace(u) - 1) / 2, -1, 1))))
    assert angles[1] > 1e-3
    assert abs(np.log2(angles[0] / angles[1]) - 2.0) < 0.1, angles  # the angle is O(eps^2)
    # a holonomic constraint would close: the polar factor of phi0 would come back
    assert float(jnp.max(jnp.abs(polar(phi_end)[0] - polar(phi0)[0]))) > 1e-3


# ------------------------------------------------------------------ API and refusals

def test_run_driver_and_refusals():
    system = make_system(kin.AffineIsotropic(2.0, 0.5, 0.3), "GL+", "material")
    state = system.check(random_state(7, bodies=1))
    trajectory = run(system, state, 0.05, 6, "nonholonomic-rattle", every=3)
    assert trajectory.times[-1] == pytest.approx(0.3)
    final = jax.tree.map(jnp.asarray, trajectory.final_state)
    assert float(nh.residuals(system.kinetic, final, "material")) < 1e-13
    energy = trajectory.observables["energy"]
    assert 0 < abs(energy[-1] - energy[0]) < 1e-3 * abs(energy[0])
    with pytest.raises(ValueError, match="nonholonomic-rattle"):
        step_function(system, "strang")
    with pytest.raises(ValueError, match="nonholonomic-rattle"):
        run(system, state, 0.05, 2, "yoshida4")
    with pytest.raises(ValueError, match="rotationless"):
        step_function(make_system(kin.AffineIsotropic(2.0, 0.5), "GL+", None),
                      "nonholonomic-rattle")
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(J3))
    for group, message in (("SO", "leaves no motion"), ("O", "leaves no motion"),
                           ("R+SO", "only the dilatation"), ("R+O", "only the dilatation"),
                           ("L", "invertible")):
        with pytest.raises(ValueError, match=message):
            HamiltonianSystem(kinetic, None, group, rotationless="spatial")
    with pytest.raises(ValueError, match="'spatial' .* or 'material'"):
        HamiltonianSystem(kinetic, None, "GL+", rotationless="symmetric")
