"""Two-polar reduction of the doubly isotropic Hamiltonians (quantum/reduction.py): the reduced
operator applied to radial functions equals the full operator of quantum/hamiltonians.py
(autodiff on R^{n^2}) applied to the wave function built from them, for n = 2 (SO(2)
characters) and n = 3 (scalar and spin = vorticity = 1 channels); the measures; the sign of
rho +- tau; the labels and the identification Psi(L m, q, R m) = Psi(L, q, R)."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody.quantum import hamiltonians as hm
from affinebody.quantum import operators as ops
from affinebody.quantum import reduction as rd

jax.config.update("jax_enable_x64", True)

HBAR = 0.8
I, A, B = 1.3, 0.4, 0.25  # noqa: E741
RTOL = 1e-8


def radial_n2(x):
    """A smooth, non-symmetric test function of (q_1, q_2) or (Q_1, Q_2)."""
    return jnp.exp(-0.3 * jnp.sum(x**2)) * (1 + 0.2 * x[0] - 0.5 * x[1] ** 2 + 0.1 * x[0] * x[1])


def points(seed, n, count, positive=True):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        phi = rng.normal(size=(n, n))
        s = np.linalg.svd(phi, compute_uv=False)
        if np.min(np.abs(np.diff(s))) < 0.1 or np.min(s) < 0.2:
            continue  # stay away from the walls q_a = q_b (and, for Q, from Q_n = 0)
        if positive and np.linalg.det(phi) < 0:
            phi = phi[::-1]
        out.append(phi)
    return jnp.asarray(np.array(out))


def coordinates(model, Q):
    return Q if model == "dalembert" else jnp.log(Q)


FULL_N2 = {
    "af-is": hm.affine_isotropic_kinetic(I, A, B, 2),
    "is-af": hm.isotropic_affine_kinetic(I, A, B, 2),
    "af-af": hm.affine_affine_kinetic(A, B, 2),
    "dalembert": hm.dalembert_kinetic(I * jnp.eye(2)),
}


def character_wave(model, m, k):
    def psi(phi):
        L, Q, R = rd.two_polar_section(phi)
        phase = jnp.exp(1j * (m * rd.so2_angle(L) + k * rd.so2_angle(R)))
        return phase * radial_n2(coordinates(model, Q))

    return psi


@partial(jax.jit, static_argnames=("model",))
def full_and_reduced_n2(model, m, k, k_reduced, phis):
    """(H Psi)(phi) by the full operator, and e^{i(m alpha + k beta)} (H_red f)(x) with the
    reduced operator of the channel (m, k_reduced)."""
    kinetic = FULL_N2[model]
    reduction = rd.TwoPolarReduction(model, 2, I, A if model != "dalembert" else 0.0, B, HBAR)
    psi = character_wave(model, m, k)
    channel = rd.so2_character_channel(m, k_reduced)

    def one(phi):
        full = kinetic(psi, HBAR)(phi)
        L, Q, R = rd.two_polar_section(phi)
        x = coordinates(model, Q)
        reduced = reduction.apply(lambda y: radial_n2(y)[None] + 0j, x, channel)[0]
        phase = jnp.exp(1j * (m * rd.so2_angle(L) + k * rd.so2_angle(R)))
        return full, reduced * phase

    return jax.vmap(one)(phis)


@pytest.mark.parametrize("model", ["af-is", "is-af", "af-af", "dalembert"])
@settings(max_examples=6, deadline=None)
@given(m=st.integers(-3, 3), k=st.integers(-3, 3))
def test_n2_reduced_operator_equals_full_operator(model, m, k):
    """n = 2, Psi = e^{i m alpha} e^{i k beta} f(x): full T Psi = e^{...} (H_red f), to 1e-8,
    at random phi (for d'Alembert also det phi < 0, i.e. Q_2 < 0)."""
    phis = points(100 + m + 10 * k, 2, 3, positive=model != "dalembert")
    full, reduced = full_and_reduced_n2(model, float(m), float(k), float(k), phis)
    assert np.min(np.abs(full)) > 1e-4
    np.testing.assert_allclose(reduced, full, rtol=RTOL)


@pytest.mark.parametrize("model", ["af-is", "dalembert"])
def test_n2_sign_of_rho_plus_tau_is_settled(model):
    """The singular 1/sinh^2 (1/(Q_1 - Q_2)^2) term carries rho + tau with both generators
    defined by right multiplication; the other sign (tau -> -tau) fails where m k != 0."""
    phis = points(3, 2, 3, positive=model != "dalembert")
    full, right = full_and_reduced_n2(model, 1.0, 2.0, 2.0, phis)
    _, wrong = full_and_reduced_n2(model, 1.0, 2.0, -2.0, phis)
    np.testing.assert_allclose(right, full, rtol=RTOL)
    assert np.min(np.abs(wrong - full) / np.abs(full)) > 1e-3


def test_n2_labels_and_identification():
    """On Psi = e^{i m alpha} e^{i k beta} f(q): spin S_12 = hbar m, vorticity V_12 = -hbar k
    (operators.py, (49)); and Psi is single-valued on GL+(2) -- the same value from the
    sections (L, q, R) and (-L, q, -R) -- exactly when m + k is even."""
    phis = points(11, 2, 2)

    @jax.jit
    def labels(m, k, phis):
        psi = character_wave("af-is", m, k)

        def one(phi):
            return (
                ops.spin_op(psi, HBAR)(phi)[0, 1],
                ops.vorticity_op(psi, HBAR)(phi)[0, 1],
                psi(phi),
            )

        return jax.vmap(one)(phis)

    for m, k in [(1, 1), (2, -1), (-3, 0)]:
        spin, vort, value = labels(float(m), float(k), phis)
        np.testing.assert_allclose(spin, HBAR * m * value, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(vort, -HBAR * k * value, rtol=1e-10, atol=1e-14)
        L, Q, R = rd.two_polar_section(phis[0])
        f = radial_n2(jnp.log(Q))
        one = jnp.exp(1j * (m * rd.so2_angle(L) + k * rd.so2_angle(R))) * f
        other = jnp.exp(1j * (m * rd.so2_angle(-L) + k * rd.so2_angle(-R))) * f
        np.testing.assert_allclose(((-L) * Q[None, :]) @ (-R).T, phis[0], atol=1e-12)
        assert bool(np.isclose(one, other, rtol=1e-12)) == rd.so2_sector_allowed(m, k)


# ----------------------------------------------------------------------------------------
# n = 3: scalar channel (spin = vorticity = 0) and the Cartesian spin = vorticity = 1 channel


FULL_N3 = {
    "af-is": hm.affine_isotropic_kinetic(I, A, B, 3),
    "dalembert": hm.dalembert_kinetic(I * jnp.eye(3)),
}
_rng = np.random.default_rng(2024)
CHANNEL_MIX = jnp.asarray(_rng.normal(size=(9, 3)))
OUTER = jnp.asarray(_rng.normal(size=9))
SCALAR_WEIGHT = 0.7


def radial_scalar(x):
    return jnp.exp(-0.2 * jnp.sum(x**2)) * (1 + 0.3 * x[0] - 0.2 * x[1] * x[2] + 0.1 * x[2] ** 2)


def radial_vector(x):
    """Nine radial functions F_{mu nu}(x) of the (1, 1) channel (no symmetry imposed)."""
    y = CHANNEL_MIX @ x
    return jnp.exp(-0.2 * jnp.sum(x**2)) * (1 + y + 0.1 * y**2)


@partial(jax.jit, static_argnames=("model",))
def full_and_reduced_n3(model, phis):
    kinetic = FULL_N3[model]
    reduction = rd.TwoPolarReduction(model, 3, I, A if model != "dalembert" else 0.0, B, HBAR)
    scalar, vector = rd.cartesian_channel(3, 0, 0), rd.cartesian_channel(3, 1, 1)

    def psi(phi):
        L, Q, R = rd.two_polar_section(phi)
        x = coordinates(model, Q)
        vec = rd.cartesian_wave_function(L, R, radial_vector(x), OUTER, 1, 1)
        return SCALAR_WEIGHT * radial_scalar(x) + vec

    def one(phi):
        full = kinetic(psi, HBAR)(phi)
        L, Q, R = rd.two_polar_section(phi)
        x = coordinates(model, Q)
        h_scalar = reduction.apply(lambda y: radial_scalar(y)[None], x, scalar)[0]
        h_vector = reduction.apply(radial_vector, x, vector)
        reduced = SCALAR_WEIGHT * h_scalar + rd.cartesian_wave_function(L, R, h_vector, OUTER, 1, 1)
        return full, reduced

    return jax.vmap(one)(phis)


@pytest.mark.parametrize("model", ["af-is", "dalembert"])
def test_n3_reduced_operator_equals_full_operator(model):
    """n = 3: Psi = c f_0(x) + <u, L F(x) R^T w> (scalar + spin = vorticity = 1 channels, nine
    unconstrained radial functions); full T Psi equals the reduced operators applied to
    (f_0, F), to 1e-8 (d'Alembert also at det phi < 0)."""
    phis = points(5, 3, 2, positive=model != "dalembert")
    full, reduced = full_and_reduced_n3(model, phis)
    assert np.min(np.abs(full)) > 1e-4
    np.testing.assert_allclose(reduced, full, rtol=RTOL)


def test_n3_identification_and_the_explicit_spin_one_channel():
    """M-invariance: no states with spin 1 and vorticity 0 (or 0, 1); for (1, 1) exactly the
    diagonal F = diag(f_1, f_2, f_3). U_sector preserves them, and on diagonal F equals the
    explicit formula of the reduction.py docstring."""
    n = 3
    assert np.allclose(rd.identification_projector(n, 1, 0), 0)
    assert np.allclose(rd.identification_projector(n, 0, 1), 0)
    proj = np.asarray(rd.identification_projector(n, 1, 1))
    diagonal = np.diag(np.eye(n).ravel())
    np.testing.assert_allclose(proj, diagonal, atol=1e-15)
    channel = rd.cartesian_channel(n, 1, 1)
    q = jnp.asarray([0.9, 0.1, -0.6])
    for model in ("af-is", "is-af", "af-af", "dalembert"):
        red = rd.TwoPolarReduction(model, n, I, A, B, HBAR)
        x = jnp.exp(q) if model == "dalembert" else q
        u = np.asarray(red.sector_potential(x, channel))
        np.testing.assert_allclose(u @ proj, proj @ u, atol=1e-12)
        coeff = np.asarray(red.pair_coefficients(x))
        f = np.array([0.3, -1.2, 0.8])
        expected = np.zeros(n)
        for p, (a, b) in enumerate(rd.pairs(n)):
            c_plus, c_minus, c_rho, c_tau = coeff[p]
            for i, j in ((a, b), (b, a)):
                expected[i] += 2 * HBAR**2 * c_plus * (f[i] - f[j])
                expected[i] += 2 * HBAR**2 * c_minus * (f[i] + f[j])
                expected[i] += HBAR**2 * (c_rho + c_tau) * f[i]
        got = (u @ np.diag(f).ravel()).reshape(n, n)
        np.testing.assert_allclose(got, np.diag(expected), atol=1e-12)


# ----------------------------------------------------------------------------------------
# measures


@pytest.mark.parametrize("n", [2, 3])
def test_two_polar_measures(n):
    """|det d phi / d(q, a, b)| |det phi|^-n = 2^{n(n-1)/2} J(q) for phi = L e^{A(a)} D(q)
    (R e^{B(b)})^T at a = b = 0 (Haar, (91)); with D = diag(Q): |det d phi / d(Q, a, b)| =
    prod |Q_a^2 - Q_b^2| (Lebesgue) -- the radial weights of reduction.py."""
    gens = jnp.asarray(np.array([rd.rotation_generator(n, a, b) for a, b in rd.pairs(n)]))
    npair = len(gens)
    haar = rd.TwoPolarReduction("af-is", n, I, A, B)
    lebesgue = rd.TwoPolarReduction("dalembert", n, I)

    def chart(L0, R0, diag_map):
        def phi_of(v):
            x, a, b = v[:n], v[n : n + npair], v[n + npair :]
            left = L0 @ (jnp.eye(n) + jnp.einsum("p,pij->ij", a, gens))
            right = R0 @ (jnp.eye(n) + jnp.einsum("p,pij->ij", b, gens))
            return (left * diag_map(x)[None, :]) @ right.T

        return phi_of

    @jax.jit
    def densities(phi, q):
        L0, Q, R0 = rd.two_polar_section(phi)
        v0 = jnp.concatenate([Q, jnp.zeros(2 * npair)])
        jac_l = jax.jacfwd(chart(L0, R0, lambda x: x))(v0).reshape(n * n, n * n)
        v0 = jnp.concatenate([q, jnp.zeros(2 * npair)])
        jac_h = jax.jacfwd(chart(L0, R0, jnp.exp))(v0).reshape(n * n, n * n)
        return (
            jnp.abs(jnp.linalg.det(jac_l)) / lebesgue.radial_weight(Q),
            jnp.abs(jnp.linalg.det(jac_h)) * jnp.exp(-n * jnp.sum(q)) / haar.radial_weight(q),
        )

    rng = np.random.default_rng(n)
    for phi in points(17, n, 3, positive=False):
        q = jnp.asarray(np.sort(rng.normal(size=n))[::-1])
        ratio_l, ratio_h = densities(phi, q)
        np.testing.assert_allclose(ratio_l, 1.0, rtol=1e-10)
        np.testing.assert_allclose(ratio_h, 2**npair, rtol=1e-10)


def test_bad_reduction_input():
    with pytest.raises(ValueError, match="model must be one of"):
        rd.TwoPolarReduction("af-J", 2)
    with pytest.raises(ValueError, match="I != \\|A\\|"):
        rd.TwoPolarReduction("af-is", 2, I=0.5, A=0.5)
    with pytest.raises(ValueError, match="I > 0|must be > 0"):
        rd.TwoPolarReduction("dalembert", 2, I=-1.0)
