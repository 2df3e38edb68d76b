"""Observables: transformation laws of the momentum maps (47), (48), (103), (108), (109),
volumes (79), and the Hamiltonian system's energy and vector field."""

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import brackets as br
from affinebody import kinetic as kin
from affinebody import mutual
from affinebody import observables as obs
from affinebody import potentials as pot
from affinebody.state import State
from affinebody.system import HamiltonianSystem

seeds = st.integers(0, 2**31 - 1)


def random_state(seed, bodies=3, n=3) -> State:
    rng = np.random.default_rng(seed)
    return State(
        x=jnp.asarray(rng.normal(size=(bodies, n))),
        phi=jnp.asarray(np.eye(n) + 0.4 * rng.normal(size=(bodies, n, n))),
        p=jnp.asarray(rng.normal(size=(bodies, n))),
        pi=jnp.asarray(rng.normal(size=(bodies, n, n))),
    )


def random_invertible(seed, n=3):
    rng = np.random.default_rng(seed)
    return jnp.asarray(np.eye(n) + 0.5 * rng.normal(size=(n, n)))


def spatial_affine(state: State, a, b) -> State:
    """Canonical lift of (x, phi) -> (A x + b, A phi): p -> A^-T p, pi -> pi A^-1."""
    a_inv = jnp.linalg.inv(a)
    return State(state.x @ a.T + b, a @ state.phi, state.p @ a_inv, state.pi @ a_inv)


def material_affine(state: State, b) -> State:
    """Canonical lift of phi -> phi B: pi -> B^-1 pi."""
    return state._replace(phi=state.phi @ b, pi=jnp.linalg.inv(b) @ state.pi)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_transformation_laws_of_the_momentum_maps(seed):
    """(47), (48): Sigma -> A Sigma A^-1 under L_A, Sigma_hat -> B^-1 Sigma_hat B under R_B;
    J = Lambda + Sigma -> A J A^-1 + b p^T under affine maps; p -> A^-T p."""
    state = random_state(seed)
    a, b = random_invertible(seed + 1), random_invertible(seed + 2)
    shift = jnp.asarray(np.random.default_rng(seed + 3).normal(size=3))
    a_inv = jnp.linalg.inv(a)
    moved = spatial_affine(state, a, shift)
    np.testing.assert_allclose(obs.affine_spin(moved), a @ obs.affine_spin(state) @ a_inv,
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(obs.comoving_affine_spin(moved), obs.comoving_affine_spin(state),
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(
        obs.affine_momentum(moved),
        a @ obs.affine_momentum(state) @ a_inv + jnp.outer(shift, obs.linear_momentum(moved)),
        rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(obs.linear_momentum(moved), obs.linear_momentum(state) @ a_inv,
                               rtol=1e-10, atol=1e-10)
    turned = material_affine(state, b)
    np.testing.assert_allclose(obs.affine_spin(turned), obs.affine_spin(state), rtol=1e-10,
                               atol=1e-10)
    np.testing.assert_allclose(obs.comoving_affine_spin(turned),
                               jnp.linalg.inv(b) @ obs.comoving_affine_spin(state) @ b,
                               rtol=1e-10, atol=1e-10)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_spin_decompositions(seed):
    state = random_state(seed)
    sigma = obs.affine_spins(state)
    sigma_hat = obs.comoving_affine_spins(state)
    # (46) with Omega = Id: the traces of the two representations agree body by body
    np.testing.assert_allclose(jnp.trace(sigma, axis1=-2, axis2=-1),
                               jnp.trace(sigma_hat, axis1=-2, axis2=-1), rtol=1e-11, atol=1e-12)
    lam = sum(jnp.outer(state.x[k], state.p[k]) for k in range(state.x.shape[0]))
    np.testing.assert_allclose(obs.orbital_affine_momentum(state), lam, rtol=1e-13, atol=1e-13)
    j = obs.affine_momentum(state)
    np.testing.assert_allclose(obs.angular_momentum(state), j - j.T, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(obs.angular_momentum(state), -obs.angular_momentum(state).T)
    np.testing.assert_allclose(obs.spin(state), sigma.sum(0) - sigma.sum(0).T, rtol=1e-13,
                               atol=1e-13)
    np.testing.assert_allclose(obs.vorticity(state), sigma_hat.sum(0) - sigma_hat.sum(0).T,
                               rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(obs.dilatation_momentum(state), jnp.trace(sigma.sum(0)),
                               rtol=1e-13)


def test_angular_momentum_generates_rotations_of_the_whole_system():
    """{F, Tr(Z J)} = d/ds F(exp(sZ) x, exp(sZ) phi) for F depending on x and phi."""
    state = random_state(4)
    z = jnp.asarray(np.random.default_rng(5).normal(size=(3, 3)))
    z = z - z.T

    def f(x, phi):
        return jnp.sum(jnp.sin(x) * jnp.sum(phi**2, axis=-1)) + jnp.linalg.det(phi[0] + phi[1])

    generator = lambda s: 0.5 * jnp.trace(z.T @ obs.angular_momentum(s))  # = Tr(Z^T J) skew Z
    bracket = br.canonical_bracket(lambda s: f(s.x, s.phi), generator, state)

    def rotated(s):
        r = jax.scipy.linalg.expm(s * z.T)
        return f(state.x @ r.T, r @ state.phi)

    rate = jax.jvp(rotated, (0.0,), (1.0,))[1]
    np.testing.assert_allclose(bracket, rate, rtol=1e-10)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_volumes_and_relative_volumes(seed):
    state = random_state(seed)
    det = np.linalg.det(np.asarray(state.phi))
    np.testing.assert_allclose(obs.volumes(state), det, rtol=1e-12)
    rel = obs.relative_volumes(state)
    for k in range(3):
        for ell in range(3):
            np.testing.assert_allclose(rel[k, ell],
                                       mutual.relative_volume(state.phi[k], state.phi[ell]),
                                       rtol=1e-10)
    # cocycle: det Gamma[K,L] det Gamma[L,M] = det Gamma[K,M]; invariant under phi -> A phi
    np.testing.assert_allclose(rel[0, 1] * rel[1, 2], rel[0, 2], rtol=1e-12)
    moved = spatial_affine(state, random_invertible(seed + 9), jnp.zeros(3))
    np.testing.assert_allclose(obs.relative_volumes(moved), rel, rtol=1e-10)


def test_hamiltonian_and_vector_field_satisfy_hamilton_equations():
    """H = T + V; the autodiff vector field gives dF/dt = {F, H} for the observables (87)."""
    system = HamiltonianSystem(
        kin.KineticEnergy(kin.AffineTranslational(1.3), kin.AffineIsotropic(2.0, 0.5, 0.3)),
        pot.total_potential([pot.Dilatation(1.0), pot.HarmonicInvariants(0.5)]))
    state = random_state(6, bodies=2, n=2)
    t = system.kinetic.hamiltonian(state)
    v = system.potential.energy(state.x, state.phi)
    np.testing.assert_allclose(system.hamiltonian(state), t + v, rtol=1e-14)
    field = system.vector_field(state)
    # dx/dt, dphi/dt from the inverse Legendre map of the kinetic helper
    velocities = system.kinetic.inverse_legendre(state)
    np.testing.assert_allclose(field.x, velocities.v, rtol=1e-12)
    np.testing.assert_allclose(field.phi, velocities.xi, rtol=1e-12)
    for f in (obs.affine_spin, obs.comoving_affine_spin, obs.affine_momentum,
              obs.linear_momentum, obs.volumes):
        rate = jax.jvp(f, (state,), (field,))[1]
        np.testing.assert_allclose(br.canonical_bracket(f, system.hamiltonian, state), rate,
                                   rtol=1e-10, atol=1e-12)
    # H is invariant under spatial SL(n) (V(det phi) breaks only the scaling): the traceless
    # part of {J, H} vanishes (Noether), the trace part does not
    rate_j = br.canonical_bracket(obs.affine_momentum, system.hamiltonian, state)
    trace_part = jnp.trace(rate_j) / 2 * jnp.eye(2)
    np.testing.assert_allclose(rate_j - trace_part, 0.0, atol=1e-12)
    assert abs(float(jnp.trace(rate_j))) > 1e-3
