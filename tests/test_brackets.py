"""Poisson brackets (87): closed forms in affinebody.brackets vs the autodiff canonical bracket."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import brackets as br
from affinebody import observables as obs
from affinebody.state import State

N, n = 2, 3


def random_state(seed: int, bodies: int = N, dim: int = n) -> State:
    rng = np.random.default_rng(seed)
    return State(
        x=jnp.asarray(rng.normal(size=(bodies, dim))),
        phi=jnp.asarray(np.eye(dim) + 0.4 * rng.normal(size=(bodies, dim, dim))),
        p=jnp.asarray(rng.normal(size=(bodies, dim))),
        pi=jnp.asarray(rng.normal(size=(bodies, dim, dim))),
    )


def config_function(phi):
    """A non-invariant configuration function of both bodies' phi."""
    g = jnp.swapaxes(phi, -1, -2) @ phi
    return jnp.sum(jnp.trace(g @ g, axis1=-2, axis2=-1)) + jnp.linalg.det(phi[0]) * phi[1, 0, 1]


seeds = st.integers(0, 2**31 - 1)


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_sigma_brackets_give_gl_structure_per_body(seed):
    state = random_state(seed)
    auto = br.canonical_bracket(obs.affine_spins, obs.affine_spins, state)  # [K,i,j,L,k,l]
    closed = br.sigma_bracket(obs.affine_spins(state))  # [K,i,j,k,l]
    for k in range(N):
        for ell in range(N):
            expected = closed[k] if k == ell else jnp.zeros_like(closed[k])
            np.testing.assert_allclose(auto[k, :, :, ell], expected, atol=1e-12, rtol=1e-12)


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_comoving_sigma_brackets_give_gl_structure_per_body(seed):
    state = random_state(seed)
    auto = br.canonical_bracket(obs.comoving_affine_spins, obs.comoving_affine_spins, state)
    closed = br.comoving_sigma_bracket(obs.comoving_affine_spins(state))
    for k in range(N):
        for ell in range(N):
            expected = closed[k] if k == ell else jnp.zeros_like(closed[k])
            np.testing.assert_allclose(auto[k, :, :, ell], expected, atol=1e-12, rtol=1e-12)


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_spatial_and_comoving_spins_commute(seed):
    state = random_state(seed)
    auto = br.canonical_bracket(obs.affine_spins, obs.comoving_affine_spins, state)
    scale = float(jnp.max(jnp.abs(obs.affine_spins(state))))
    np.testing.assert_allclose(auto, 0.0, atol=1e-12 * scale)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_linear_brackets_are_lie_algebra_homomorphisms(seed):
    """{Sigma(Z1), Sigma(Z2)} = Sigma([Z1,Z2]), {Sh(Z1), Sh(Z2)} = -Sh([Z1,Z2]), J(Z) likewise."""
    state = random_state(seed)
    rng = np.random.default_rng(seed + 1)
    z1, z2 = (jnp.asarray(rng.normal(size=(n, n))) for _ in range(2))

    def lin(f, z):
        return lambda s: jnp.trace(z @ f(s))

    for f, closed in (
        (obs.affine_spin, br.sigma_linear_bracket(z1, z2, obs.affine_spin(state))),
        (obs.comoving_affine_spin,
         br.comoving_sigma_linear_bracket(z1, z2, obs.comoving_affine_spin(state))),
        # the total affine momentum J = Lambda + Sigma (109) generates the same gl(n) action
        (obs.affine_momentum, br.sigma_linear_bracket(z1, z2, obs.affine_momentum(state))),
    ):
        auto = br.canonical_bracket(lin(f, z1), lin(f, z2), state)
        np.testing.assert_allclose(auto, closed, rtol=1e-11, atol=1e-11)


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_spin_brackets_with_configuration_functions(seed):
    state = random_state(seed)
    d = jax.grad(config_function)(state.phi)
    f = lambda s: config_function(s.phi)
    auto = br.canonical_bracket(obs.affine_spins, f, state)
    np.testing.assert_allclose(auto, br.sigma_config_bracket(state.phi, d), rtol=1e-11,
                               atol=1e-11)
    auto_hat = br.canonical_bracket(obs.comoving_affine_spins, f, state)
    np.testing.assert_allclose(auto_hat, br.comoving_sigma_config_bracket(state.phi, d),
                               rtol=1e-11, atol=1e-11)


def test_spins_generate_left_and_right_translations():
    """{F, Tr(Z Sigma_K)} = d/ds F(exp(sZ) phi_K), {F, Tr(Z Sh_K)} = d/ds F(phi_K exp(sZ))."""
    state = random_state(7)
    z = jnp.asarray(np.random.default_rng(8).normal(size=(n, n)))
    d = jax.grad(config_function)(state.phi)
    for k in range(N):
        def moved(s, left, k=k):
            g = jax.scipy.linalg.expm(s * z)
            new = g @ state.phi[k] if left else state.phi[k] @ g
            return config_function(state.phi.at[k].set(new))

        left_rate = jax.jvp(lambda s: moved(s, True), (0.0,), (1.0,))[1]
        right_rate = jax.jvp(lambda s: moved(s, False), (0.0,), (1.0,))[1]
        # {F, G} = -{G, F}
        closed_left = -jnp.trace(z @ br.sigma_config_bracket(state.phi[k], d[k]))
        closed_right = -jnp.trace(z @ br.comoving_sigma_config_bracket(state.phi[k], d[k]))
        np.testing.assert_allclose(closed_left, left_rate, rtol=1e-11)
        np.testing.assert_allclose(closed_right, right_rate, rtol=1e-11)


def test_translational_brackets_with_functions_of_position():
    state = random_state(3)
    f = lambda x: jnp.sum(jnp.sin(x[0]) * x[1] ** 2) + x[0, 0] * x[1, 1]
    dfx = jax.grad(f)(state.x)
    auto_p = br.canonical_bracket(lambda s: s.p, lambda s: f(s.x), state)
    np.testing.assert_allclose(auto_p, br.momentum_config_bracket(dfx), rtol=1e-12)
    lam = lambda s: s.x[..., :, None] * s.p[..., None, :]  # per-body Lambda_K = x_K p_K^T
    auto_l = br.canonical_bracket(lam, lambda s: f(s.x), state)
    np.testing.assert_allclose(auto_l, br.affine_momentum_config_bracket(state.x, dfx),
                               rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("seed", [0, 1])
def test_canonical_bracket_is_antisymmetric_and_satisfies_jacobi(seed):
    state = random_state(seed, bodies=1, dim=2)
    fs = [
        lambda s: jnp.sum(s.phi @ s.pi @ s.phi) + jnp.sum(s.x * s.p),
        lambda s: (jnp.sum(jnp.trace(s.pi @ s.pi @ s.phi, axis1=-2, axis2=-1))
                   + jnp.sum(s.p**2 * s.x)),
        lambda s: jnp.linalg.det(s.phi[0]) * jnp.sum(s.pi**2) + s.x[0, 0] * s.p[0, 1],
    ]

    def bracket_fn(f, g):
        return lambda s: br.canonical_bracket(f, g, s)

    a, b, c = fs
    np.testing.assert_allclose(br.canonical_bracket(a, b, state),
                               -br.canonical_bracket(b, a, state), rtol=1e-12)
    jacobi = (br.canonical_bracket(a, bracket_fn(b, c), state)
              + br.canonical_bracket(b, bracket_fn(c, a), state)
              + br.canonical_bracket(c, bracket_fn(a, b), state))
    scale = abs(float(br.canonical_bracket(a, bracket_fn(b, c), state))) + 1.0
    assert abs(float(jacobi)) < 1e-10 * scale
