"""Velocities, momenta and the action of the affine groups on them: paper eqs. (34)-(49)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import actions, momenta, velocities
from affinebody.state import State, VelocityState
from strategies import SAMPLED_GROUPS, assert_close, dims, matrices, square_matrices, vectors

FAST = settings(max_examples=12, deadline=None)

_T = lambda a: np.swapaxes(np.asarray(a), -1, -2)
_inv = np.linalg.inv


def _tr(a):
    return np.trace(np.asarray(a), axis1=-2, axis2=-1)


def _skew(a):
    return 0.5 * (a - np.swapaxes(a, -1, -2))


def _sym(a):
    return 0.5 * (a + np.swapaxes(a, -1, -2))


def _tangent_at_zero(curve):
    """d/dt curve(t) at t = 0 by forward-mode autodiff."""
    return jax.jvp(curve, (0.0,), (1.0,))[1]


def _cayley(x):
    """Cayley map (Id - X/2)^-1 (Id + X/2): equals exp(X) to second order, maps so(n) into
    SO(n), and compiles much faster than expm; only tangents at t = 0 are used here."""
    ident = jnp.eye(x.shape[-1])
    return jnp.linalg.solve(ident - 0.5 * x, ident + 0.5 * x)


#: xi of the curves t -> phi0 cay(t W) (material) and t -> cay(t W) phi0 (spatial).
_xi_material = jax.jit(lambda phi0, w: _tangent_at_zero(lambda t: phi0 @ _cayley(t * w)))
_xi_spatial = jax.jit(lambda phi0, w: _tangent_at_zero(lambda t: _cayley(t * w) @ phi0))


# ------------------------------------------------------------------------ velocities (34)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_affine_velocities_34_from_one_parameter_curves(group, data):
    n = data.draw(dims)
    phi0 = data.draw(matrices(group, n))
    w = data.draw(square_matrices(n, bound=1.0))
    xi = _xi_material(phi0, w)
    assert_close(velocities.comoving_affine_velocity(phi0, xi), w, 1e-9)  # Omega_hat = W
    assert_close(velocities.spatial_affine_velocity(phi0, xi), phi0 @ w @ _inv(phi0), 1e-9)
    xi = _xi_spatial(phi0, w)
    assert_close(velocities.spatial_affine_velocity(phi0, xi), w, 1e-9)  # Omega = W
    assert_close(velocities.comoving_affine_velocity(phi0, xi), _inv(phi0) @ w @ phi0, 1e-9)


@FAST
@given(st.data())
def test_transformation_rules_35_36_38(data):
    n = data.draw(dims)
    phi, a, b = (data.draw(matrices("GL", n)) for _ in range(3))
    xi = data.draw(square_matrices(n))
    x, v, shift = (data.draw(vectors(n)) for _ in range(3))
    omega = velocities.spatial_affine_velocity(phi, xi)
    omega_hat = velocities.comoving_affine_velocity(phi, xi)
    v_hat = velocities.comoving_velocity(phi, v)
    assert_close(v_hat, np.linalg.solve(phi, v[..., None])[..., 0], 1e-10)  # (38)

    spatial = actions.transform_velocity_state(VelocityState(x, phi, v, xi), A=a, b=shift)
    # (35): L_A: Omega -> A Omega A^-1, Omega_hat unchanged; v_hat unchanged as well.
    assert_close(velocities.spatial_affine_velocity(spatial.phi, spatial.xi),
                 a @ omega @ _inv(a), 1e-9)
    assert_close(velocities.comoving_affine_velocity(spatial.phi, spatial.xi), omega_hat, 1e-9)
    assert_close(velocities.comoving_velocity(spatial.phi, spatial.v), v_hat, 1e-9)

    material = actions.transform_velocity_state(VelocityState(x, phi, v, xi), B=b)
    # (36): R_B: Omega unchanged, Omega_hat -> B^-1 Omega_hat B; v_hat -> B^-1 v_hat.
    assert_close(velocities.spatial_affine_velocity(material.phi, material.xi), omega, 1e-9)
    assert_close(velocities.comoving_affine_velocity(material.phi, material.xi),
                 _inv(b) @ omega_hat @ b, 1e-9)
    assert_close(velocities.comoving_velocity(material.phi, material.v),
                 np.einsum("...ij,...j->...i", _inv(b), v_hat), 1e-9)


@FAST
@given(st.sampled_from(("SO", "O")), st.data())
def test_rigid_motion_has_skew_affine_velocities_37_39(group, data):
    n = data.draw(dims)
    rot = data.draw(matrices(group, n))
    w = _skew(data.draw(square_matrices(n)))
    xi = _xi_material(rot, w)  # t -> R cay(t w) stays in O(n)
    omega = np.asarray(velocities.spatial_affine_velocity(rot, xi))
    omega_hat = np.asarray(velocities.comoving_affine_velocity(rot, xi))
    assert_close(velocities.gyroscopic_residual(rot, xi), 0.0, atol=1e-10)  # (39)
    assert_close(omega, -_T(omega), 1e-10)  # (37)
    assert_close(omega_hat, -_T(omega_hat), 1e-10)
    # Rigid motion is rotational: (40) holds only where omega = 0.
    assert_close(velocities.spatial_rotationless_residual(rot, xi), 2 * omega, 1e-10)


@FAST
@given(st.data())
def test_rotationless_constraints_40_41(data):
    n = data.draw(dims)
    phi0 = data.draw(matrices("GL", n))
    s = _sym(data.draw(square_matrices(n)))
    xi = _xi_spatial(phi0, s)  # Omega = S symmetric: purely deformative
    assert_close(velocities.spatial_rotationless_residual(phi0, xi), 0.0, atol=1e-9)  # (40)
    omega_hat = _inv(phi0) @ s @ phi0
    assert_close(velocities.material_rotationless_residual(phi0, xi),
                 omega_hat - _T(omega_hat), 1e-9)
    xi = _xi_material(phi0, s)  # Omega_hat = S symmetric: materially rotationless
    assert_close(velocities.material_rotationless_residual(phi0, xi), 0.0, atol=1e-9)  # (41)


def test_spatially_and_materially_rotationless_are_not_equivalent():
    phi = np.array([[1.0, 1.0], [0.0, 1.0]])
    xi = np.diag([1.0, -1.0]) @ phi  # Omega = diag(1, -1), Omega_hat = [[1, 2], [0, -1]]
    assert_close(velocities.spatial_rotationless_residual(phi, xi), 0.0, atol=1e-15)
    assert_close(velocities.material_rotationless_residual(phi, xi), [[0, 2], [-2, 0]], 1e-14)


# --------------------------------------------------------------------- momenta (42)-(49)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_pairings_42_44_46(group, data):
    n = data.draw(dims)
    phi = data.draw(matrices(group, n))
    xi, pi = data.draw(square_matrices(n)), data.draw(square_matrices(n))
    p, v = data.draw(vectors(n)), data.draw(vectors(n))
    assert_close(momenta.translational_pairing(p, v), np.sum(p * v, axis=-1), 1e-12)
    assert_close(momenta.translational_pairing(p, v), _tr(p[..., :, None] * v[..., None, :]))
    # (43), (44): p_hat = phi^T p, p^T v = p_hat^T v_hat
    p_hat = momenta.comoving_momentum(phi, p)
    assert_close(p_hat, np.einsum("...ji,...j->...i", phi, p), 1e-12)
    v_hat = velocities.comoving_velocity(phi, v)
    assert_close(momenta.translational_pairing(p_hat, v_hat), np.sum(p * v, axis=-1), 1e-9)
    # (45), (46)
    sigma, sigma_hat = momenta.affine_spin(phi, pi), momenta.comoving_affine_spin(phi, pi)
    assert_close(sigma, phi @ pi, 1e-12)
    assert_close(sigma_hat, pi @ phi, 1e-12)
    omega = velocities.spatial_affine_velocity(phi, xi)
    omega_hat = velocities.comoving_affine_velocity(phi, xi)
    pairing = _tr(pi @ xi)
    assert_close(momenta.internal_pairing(pi, xi), pairing, 1e-12)
    assert_close(_tr(sigma @ omega), pairing, 1e-9)
    assert_close(_tr(sigma_hat @ omega_hat), pairing, 1e-9)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_momentum_from_affine_spin_inverts_45(group, data):
    n = data.draw(dims)
    phi = data.draw(matrices(group, n))
    pi, sigma = data.draw(square_matrices(n)), data.draw(square_matrices(n))
    assert_close(momenta.momentum_from_affine_spin(phi, momenta.affine_spin(phi, pi)), pi, 1e-9)
    assert_close(
        momenta.momentum_from_comoving_affine_spin(phi, momenta.comoving_affine_spin(phi, pi)),
        pi, 1e-9,
    )
    assert_close(momenta.affine_spin(phi, momenta.momentum_from_affine_spin(phi, sigma)),
                 sigma, 1e-9)
    assert_close(
        momenta.comoving_affine_spin(phi, momenta.momentum_from_comoving_affine_spin(phi, sigma)),
        sigma, 1e-9,
    )


def _test_function(phi, weights):
    return jnp.sum(jnp.sin(phi) * weights) + jnp.linalg.det(phi) ** 2


#: pi = (df/dphi)^T in the transposed placement of docs/theory/conventions.md.
_momentum_of = jax.jit(lambda phi, weights: jax.grad(_test_function)(phi, weights).T)
_along_spatial = jax.jit(
    lambda phi, z, w: _tangent_at_zero(lambda t: _test_function(_cayley(t * z) @ phi, w))
)
_along_material = jax.jit(
    lambda phi, z, w: _tangent_at_zero(lambda t: _test_function(phi @ _cayley(t * z), w))
)


@FAST
@given(st.data())
def test_affine_spins_generate_left_and_right_translations_45_49(data):
    """With pi = (df/dphi)^T: d/dt f(cay(tZ) phi) = Tr(Sigma Z), d/dt f(phi cay(tZ)) =
    Tr(Sigma_hat Z); for skew Z these are Tr(S Z)/2 and Tr(V Z)/2 (49)."""
    n = data.draw(dims)
    phi = data.draw(matrices("GL", n, batch=()))
    z, weights = data.draw(square_matrices(n, batch=())), data.draw(square_matrices(n, batch=()))
    pi = np.asarray(_momentum_of(phi, weights))
    sigma, sigma_hat = momenta.affine_spin(phi, pi), momenta.comoving_affine_spin(phi, pi)
    assert_close(_along_spatial(phi, z, weights), _tr(sigma @ z), 1e-9)
    assert_close(_along_material(phi, z, weights), _tr(sigma_hat @ z), 1e-9)
    spin, vorticity = np.asarray(momenta.spin(sigma)), np.asarray(momenta.vorticity(sigma_hat))
    assert_close(spin, -_T(spin), 0.0)
    assert_close(vorticity, -_T(vorticity), 0.0)
    assert_close(spin, sigma - _T(sigma), 0.0)
    w = _skew(z)
    assert_close(_along_spatial(phi, w, weights), 0.5 * _tr(spin @ w), 1e-9)
    assert_close(_along_material(phi, w, weights), 0.5 * _tr(vorticity @ w), 1e-9)


# ------------------------------------------------------------------------------ actions


def _states(data, n, bodies=2):
    batch = (bodies,)
    x, p, v = (data.draw(vectors(n, batch)) for _ in range(3))
    phi = data.draw(matrices("GL", n, batch))
    xi, pi = data.draw(square_matrices(n, batch)), data.draw(square_matrices(n, batch))
    return State(x, phi, p, pi), VelocityState(x, phi, v, xi)


@FAST
@given(st.booleans(), st.data())
def test_actions_preserve_pairings_42_and_give_47_48(per_body, data):
    n = data.draw(dims)
    state, vstate = _states(data, n)
    batch = (2,) if per_body else ()
    a, b = data.draw(matrices("GL", n, batch)), data.draw(matrices("GL", n, batch))
    shift = data.draw(vectors(n, batch))
    new, vnew = actions.transform_state(state, a, b, shift), actions.transform_velocity_state(
        vstate, a, b, shift
    )
    assert_close(new.x, vnew.x, 0.0)
    assert_close(new.phi, vnew.phi, 0.0)
    assert_close(new.phi, a @ state.phi @ b, 1e-12)
    assert_close(new.x, np.einsum("...ij,...j->...i", a, state.x) + shift, 1e-12)
    # (42): <p, v> and Tr(pi xi) invariant
    assert_close(np.sum(new.p * vnew.v, -1), np.sum(state.p * vstate.v, -1), 1e-9)
    assert_close(_tr(new.pi @ vnew.xi), _tr(state.pi @ vstate.xi), 1e-9)
    # (47), (48): spatial and material actions on the affine spins
    spatial = actions.transform_state(state, A=a)
    material = actions.transform_state(state, B=b)
    sigma = momenta.affine_spin(state.phi, state.pi)
    sigma_hat = momenta.comoving_affine_spin(state.phi, state.pi)
    assert_close(momenta.affine_spin(spatial.phi, spatial.pi), a @ sigma @ _inv(a), 1e-9)
    assert_close(momenta.comoving_affine_spin(spatial.phi, spatial.pi), sigma_hat, 1e-9)
    assert_close(momenta.affine_spin(material.phi, material.pi), sigma, 1e-9)
    assert_close(momenta.comoving_affine_spin(material.phi, material.pi),
                 _inv(b) @ sigma_hat @ b, 1e-9)
    # (35), (36) once more through the action on the Lagrangian state
    omega_hat = velocities.comoving_affine_velocity(vstate.phi, vstate.xi)
    assert_close(velocities.comoving_affine_velocity(vnew.phi, vnew.xi),
                 _inv(b) @ omega_hat @ b, 1e-9)


def _field(x, phi, weights):
    """A smooth function on R^n x GL(n) whose gradient plays the part of (p, pi^T)."""
    return jnp.sum(jnp.cos(x) * weights[0]) + _test_function(phi, weights) + x @ phi @ x


_field_momenta = jax.jit(
    lambda x, phi, weights: tuple(g.T if g.ndim == 2 else g
                                  for g in jax.grad(_field, (0, 1))(x, phi, weights))
)


def _pulled_back(x_new, phi_new, a, b, shift, weights):
    a_inv = jnp.linalg.inv(a)
    return _field(a_inv @ (x_new - shift), a_inv @ phi_new @ jnp.linalg.inv(b), weights)


_pulled_back_momenta = jax.jit(
    lambda *args: tuple(g.T if g.ndim == 2 else g
                        for g in jax.grad(_pulled_back, (0, 1))(*args))
)


@FAST
@given(st.data())
def test_momentum_action_is_the_cotangent_lift(data):
    """p = df/dx and pi = (df/dphi)^T transform as the gradient of the transported f."""
    n = data.draw(dims)
    x, shift = data.draw(vectors(n, ())), data.draw(vectors(n, ()))
    phi, a, b = (data.draw(matrices("GL", n, ())) for _ in range(3))
    weights = data.draw(square_matrices(n, ()))
    p, pi = _field_momenta(x, phi, weights)
    new = actions.transform_state(State(x, phi, p, pi), a, b, shift)
    p_new, pi_new = _pulled_back_momenta(new.x, new.phi, a, b, shift, weights)
    assert_close(new.p, p_new, 1e-9)
    assert_close(new.pi, pi_new, 1e-9)


@FAST
@given(st.data())
def test_actions_compose_as_a_group_action(data):
    n = data.draw(dims)
    state, vstate = _states(data, n)
    a1, a2, b1, b2 = (data.draw(matrices("GL", n, ())) for _ in range(4))
    s1, s2 = data.draw(vectors(n, ())), data.draw(vectors(n, ()))
    twice = actions.transform_state(actions.transform_state(state, a1, b1, s1), a2, b2, s2)
    once = actions.transform_state(state, a2 @ a1, b1 @ b2, a2 @ s1 + s2)
    for got, expected in zip(twice, once, strict=True):
        assert_close(got, expected, 1e-9)
    vtwice = actions.transform_velocity_state(
        actions.transform_velocity_state(vstate, a1, b1, s1), a2, b2, s2
    )
    vonce = actions.transform_velocity_state(vstate, a2 @ a1, b1 @ b2, a2 @ s1 + s2)
    for got, expected in zip(vtwice, vonce, strict=True):
        assert_close(got, expected, 1e-9)
    # left/right translations of (13): the matrix products, to round-off (XLA's and numpy's
    # products may round the last bit differently)
    assert_close(actions.left_translation(a1, state.phi), a1 @ state.phi, 1e-14)
    assert_close(actions.right_translation(state.phi, b1), state.phi @ b1, 1e-14)


_transport = jax.jit(
    lambda x, phi, v, xi, a, b, shift: jax.jvp(
        lambda x, phi: (a @ x + shift, a @ phi @ b), (x, phi), (v, xi)
    )[1]
)


@FAST
@given(st.data())
def test_velocity_action_is_the_tangent_map(data):
    n = data.draw(dims)
    x, v, shift = (data.draw(vectors(n, ())) for _ in range(3))
    phi, a, b = (data.draw(matrices("GL", n, ())) for _ in range(3))
    xi = data.draw(square_matrices(n, ()))
    new = actions.transform_velocity_state(VelocityState(x, phi, v, xi), a, b, shift)
    v_new, xi_new = _transport(x, phi, v, xi, a, b, shift)
    assert_close(new.v, v_new, 1e-12)
    assert_close(new.xi, xi_new, 1e-12)
