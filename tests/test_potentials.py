"""Potentials: autodiff forces, declared symmetries (invariance, tightness, Noether), cut-off,
periodic images, analytic minima and the closed-form gradients of docs/theory/exact-flows.md."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody.potentials import (
    SYMMETRIES,
    Cutoff,
    Dilatation,
    ExternalHarmonic,
    ExternalLinear,
    Gaussian,
    HarmonicInvariants,
    LennardJones,
    Morse,
    OneBodyPotential,
    PairPotential,
    StVenantKirchhoff,
    build_potential,
    generalized_forces,
    switching,
    total_potential,
)
from samples import configuration, random_rotation, transform


def catalogue(n: int) -> list:
    """One potential of every kind, parameters chosen so that every pair of a compact
    configuration (see ``configuration``) interacts."""
    return [
        LennardJones(0.7, 0.3),
        LennardJones(0.7, 0.25, argument="D", cutoff=Cutoff(6.0, 5.0, "D")),
        Morse(1.3, 1.7, 1.1),
        Morse(1.3, 1.7, 1.1, argument="D", cutoff=Cutoff(3.0, 0.5, "r")),
        Gaussian(-1.1, 0.9),
        Gaussian(2.0, 1.3, argument="D"),
        HarmonicInvariants(0.8),
        HarmonicInvariants(0.8, invariants="K", reference=tuple(1.0 + a for a in range(n))),
        PairPotential.from_expression("exp(-D**2) * (M1 - 2)**2 + 0.3*det", n),
        PairPotential.from_expression("r**2 * log(1 + det**2) + M2", n),
        PairPotential(lambda K, r: jnp.sum(K, axis=-1) * jnp.exp(-r), ("K", "r")),
        OneBodyPotential.from_expression("10*(det - 1)**2", n),
        OneBodyPotential.from_expression("x1**2 * K2 + sin(x2) + I2", n),
        Dilatation(2.0),
        Dilatation(1.5, volume=1.2, form="harmonic"),
        StVenantKirchhoff(0.4, 1.1),
        ExternalHarmonic(1.2, tuple(0.3 * (-1) ** a for a in range(n))),
        ExternalLinear(tuple(0.5 + a for a in range(n))),
        OneBodyPotential(lambda phi: jnp.sum(phi * WEIGHTS[n], axis=(-2, -1)), ("phi",)),
        OneBodyPotential(lambda E, det: E[..., 0, 0] ** 2 + det, ("E", "det")),
    ]


WEIGHTS = {n: jnp.arange(1.0, n * n + 1).reshape(n, n) for n in (2, 3)}


def gradient(pot, x, phi):
    """(dV/dx, dV/dphi) by autodiff (eager: one compile per primitive, not per potential)."""
    fx, fphi = generalized_forces(pot, x, phi)
    return -fx, -fphi


CATALOGUES = {n: catalogue(n) for n in (2, 3)}
BODIES = 4  # one shape for (almost) every test: JAX compiles each primitive once per shape
CASES = [(n, i) for n in (2, 3) for i in range(len(CATALOGUES[n]))]


def case_id(case):
    n, i = case
    pot = CATALOGUES[n][i]
    return f"n{n}-{i}-{type(pot).__name__}"


# --------------------------------------------------------------------------------------------
# forces


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_autodiff_forces_match_central_differences(case):
    n, i = case
    pot = CATALOGUES[n][i]
    rng = np.random.default_rng(100 + i)
    x, phi = configuration(rng, BODIES, n)
    gx, gphi = gradient(pot, x, phi)
    # three random directions, +-h each: one batched energy call of the shape used throughout
    h = 1e-5
    dx = rng.normal(size=(3, *x.shape))
    dphi = rng.normal(size=(3, *phi.shape))
    xs = jnp.concatenate([x + h * dx, x - h * dx])
    phis = jnp.concatenate([phi + h * dphi, phi - h * dphi])
    e = np.asarray(pot.energy(xs, phis))
    numeric = (e[:3] - e[3:]) / (2 * h)
    autodiff = np.einsum("kd,ekd->e", gx, dx) + np.einsum("kab,ekab->e", gphi, dphi)
    scale = max(1.0, float(np.max(np.abs(autodiff))))
    np.testing.assert_allclose(autodiff, numeric, atol=1e-7 * scale, rtol=1e-7)
    assert np.max(np.abs(autodiff)) > 1e-3  # the potential does depend on the configuration


# --------------------------------------------------------------------------------------------
# symmetries: declared ones hold, undeclared ones fail (tight), Noether identities


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
@pytest.mark.parametrize("n", [2, 3])
def test_declared_symmetries_hold_and_are_tight(n, seed):
    rng = np.random.default_rng(seed)
    x, phi = configuration(rng, BODIES, n)
    moved = [transform(symmetry, rng, x, phi) for symmetry in SYMMETRIES]
    xs = jnp.stack([x] + [m[0] for m in moved])  # one batched call per potential
    phis = jnp.stack([phi] + [m[1] for m in moved])
    for pot in CATALOGUES[n]:
        e0, *e1 = np.asarray(pot.energy(xs, phis))
        for symmetry, e in zip(SYMMETRIES, e1, strict=True):
            change = abs(e - e0) / (1.0 + abs(e0))
            if symmetry in pot.symmetry:
                assert change < 1e-9, (pot, symmetry, e0, e)
            else:
                assert change > 1e-7, (pot, symmetry, e0, e)


def noether_charges(x, phi, gx, gphi):
    """sum_K dV/dx_K, sum_K [x_K gx_K^T + phi_K gphi_K^T], sum_K phi_K^T gphi_K."""
    force_sum = jnp.sum(gx, axis=0)
    spatial = jnp.einsum("ki,kj->ij", x, gx) + jnp.einsum("kia,kja->ij", phi, gphi)
    material = jnp.einsum("kia,kib->ab", phi, gphi)
    return force_sum, spatial, material


@pytest.mark.parametrize("n", [2, 3])
def test_noether_identities_of_declared_symmetries(n):
    rng = np.random.default_rng(7)
    x, phi = configuration(rng, BODIES, n)
    for pot in CATALOGUES[n]:
        gx, gphi = gradient(pot, x, phi)
        force_sum, spatial, material = noether_charges(x, phi, gx, gphi)
        scale = 1.0 + float(jnp.max(jnp.abs(gphi))) + float(jnp.max(jnp.abs(gx)))
        checks = {
            "translation": force_sum,
            "spatial-affine": spatial,
            "spatial-euclidean": spatial - spatial.T,
            "material-affine": material,
            "material-euclidean": material - material.T,
        }
        for symmetry, charge in checks.items():
            size = float(jnp.max(jnp.abs(charge))) / scale
            if symmetry in pot.symmetry:
                assert size < 1e-12, (pot, symmetry, size)
            else:
                assert size > 1e-6, (pot, symmetry, size)


def test_energy_is_invariant_under_relabelling_bodies():
    # (59) sums V_KL over all ordered pairs: asymmetric arguments (M_a, det Gamma) included
    rng = np.random.default_rng(5)
    x, phi = configuration(rng, BODIES, 2)
    perms = [np.arange(BODIES)] + [rng.permutation(BODIES) for _ in range(5)]
    xs, phis = jnp.stack([x[p] for p in perms]), jnp.stack([phi[p] for p in perms])
    for pot in CATALOGUES[2]:
        e = np.asarray(pot.energy(xs, phis))
        np.testing.assert_allclose(e, e[0], rtol=1e-12, atol=1e-12)


def test_pair_with_asymmetric_variables_is_half_sum_over_ordered_pairs():
    # V = 1/2 sum_{K != L} f(M1[phi_K, phi_L]) with M1 = Tr(phi_K^-1 phi_L), eq. (59)
    rng = np.random.default_rng(9)
    x, phi = configuration(rng, BODIES, 2)
    pot = PairPotential.from_expression("(M1 - 1.5)**2 + det", 2)
    p = np.asarray(phi)
    expected = 0.0
    for k, l in itertools.permutations(range(BODIES), 2):
        gamma = np.linalg.solve(p[k], p[l])
        expected += 0.5 * ((np.trace(gamma) - 1.5) ** 2 + np.linalg.det(gamma))
    assert float(pot.energy(x, phi)) == pytest.approx(expected, rel=1e-12)


def test_total_potential_sums_energies_and_intersects_symmetries():
    x, phi = configuration(np.random.default_rng(2), BODIES, 2)
    parts = CATALOGUES[2][4:9]
    total = total_potential([parts[0], total_potential(parts[1:])])
    assert float(total.energy(x, phi)) == pytest.approx(
        sum(float(p.energy(x, phi)) for p in parts), rel=1e-12
    )
    assert total.symmetry == frozenset.intersection(*(p.symmetry for p in parts))
    assert float(total_potential([]).energy(x, phi)) == 0.0


def test_potentials_are_hashable_static_arguments_of_jit():
    x, phi = configuration(np.random.default_rng(6), BODIES, 3)
    pots = CATALOGUES[3]
    total = total_potential([pots[1], pots[8], pots[15]])
    assert hash(total) == hash(total_potential([pots[1], pots[8], pots[15]]))
    energy = jax.jit(lambda pot, a, b: pot.energy(a, b), static_argnums=0)
    assert float(energy(total, x, phi)) == pytest.approx(float(total.energy(x, phi)), rel=1e-13)


def test_separable_form_equals_sum_of_translational_and_internal_parts():
    # (60): f(r) + g(M) as one expression equals two separate pair potentials
    x, phi = configuration(np.random.default_rng(4), BODIES, 2)
    joint = PairPotential.from_expression("exp(-r) + (M2 - 2)**2", 2)
    split = total_potential(
        [
            PairPotential.from_expression("exp(-r)", 2),
            PairPotential.from_expression("(M2 - 2)**2", 2),
        ]
    )
    assert float(joint.energy(x, phi)) == pytest.approx(float(split.energy(x, phi)), rel=1e-13)
    assert (
        joint.symmetry
        == split.symmetry
        == frozenset({"translation", "spatial-euclidean", "material-euclidean", "material-affine"})
    )


# --------------------------------------------------------------------------------------------
# analytic facts about the families


def two_bodies(distance, n: int = 3, scale: float = 1.0):
    """Batch of two-body systems at the given separations along e_1, phi = scale * Id."""
    d = jnp.atleast_1d(jnp.asarray(distance, dtype=jnp.float64))
    x = jnp.zeros((d.size, 2, n)).at[:, 1, 0].set(d)
    phi = jnp.broadcast_to(scale * jnp.eye(n), (d.size, 2, n, n))
    return x, phi


def radial(pot, n=3, scale=1.0):
    """E(d) and E'(d) along the separation (arrays of d; the systems are independent)."""

    def energy(d):
        return pot.energy(*two_bodies(d, n, scale))

    def slope(d):
        return jax.grad(lambda t: jnp.sum(energy(t)))(jnp.atleast_1d(jnp.asarray(d, float)))

    return energy, slope


def test_lennard_jones_minimum_in_r_and_in_affine_distance():
    eps, sigma = 0.8, 1.3
    r_min = 2 ** (1 / 6) * sigma
    d = jnp.array([r_min, 0.99 * r_min, 1.01 * r_min, 3.0 * r_min])
    e, de = radial(LennardJones(eps, sigma))
    energy = np.asarray(e(d))
    assert energy[0] == pytest.approx(-eps, rel=1e-13)
    assert np.all(energy[1:] > -eps)
    assert abs(float(de(d)[0])) < 1e-12
    # in D with phi = 2 Id: D = r / 2, so the minimum sits at r = 2 * 2^(1/6) sigma
    e, de = radial(LennardJones(eps, sigma, argument="D"), scale=2.0)
    assert float(e(2 * d)[0]) == pytest.approx(-eps, rel=1e-13)
    assert abs(float(de(2 * d)[0])) < 1e-12


def test_morse_minimum_depth_and_dissociation():
    depth, alpha, r0 = 1.7, 2.1, 0.9
    d = jnp.array([r0, 0.8 * r0, 1.2 * r0, 40.0])
    e, de = radial(Morse(depth, alpha, r0))
    energy = np.asarray(e(d))
    assert energy[0] == pytest.approx(-depth, rel=1e-14)
    assert np.all(energy[1:] > -depth)
    assert abs(energy[3]) < 1e-12
    assert abs(float(de(d)[0])) < 1e-13
    h = 1e-5  # curvature at the minimum, V'' = 2 depth alpha^2, from the autodiff slope
    slope = np.asarray(de(jnp.array([r0 - h, r0 + h, r0, r0])))
    assert (slope[1] - slope[0]) / (2 * h) == pytest.approx(2 * depth * alpha**2, rel=1e-8)


def test_gaussian_values():
    e, de = radial(Gaussian(2.5, 0.7))
    d = jnp.array([0.0, 0.7, 1.4, 2.1])
    np.testing.assert_allclose(e(d), 2.5 * np.exp(-0.5 * np.arange(4) ** 2), rtol=1e-14)
    np.testing.assert_allclose(
        de(d), -2.5 * d / 0.49 * np.exp(-0.5 * np.arange(4) ** 2), rtol=1e-13, atol=1e-15
    )


def test_elastic_energy_formula_and_rotation_free():
    rng = np.random.default_rng(11)
    x, phi = configuration(rng, BODIES, 3)
    lam, mu = 0.4, 1.1
    pot = StVenantKirchhoff(lam, mu)
    expected = 0.0
    for p in np.asarray(phi):
        strain = 0.5 * (p.T @ p - np.eye(3))
        expected += 0.5 * lam * np.trace(strain) ** 2 + mu * np.trace(strain @ strain)
    assert float(pot.energy(x, phi)) == pytest.approx(expected, rel=1e-12)
    rotations = jnp.asarray(np.stack([random_rotation(rng, 3) for _ in range(BODIES)]))
    assert abs(float(pot.energy(x, rotations))) < 1e-13


def test_dilatation_gradient_is_f_prime_det_phi_inverse_transpose():
    # docs/theory/exact-flows.md: d/dphi V(det phi) = V'(det phi) det(phi) phi^-T
    rng = np.random.default_rng(12)
    x, phi = configuration(rng, BODIES, 3)
    det = np.linalg.det(np.asarray(phi))
    inv_t = np.swapaxes(np.linalg.inv(np.asarray(phi)), -1, -2)
    k, v0 = 1.5, 1.2
    for form, fprime in (
        ("log", k * np.log(det / v0) / det),
        ("harmonic", k * (det - v0)),
    ):
        _, gphi = generalized_forces(Dilatation(k, v0, form), x, phi)
        np.testing.assert_allclose(-gphi, (fprime * det)[:, None, None] * inv_t, rtol=1e-11)


def test_external_fields_give_analytic_forces():
    x, phi = configuration(np.random.default_rng(13), BODIES, 2)
    fx, fphi = generalized_forces(ExternalHarmonic(2.0, (0.5, -1.0)), x, phi)
    np.testing.assert_allclose(fx, -2.0 * (x - jnp.array([0.5, -1.0])), rtol=1e-14)
    assert float(jnp.max(jnp.abs(fphi))) == 0.0
    fx, _ = generalized_forces(ExternalLinear((0.0, -9.81)), x, phi)
    np.testing.assert_allclose(fx, jnp.broadcast_to(jnp.array([0.0, -9.81]), x.shape))


# --------------------------------------------------------------------------------------------
# closed-form gradients of the mutual invariants (docs/theory/exact-flows.md)


def mpow(m, a):
    return np.linalg.matrix_power(m, a)


@pytest.mark.parametrize("a", [1, 2, 3])
def test_gradient_of_mutual_trace_invariant_k(a):
    # d/dphi Tr((psi^T phi)^a) = a psi ((psi^T phi)^(a-1))^T, and symmetric in (psi, phi)
    x, phi = configuration(np.random.default_rng(20 + a), 2, 3)
    _, gphi = gradient(PairPotential.from_expression(f"K{a}", 3), x, phi)
    psi_, phi_ = np.asarray(phi)
    np.testing.assert_allclose(gphi[1], a * psi_ @ mpow(psi_.T @ phi_, a - 1).T, rtol=1e-11)
    np.testing.assert_allclose(gphi[0], a * phi_ @ mpow(phi_.T @ psi_, a - 1).T, rtol=1e-11)


@pytest.mark.parametrize("a", [1, 2, 3])
def test_gradient_of_affine_invariant_m(a):
    # the energy is (Tr(Gamma^a) + Tr(Gamma^-a))/2, Gamma = psi^-1 phi, eq. (59);
    # docs/theory/exact-flows.md:
    # d/dphi Tr((psi^-1 phi)^a) = a psi^-T ((psi^-1 phi)^(a-1))^T,
    # d/dpsi Tr((psi^-1 phi)^a) = -a psi^-T ((psi^-1 phi)^a)^T
    x, phi = configuration(np.random.default_rng(30 + a), 2, 3)
    _, gphi = gradient(PairPotential.from_expression(f"M{a}", 3), x, phi)
    psi_, phi_ = np.asarray(phi)
    g = np.linalg.solve(psi_, phi_)
    h = np.linalg.solve(phi_, psi_)
    ipsi_t, iphi_t = np.linalg.inv(psi_).T, np.linalg.inv(phi_).T
    d_phi = 0.5 * (a * ipsi_t @ mpow(g, a - 1).T - a * iphi_t @ mpow(h, a).T)
    d_psi = 0.5 * (-a * ipsi_t @ mpow(g, a).T + a * iphi_t @ mpow(h, a - 1).T)
    np.testing.assert_allclose(gphi[1], d_phi, rtol=1e-10)
    np.testing.assert_allclose(gphi[0], d_psi, rtol=1e-10)


def test_gradient_of_affine_distance_squared():
    # d/dphi (u^T C[phi] u) = -2 (C u)(phi^-1 u)^T, D^2 = u^T (C[phi_K] + C[phi_L])/2 u (75)
    x, phi = configuration(np.random.default_rng(40), 2, 3)
    gx, gphi = gradient(PairPotential.from_expression("D**2", 3), x, phi)
    u = np.asarray(x[0] - x[1])
    p = np.asarray(phi)
    cauchy = [np.linalg.inv(q).T @ np.linalg.inv(q) for q in p]
    for k in range(2):
        expected = -np.outer(cauchy[k] @ u, np.linalg.solve(p[k], u))  # (1/2) * (-2 ...)
        np.testing.assert_allclose(gphi[k], expected, rtol=1e-11)
    np.testing.assert_allclose(gx[0], (cauchy[0] + cauchy[1]) @ u, rtol=1e-11)


# --------------------------------------------------------------------------------------------
# cut-off and switching


def test_switching_function_is_c2_at_both_ends():
    r_on, r_cut = 1.0, 1.5

    def s(t):
        return switching(t, r_on, r_cut)

    def ds(t):
        return jax.grad(lambda u: jnp.sum(s(u)))(t)

    def d2s(t):
        return jax.grad(lambda u: jnp.sum(ds(u)))(t)

    eps = 1e-7
    t = jnp.array([r_on - eps, r_on + eps, r_cut - eps, r_cut + eps])
    np.testing.assert_allclose(s(t), [1.0, 1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ds(t), 0.0, atol=1e-9)
    np.testing.assert_allclose(d2s(t), 0.0, atol=1e-4)
    # not trivially flat in between: S = 1/2 and S' = -15/8 / (r_cut - r_on) at the midpoint
    mid = jnp.array([1.25])
    assert float(s(mid)[0]) == pytest.approx(0.5, rel=1e-14)
    assert float(ds(mid)[0]) == pytest.approx(-1.875 / 0.5, rel=1e-12)


def test_cut_off_energy_and_force_are_continuous_and_exactly_zero_beyond():
    pot = LennardJones(1.0, 1.0, cutoff=Cutoff(2.5, 2.0))
    e, de = radial(pot)
    plain, dplain = radial(LennardJones(1.0, 1.0))
    eps = 1e-9
    # continuity of E and dE/dr across r_on and r_cut: one-sided limits agree
    d = jnp.array([2.0 - eps, 2.0 + eps, 2.5 - eps, 2.5 + eps])
    energy, slope = np.asarray(e(d)), np.asarray(de(d))
    np.testing.assert_allclose(energy[0::2], energy[1::2], atol=1e-8)
    np.testing.assert_allclose(slope[0::2], slope[1::2], atol=1e-6)
    assert abs(slope[0]) > 0.1  # the slope that must be continuous at r_on is not zero
    inside = jnp.array([1.2, 1.5, 1.9, 2.0])
    np.testing.assert_array_equal(e(inside), plain(inside))
    np.testing.assert_array_equal(de(inside), dplain(inside))
    beyond = jnp.array([2.5, 2.7, 10.0, 1e3])
    np.testing.assert_array_equal(e(beyond), 0.0)
    np.testing.assert_array_equal(de(beyond), 0.0)
    assert np.all(np.asarray(e(jnp.array([2.1, 2.2, 2.3, 2.4]))) != 0.0)


def test_no_nan_in_gradients_for_coincident_bodies_or_singular_terms_beyond_cutoff():
    n = 2
    rng = np.random.default_rng(70)
    x, phi = configuration(rng, BODIES, n)
    x = x.at[1].set(x[0])  # coincident centres of bodies 0 and 1: r = D = 0
    for pot in (
        Gaussian(1.0, 1.0),
        Gaussian(1.0, 1.0, argument="D"),
        PairPotential.from_expression("exp(-r) + exp(-D)", n),
    ):
        gx, gphi = gradient(pot, x, phi)
        assert bool(jnp.all(jnp.isfinite(gx)) and jnp.all(jnp.isfinite(gphi)))
        np.testing.assert_allclose(jnp.sum(gx, axis=0), 0.0, atol=1e-12)
    # a NaN centre is NaN, not the coincident value (r = D = 0 read a NaN |u|^2 as 0: the
    # energy of exp(-D**2) was 1.0, found by an audit of the API)
    bad = x.at[0, 0].set(jnp.nan)
    for expr in ("exp(-r**2)", "exp(-D**2)"):
        assert np.isnan(float(PairPotential.from_expression(expr, n).energy(bad, phi))), expr
        cut = PairPotential.from_expression(expr, n, cutoff=Cutoff(1.5, variable=expr[5]))
        assert np.isnan(float(cut.energy(bad, phi))), expr  # not a pair beyond the cut-off
    # log(M1) is NaN for Gamma = -Id (M1 = -2); those pairs lie beyond the cut-off, so they
    # must contribute exactly zero energy and zero, finite forces
    pot = PairPotential.from_expression("log(M1) * exp(-r)", n, cutoff=Cutoff(1.0))
    x = jnp.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0], [3.0, 3.0]])
    phi = jnp.stack([jnp.eye(n), -jnp.eye(n), -jnp.eye(n), jnp.eye(n)])
    assert float(pot.energy(x, phi)) == 0.0
    gx, gphi = gradient(pot, x, phi)
    assert float(jnp.max(jnp.abs(gx))) == 0.0 and float(jnp.max(jnp.abs(gphi))) == 0.0
    # a single body has no pairs (the diagonal K = L is never formed)
    one = (jnp.zeros((1, n)), jnp.eye(n)[None])
    assert float(pot.energy(*one)) == 0.0 and float(LennardJones(1, 1).energy(*one)) == 0.0


# --------------------------------------------------------------------------------------------
# periodic box


def switch_numpy(s, r_on, r_cut):
    t = np.clip((s - r_on) / (r_cut - r_on), 0.0, 1.0)
    return 1.0 - t**3 * (10.0 - 15.0 * t + 6.0 * t**2)


def morse_numpy(u, phi_k, phi_l, cutoff):
    r = np.linalg.norm(u)
    v = (1.0 - np.exp(-1.5 * (r - 1.0))) ** 2 - 1.0
    return v * switch_numpy(r, cutoff.r_on, cutoff.r_cut) if r < cutoff.r_cut else 0.0


def affine_expression_numpy(u, phi_k, phi_l, cutoff):
    """exp(-D^2) (M1 - 2)^2 + r, averaged over both orders of the pair, eq. (59)."""
    r = np.linalg.norm(u)
    if r >= cutoff.r_cut:
        return 0.0
    d2 = 0.5 * (np.sum(np.linalg.solve(phi_k, u) ** 2) + np.sum(np.linalg.solve(phi_l, u) ** 2))
    m_kl = np.trace(np.linalg.solve(phi_k, phi_l))
    m_lk = np.trace(np.linalg.solve(phi_l, phi_k))
    f = 0.5 * (np.exp(-d2) * ((m_kl - 2) ** 2 + (m_lk - 2) ** 2)) + r
    return f * switch_numpy(r, cutoff.r_on, cutoff.r_cut)


def explicit_image_sum(pair_energy, x, phi, box, cutoff):
    """sum_{K<L} sum over all images x_K - x_L + m * box, m in {-1, 0, 1}^n, in NumPy."""
    n = x.shape[-1]
    total = 0.0
    for k, l in itertools.combinations(range(x.shape[0]), 2):
        for m in itertools.product((-1, 0, 1), repeat=n):
            u = x[k] - x[l] + np.asarray(m) * np.asarray(box)
            total += pair_energy(u, phi[k], phi[l], cutoff)
    return total


@pytest.mark.parametrize("n", [2, 3])
def test_minimum_image_equals_explicit_nearest_image_sum(n):
    rng = np.random.default_rng(50 + n)
    box = (3.9, 4.4, 4.1)[:n]
    _, phi = configuration(rng, BODIES, n)
    x = jnp.asarray(rng.uniform(0, 1, size=(BODIES, n)) * np.asarray(box))
    cutoff = Cutoff(1.9, 1.5)
    cases = (
        (Morse(1.0, 1.5, 1.0, cutoff=cutoff, box=box), morse_numpy),
        (
            PairPotential.from_expression(
                "exp(-D**2) * (M1 - 2)**2 + r", n, cutoff=cutoff, box=box
            ),
            affine_expression_numpy,
        ),
    )
    for periodic, reference in cases:
        expected = explicit_image_sum(reference, np.asarray(x), np.asarray(phi), box, cutoff)
        assert expected != 0.0
        assert float(periodic.energy(x, phi)) == pytest.approx(expected, rel=1e-12)
        # periodic in every body's position, translation invariant, zero total force
        shifts = [x.at[k].add(jnp.asarray(box) * jnp.array([1, -2, 3][:n])) for k in range(3)]
        moved = jnp.stack(shifts + [x + jnp.asarray(rng.normal(size=n) * 7.0) for _ in range(3)])
        np.testing.assert_allclose(
            periodic.energy(moved, jnp.stack([phi] * 6)), expected, rtol=1e-12
        )
        gx, _ = gradient(periodic, x, phi)
        np.testing.assert_allclose(jnp.sum(gx, axis=0), 0.0, atol=1e-12)
        free = dataclasses.replace(periodic, box=None)
        assert periodic.symmetry == free.symmetry - {"spatial-euclidean", "spatial-affine"}


def test_box_requires_cut_off_within_half_the_box():
    with pytest.raises(ValueError, match="cut-off on r"):
        LennardJones(1.0, 1.0, box=(5.0, 5.0))
    with pytest.raises(ValueError, match="half the shortest box edge"):
        LennardJones(1.0, 1.0, cutoff=Cutoff(3.0), box=(5.0, 8.0))
    with pytest.raises(ValueError, match="cut-off on r"):
        Gaussian(1.0, 1.0, cutoff=Cutoff(2.0, variable="D"), box=(5.0, 5.0))


# --------------------------------------------------------------------------------------------
# registry


@pytest.mark.parametrize(
    "kind, params, message",
    [
        ("lennard-jones", {"epsilon": 1.0}, "needs sigma"),
        ("lennard-jones", {"epsilon": -1.0, "sigma": 1.0}, "epsilon must be > 0"),
        ("morse", {"depth": 1, "alpha": 1, "r0": 1, "argument": "q"}, "argument must be"),
        ("gaussian", {"amplitude": 1, "width": 1, "colour": 2}, "unknown parameter"),
        ("gaussian", {"amplitude": 1, "width": 1, "r_cut": 1, "r_on": 2}, "r_on"),
        ("gaussian", {"amplitude": "big", "width": 1}, "real number"),
        ("pair", {"expr": "__import__('os')"}, "potential.2.expr"),
        ("pair", {"expr": "q * r"}, "unknown name 'q'"),
        ("pair", {"expr": "0"}, "must depend on the pair's variables"),  # crashed at energy
        ("one-body", {"expr": "M1"}, "unknown name 'M1'"),
        ("dilatation", {"stiffness": 1, "form": "cubic"}, "form must be"),
        ("elastic", {"lam": 1, "mu": 0}, "mu must be > 0"),
        ("no-such-thing", {}, "potential.2.kind: unknown potential"),
    ],
)
def test_bad_config_parameters_are_refused_naming_the_field(kind, params, message):
    with pytest.raises(ValueError) as info:
        build_potential(kind, params, n=2, field="potential.2")
    assert str(info.value).startswith("config error: potential.2")
    assert message in str(info.value)


def test_elastic_in_one_dimension_is_refused_with_the_same_energy_as_a_one_body_expression():
    """n = 1: elastic's Tr(E^2) is not a variable of its own (the command failed with "variable
    'E2' does not exist"); the refusal names the one-body expression of the same energy, and
    that expression gives lam/2 (Tr E)^2 + mu Tr(E^2) with E = (phi^2 - 1)/2."""
    import re

    lam, mu = 0.7, 1.3
    with pytest.raises(ValueError, match="one-body") as info:
        StVenantKirchhoff(lam, mu).check_dimension(1)
    expr = re.search(r'expr = "([^"]+)"', str(info.value)).group(1)
    term = build_potential("one-body", {"expr": expr}, n=1)
    phi = np.array([[[1.3]], [[0.6]]])
    E = (phi[:, 0, 0] ** 2 - 1) / 2
    assert float(term.energy(np.zeros((2, 1)), phi)) == pytest.approx(
        np.sum(lam / 2 * E**2 + mu * E**2), rel=1e-14)


def test_dimension_dependent_parameters_are_checked_against_n():
    x, phi = configuration(np.random.default_rng(61), 2, 3)
    with pytest.raises(ValueError, match="3 components"):
        ExternalLinear((0.0, 1.0)).energy(x, phi)
    with pytest.raises(ValueError, match="n = 3 entries"):
        HarmonicInvariants(1.0, reference=(2.0, 2.0)).energy(x, phi)
    with pytest.raises(ValueError, match="does not exist in dimension"):
        PairPotential(lambda M3: M3, ("M3",)).energy(x[:, :2], phi[:, :2, :2])
    with pytest.raises(ValueError, match="lam \\+ 2 mu / n"):
        StVenantKirchhoff(-0.7, 1.0).energy(x, phi)


def test_a_traced_family_parameter_is_refused_with_the_way_that_differentiates():
    """A built-in family's parameter is static: jax.grad over Dilatation(stiffness=k) is
    refused in one line naming the field and the fix; the fix (a Python function closing
    over k) gives dV/dk, here V / k = (det phi - 1)^2 / 2 summed, the family at stiffness 1."""
    x, phi = jnp.zeros((2, 2)), jnp.array([np.diag([1.2, 0.9]), np.diag([0.8, 1.1])])
    with pytest.raises(ValueError, match="dilatation.stiffness") as refused:
        jax.grad(lambda k: Dilatation(stiffness=k, form="harmonic").energy(x, phi))(2.0)
    assert "\n" not in str(refused.value) and "closes over it" in str(refused.value)
    closed = jax.grad(lambda k: OneBodyPotential(lambda det: 0.5 * k * (det - 1.0) ** 2,
                                                 ("det",)).energy(x, phi))(2.0)
    assert float(closed) == pytest.approx(
        float(Dilatation(stiffness=1.0, form="harmonic").energy(x, phi)), rel=1e-14)
