"""Quantum operators (92)-(113) and kinetic operators (76a)-(85): commutation relations,
formal Hermiticity by quadrature, exponentials as translations, and the kinetic operators
against independent Laplacians / Laplace-Beltrami operators of the classical metrics."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.polynomial.legendre import leggauss

from affinebody import kinetic
from affinebody.groups import expm
from affinebody.quantum import hamiltonians as hm
from affinebody.quantum import operators as ops

jax.config.update("jax_enable_x64", True)

HBAR = 0.7


def random_phi(rng, n, positive=True):
    phi = rng.normal(size=(n, n)) + 1.5 * np.eye(n)
    if positive and np.linalg.det(phi) < 0:
        phi = phi[::-1]
    return jnp.asarray(phi)


def gaussian_wave(rng, n):
    """Complex Gaussian times a quadratic polynomial on L(n, R)."""
    c = jnp.asarray(rng.normal(size=(n, n)))
    d = jnp.asarray(rng.normal(size=(n, n)))
    w = jnp.asarray(0.3 * rng.normal(size=(n, n)))

    def psi(phi):
        poly = 1.0 + jnp.sum(d * phi) + 1j * jnp.sum(w * phi) ** 2
        return poly * jnp.exp(-0.25 * jnp.sum(phi**2) + 1j * jnp.sum(c * phi))

    return psi


def haar_wave(coeffs, n):
    """P(phi) exp(-(Tr G + Tr G^-1)/2): decays at infinity and at det phi -> 0."""
    c1, c2 = coeffs

    def psi(phi):
        g = phi.T @ phi
        decay = jnp.exp(-0.5 * (jnp.trace(g) + jnp.trace(jnp.linalg.inv(g))))
        return (1.0 + jnp.sum(c1 * phi) + jnp.sum(c2 * phi) ** 2) * decay

    return psi


def full(op_value):
    return np.asarray(op_value)


# ----------------------------------------------------------------------------------------
# commutation relations


@pytest.mark.parametrize("n", [3])
def test_affine_spin_commutation_relations(n):
    """[Sigma^a_b, Sigma^c_d] = (hbar/i)(d^c_b Sigma^a_d - d^a_d Sigma^c_b), Sigma_hat with the
    opposite sign, [Sigma, Sigma_hat] = 0; the Lebesgue-corrected (107) versions likewise."""
    rng = np.random.default_rng(n)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    eye = jnp.eye(n)

    @jax.jit
    def relations(phi):
        out = {}
        for measure in (None, "lebesgue"):
            s = lambda f, m=measure: ops.affine_spin_op(f, HBAR, m)
            sh = lambda f, m=measure: ops.comoving_affine_spin_op(f, HBAR, m)
            ss, one = s(s(psi))(phi), s(psi)(phi)
            hh, one_h = sh(sh(psi))(phi), sh(psi)(phi)
            sh_s = s(sh(psi))(phi)  # [a,b,c,d] = Sigma_ab Sigma_hat_cd psi
            hs = sh(s(psi))(phi)  # [c,d,a,b] = Sigma_hat_cd Sigma_ab psi
            expect = (HBAR / 1j) * (
                jnp.einsum("cb,ad->abcd", eye, one) - jnp.einsum("ad,cb->abcd", eye, one)
            )
            expect_h = -(HBAR / 1j) * (
                jnp.einsum("cb,ad->abcd", eye, one_h) - jnp.einsum("ad,cb->abcd", eye, one_h)
            )
            out[str(measure)] = (
                ss - jnp.transpose(ss, (2, 3, 0, 1)) - expect,
                hh - jnp.transpose(hh, (2, 3, 0, 1)) - expect_h,
                sh_s - jnp.transpose(hs, (2, 3, 0, 1)),
                jnp.max(jnp.abs(expect)),
            )
        return out

    for defect_s, defect_h, mixed, scale in relations(phi).values():
        assert scale > 1e-3
        np.testing.assert_allclose(full(defect_s), 0, atol=1e-10 * scale)
        np.testing.assert_allclose(full(defect_h), 0, atol=1e-10 * scale)
        np.testing.assert_allclose(full(mixed), 0, atol=1e-10 * scale)


def test_total_affine_momentum_commutation_relations():
    """J = Lambda + Sigma (108) generates spatial affine maps of (x, phi): gl(n) relations of
    Sigma; and [p_a, J^c_d] = (hbar/i) delta^c_a p_d (translations form an ideal)."""
    n = 2
    rng = np.random.default_rng(11)
    inner = gaussian_wave(rng, n)
    k = jnp.asarray(rng.normal(size=n))
    psi = lambda x, phi: inner(phi) * jnp.exp(-0.5 * jnp.sum(x**2) + 1j * k @ x) * (1 + x[0])
    x = jnp.asarray(rng.normal(size=n))
    phi = random_phi(rng, n)
    eye = jnp.eye(n)
    J = lambda f: ops.total_affine_momentum_op(f, HBAR)
    P = lambda f: ops.linear_momentum_op(f, HBAR)

    @jax.jit
    def relations(x, phi):
        jj, one = J(J(psi))(x, phi), J(psi)(x, phi)
        expect = (HBAR / 1j) * (
            jnp.einsum("cb,ad->abcd", eye, one) - jnp.einsum("ad,cb->abcd", eye, one)
        )
        pj = P(J(psi))(x, phi)  # [a, c, d] = p_a J_cd psi
        jp = J(P(psi))(x, phi)  # [c, d, a]
        expect_p = (HBAR / 1j) * jnp.einsum("ca,d->acd", eye, P(psi)(x, phi))
        return jj - jnp.transpose(jj, (2, 3, 0, 1)) - expect, pj - jnp.transpose(
            jp, (2, 0, 1)
        ) - expect_p

    d1, d2 = relations(x, phi)
    np.testing.assert_allclose(full(d1), 0, atol=1e-10)
    np.testing.assert_allclose(full(d2), 0, atol=1e-10)


# ----------------------------------------------------------------------------------------
# exponentials: the unitary groups (94)-(102)


GROUPS = {
    "left": (ops.left_translation_group, ops.affine_spin_op),
    "right": (ops.right_translation_group, ops.comoving_affine_spin_op),
}


@pytest.mark.parametrize("n", [1, 3])
def test_groups_solve_their_generator_equation(n):
    """F(t) = (L(t z) psi)(phi) = psi(exp(tz) phi) (97) and F(t) = (R(t z) psi)(phi) =
    psi(phi exp(tz)) (99, corrected), bare or with the Lebesgue multiplier, solve
    dF/dt = (i/hbar) z^b_a X^a_b F with F(0) = psi for X = Sigma, Sigma_hat (93) or their
    (107) versions: by uniqueness F(t) = exp((i/hbar) t z.X) psi. (n = 2: power series below.)"""
    rng = np.random.default_rng(10 * n)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    z = jnp.asarray(0.4 * rng.normal(size=(n, n)))

    @jax.jit
    def residuals(t, phi):
        out, scale = [], []
        for group, generator in GROUPS.values():
            for measure in (None, "lebesgue"):
                flow = lambda s, ph, m=measure, gr=group: gr(psi, s * z, m)(ph)
                dfdt = jax.jvp(lambda s, fl=flow: fl(s, phi), (t,), (1.0,))[1]
                xf = generator(lambda ph, fl=flow: fl(t, ph), HBAR, measure)(phi)
                out.append(dfdt - (1j / HBAR) * ops.generator_pairing(z, xf, bodies=False))
                out.append(flow(0.0, phi) - psi(phi))
                scale.append(jnp.abs(dfdt))
        return jnp.stack(out), jnp.min(jnp.stack(scale))

    res, scale = residuals(0.8, phi)
    assert scale > 1e-4
    np.testing.assert_allclose(full(res), 0, atol=1e-11)


def test_power_series_of_affine_spins():
    """Truncated exp((i/hbar) z^b_a Sigma^a_b) psi -> psi(exp(z) phi) (97) and likewise
    Sigma_hat -> psi(phi exp z) (99): the series itself (nested autodiff), n = 2; the error
    of the partial sums falls monotonically, by > 1e3 over four orders, below 1e-7."""
    n, order = 2, 4
    rng = np.random.default_rng(5)
    c = jnp.asarray(rng.normal(size=(n, n)))
    d = jnp.asarray(rng.normal(size=(n, n)))
    psi = lambda phi: (jnp.sum(c * phi) + 1j) * (jnp.sum(d * phi) - 0.5) + jnp.sum(phi**2)
    phi = random_phi(rng, n)
    z = jnp.asarray(0.02 * rng.normal(size=(n, n)))

    def partial_sums(generator):
        term, total, sums = psi, psi(phi), []
        for j in range(1, order + 1):
            term = (
                lambda f: (
                    lambda ph: (
                        (1j / HBAR) * ops.generator_pairing(z, generator(f, HBAR)(ph), bodies=False)
                    )
                )
            )(term)
            total = total + term(phi) / math.factorial(j)
            sums.append(total)
        return jnp.stack(sums)

    @jax.jit
    def errors():
        left = partial_sums(ops.affine_spin_op) - psi(expm(z) @ phi)
        right = partial_sums(ops.comoving_affine_spin_op) - psi(phi @ expm(z))
        return jnp.abs(jnp.stack([left, right])) / jnp.abs(psi(phi))

    for err in np.asarray(errors()):
        assert err[0] > 1e-5
        assert np.all(err[1:] < err[:-1])
        assert err[-1] < min(1e-7, 1e-3 * err[0])


def test_many_body_groups_and_translations():
    """(100)-(103), (111): the total Sigma (+ hbar n N / 2i with measure) generates
    exp(z) acting on every body; V(y) = exp((i/hbar) y.p) translates (96); J generates
    (x, phi) -> (exp(z) x, exp(z) phi)."""
    n, bodies = 2, 2
    rng = np.random.default_rng(8)
    single = gaussian_wave(rng, n)
    psi = lambda phi: single(phi[0]) * single(phi[1].T + 0.3)
    phi = jnp.stack([random_phi(rng, n), random_phi(rng, n)])
    x = jnp.asarray(rng.normal(size=(bodies, n)))
    psi_x = lambda x, phi: psi(phi) * jnp.exp(-jnp.sum((x - 0.2) ** 2) + 1j * x[0, 1])
    z = jnp.asarray(0.4 * rng.normal(size=(n, n)))
    y = jnp.asarray(rng.normal(size=n))

    @jax.jit
    def residuals(t):
        out = []
        for measure in (None, "lebesgue"):
            flow = lambda s, ph, m=measure: ops.left_translation_group(psi, s * z, m)(ph)
            dfdt = jax.jvp(lambda s, fl=flow: fl(s, phi), (t,), (1.0,))[1]
            xf = ops.affine_spin_op(lambda ph, fl=flow: fl(t, ph), HBAR, measure)(phi)
            out.append(dfdt - (1j / HBAR) * ops.generator_pairing(z, xf, bodies=True))
        trans = lambda s, xx: ops.translation_group(psi_x, s * y)(xx, phi)
        dfdt = jax.jvp(lambda s: trans(s, x), (t,), (1.0,))[1]
        p = ops.linear_momentum_op(lambda xx, ph: trans(t, xx), HBAR)(x, phi)  # [N, n]
        out.append(dfdt - (1j / HBAR) * jnp.einsum("a,ka->", y, p))
        aff = lambda s, xx, ph: ops.spatial_affine_group(psi_x, s * z)(xx, ph)
        dfdt = jax.jvp(lambda s: aff(s, x, phi), (t,), (1.0,))[1]
        jop = ops.total_affine_momentum_op(lambda xx, ph: aff(t, xx, ph), HBAR)(x, phi)
        out.append(dfdt - (1j / HBAR) * ops.generator_pairing(z, jop, bodies=True))
        return jnp.stack(out)

    np.testing.assert_allclose(full(residuals(0.6)), 0, atol=1e-11)
    # (111): the Lebesgue total is the bare total plus hbar n N / 2i
    diff = jax.jit(
        lambda ph: (
            ops.affine_spin_op(psi, HBAR, "lebesgue")(ph).sum(0)
            - ops.affine_spin_op(psi, HBAR)(ph).sum(0)
            - HBAR * n * bodies / 2j * jnp.eye(n) * psi(ph)
        )
    )(phi)
    np.testing.assert_allclose(diff, 0, atol=1e-12)
    # a kinetic term of N bodies is the sum of the one-body operators (same K per body)
    kin = hm.affine_isotropic_kinetic(1.3, 0.4, 0.3, n)

    @jax.jit
    def kinetic_defect(phi):
        first = kin(lambda p0: psi(phi.at[0].set(p0)), HBAR)(phi[0])
        second = kin(lambda p1: psi(phi.at[1].set(p1)), HBAR)(phi[1])
        return kin(psi, HBAR)(phi) - first - second, jnp.abs(first)

    defect, scale = kinetic_defect(phi)
    assert scale > 1e-3
    assert abs(defect) < 1e-11


# ----------------------------------------------------------------------------------------
# Hermiticity by quadrature


def _defect_and_expected(fv, gv, xf, xg, div, weight):
    """<f, X g> - <X f, g> and i hbar <f, div g> (the integration-by-parts prediction)."""
    ip = lambda a, b: jnp.sum(weight * jnp.conj(a) * b, axis=-1)
    return ip(fv, xg) - ip(xf, gv), 1j * HBAR * ip(fv, div * gv), ip(fv, gv)


def test_hermiticity_n1_exact_quadrature():
    """n = 1 on (0, inf), trapezoid in s = log phi (spectrally exact for these functions):
    Sigma (93) is Hermitian in Haar, not in Lebesgue (defect i hbar n <f,g>); (107) is
    Hermitian in Lebesgue; pi (113) the other way round; the groups L(z) are unitary in the
    matching measure only."""
    s = jnp.linspace(-9.0, 9.0, 1201)
    h = s[1] - s[0]
    phis = jnp.exp(s)[:, None, None]
    f = lambda phi: (
        jnp.exp(-0.5 * jnp.log(phi[0, 0]) ** 2 + 0.7j * jnp.log(phi[0, 0])) * (1 + phi[0, 0])
    )
    g = lambda phi: jnp.exp(-0.8 * (jnp.log(phi[0, 0]) - 0.3) ** 2) * (1 - 0.5j * phi[0, 0])
    weights = {"haar": h * jnp.ones_like(s), "lebesgue": h * jnp.exp(s)}  # dphi/phi, dphi
    for name, w in weights.items():  # w = density * dphi/ds
        np.testing.assert_allclose(ops.configuration_density(phis, name) * h * jnp.exp(s), w)
    divs = {  # div_w v for (Sigma, pi) in measure w (operators.py docstring), n = 1
        "haar": (0.0, -1.0 / jnp.exp(s)),
        "lebesgue": (1.0, 0.0),
    }
    ev = jax.jit(lambda fn: jax.vmap(lambda p: fn(p).reshape(()))(phis), static_argnums=0)
    fv, gv = ev(f), ev(g)
    for op_measure, hermitian_in in [(None, "haar"), ("lebesgue", "lebesgue")]:
        sf = ev(ops.affine_spin_op(f, HBAR, op_measure))
        sg = ev(ops.affine_spin_op(g, HBAR, op_measure))
        for measure, w in weights.items():
            defect, predicted, norm = _defect_and_expected(fv, gv, sf, sg, 0, w)
            if measure == hermitian_in:
                assert abs(defect) < 1e-11
            elif op_measure is None:  # bare Sigma in Lebesgue: div = n = 1
                assert abs(norm) > 0.1
                expected = _defect_and_expected(fv, gv, sf, sg, divs[measure][0], w)[1]
                np.testing.assert_allclose(defect, expected, atol=1e-11)
            else:
                assert abs(defect) > 1e-2
    for op_measure, hermitian_in in [(None, "lebesgue"), ("haar", "haar")]:
        pf = ev(ops.canonical_momentum_op(f, HBAR, op_measure))
        pg = ev(ops.canonical_momentum_op(g, HBAR, op_measure))
        for measure, w in weights.items():
            defect = _defect_and_expected(fv, gv, pf, pg, 0, w)[0]
            if measure == hermitian_in:
                assert abs(defect) < 1e-11
            elif op_measure is None:
                expected = _defect_and_expected(fv, gv, pf, pg, divs[measure][1], w)[1]
                assert abs(expected) > 1e-2
                np.testing.assert_allclose(defect, expected, atol=1e-11)
    # unitarity of L(z) = Psi(e^z phi) (97) in Haar; with the multiplier in Lebesgue
    z = jnp.asarray([[0.4]])
    norm = lambda vals, w: jnp.sum(w * jnp.abs(vals) ** 2)
    bare = ev(ops.left_translation_group(f, z))
    corrected = ev(ops.left_translation_group(f, z, "lebesgue"))
    np.testing.assert_allclose(norm(bare, weights["haar"]), norm(fv, weights["haar"]), rtol=1e-11)
    np.testing.assert_allclose(
        norm(corrected, weights["lebesgue"]), norm(fv, weights["lebesgue"]), rtol=1e-11
    )
    assert abs(norm(bare, weights["lebesgue"]) / norm(fv, weights["lebesgue"]) - 1) > 0.1


def test_hermiticity_n1_with_translations_alpha_measure():
    """On R x GL+(1) with alpha = |det phi|^(-n-1) dx dphi (89): J = Lambda + Sigma (108) is
    formally Hermitian with no correction, but Sigma alone is not (defect -i hbar <f, g>: the
    paper's claim that (93) is Hermitian in L^2(alpha) fails; it holds for lambda x dx)."""
    xs = jnp.linspace(-8.0, 8.0, 161)
    s = jnp.linspace(-8.0, 8.0, 321)
    hx, hs = xs[1] - xs[0], s[1] - s[0]
    X, S = jnp.meshgrid(xs, s, indexing="ij")
    X, S = X.ravel(), S.ravel()
    alpha = hx * hs * jnp.exp(-S)  # |phi|^-2 dphi dx = e^{-s} ds dx
    f = lambda x, phi: (
        jnp.exp(-0.5 * x[0] ** 2 - 0.5 * jnp.log(phi[0, 0]) ** 2 + 0.4j * x[0]) * (1 + phi[0, 0])
    )
    g = lambda x, phi: (
        jnp.exp(-((x[0] - 0.3) ** 2) - jnp.log(phi[0, 0]) ** 2) * (1 + 0.5j * x[0] * phi[0, 0])
    )
    ev = jax.jit(
        lambda fn: jax.vmap(lambda x, sv: fn(x[None], jnp.exp(sv)[None, None]).reshape(()))(X, S),
        static_argnums=0,
    )
    fv, gv = ev(f), ev(g)
    jf = ev(ops.total_affine_momentum_op(f, HBAR))
    jg = ev(ops.total_affine_momentum_op(g, HBAR))
    sf = ev(ops.on_internal(ops.affine_spin_op, f, hbar=HBAR))
    sg = ev(ops.on_internal(ops.affine_spin_op, g, hbar=HBAR))
    defect_j, _, norm = _defect_and_expected(fv, gv, jf, jg, 0, alpha)
    defect_s, predicted, _ = _defect_and_expected(fv, gv, sf, sg, -1.0, alpha)
    assert abs(norm) > 0.05
    assert abs(defect_j) < 1e-10
    np.testing.assert_allclose(defect_s, predicted, atol=1e-10)
    assert abs(defect_s) > 1e-2


@pytest.fixture(scope="module")
def two_polar_grid_n2():
    """Product rule on GL+(2) in two-polar coordinates phi = L(a) diag(e^{s+u/2}, e^{s-u/2})
    R(b)^T: trapezoid in the angles and s, Gauss-Legendre in u in (0, 3.6); Haar weight
    sinh(u), Lebesgue weight sinh(u) e^{4s} (common constant factors dropped)."""
    na, ns, nu = 8, 81, 32  # angular degree of every integrand < 8: trapezoid exact
    ang = jnp.arange(na) * 2 * jnp.pi / na
    s = jnp.linspace(-2.0, 2.0, ns)
    u_nodes, u_w = leggauss(nu)
    u = 1.8 * (jnp.asarray(u_nodes) + 1)
    uw = 1.8 * jnp.asarray(u_w)
    A, B, S, U = (a.ravel() for a in jnp.meshgrid(ang, ang, s, u, indexing="ij"))
    W = jnp.meshgrid(ang, ang, s, uw, indexing="ij")[3].ravel() * jnp.sinh(U)
    rot = lambda t: jnp.stack(
        [jnp.stack([jnp.cos(t), -jnp.sin(t)]), jnp.stack([jnp.sin(t), jnp.cos(t)])]
    )
    phis = jax.vmap(
        lambda a, b, s, u: rot(a) @ jnp.diag(jnp.exp(jnp.stack([s + u / 2, s - u / 2]))) @ rot(b).T
    )(A, B, S, U)
    return phis, {"haar": W, "lebesgue": W * jnp.exp(4 * S)}


def test_hermiticity_n2_two_polar_quadrature(two_polar_grid_n2):
    """Every component of Sigma, Sigma_hat (93) is Hermitian in the Haar measure on GL+(2);
    in Lebesgue measure their defect is i hbar n delta^a_b <f, g> and (107) repairs it; pi
    (113) is Hermitian in Lebesgue, its Haar defect is i hbar <f, -n phi^-T g> and the Haar
    correction repairs it."""
    phis, weights = two_polar_grid_n2
    n = 2
    rng = np.random.default_rng(3)
    f = haar_wave(
        (jnp.asarray(rng.normal(size=(n, n))), 0.5j * jnp.asarray(rng.normal(size=(n, n)))), n
    )
    g = haar_wave(
        (jnp.asarray(1j * rng.normal(size=(n, n))), 0.4 * jnp.asarray(rng.normal(size=(n, n)))), n
    )

    @jax.jit
    def values(phis):
        ev = lambda fn: jax.vmap(fn)(phis)
        out = {"f": ev(f), "g": ev(g), "inv": ev(jnp.linalg.inv)}
        for name, make, measure in [
            ("sigma", ops.affine_spin_op, None),
            ("sigma_hat", ops.comoving_affine_spin_op, None),
            ("sigma_leb", ops.affine_spin_op, "lebesgue"),
            ("sigma_hat_leb", ops.comoving_affine_spin_op, "lebesgue"),
            ("pi", ops.canonical_momentum_op, None),
            ("pi_haar", ops.canonical_momentum_op, "haar"),
        ]:
            out[name] = (ev(make(f, HBAR, measure)), ev(make(g, HBAR, measure)))
        return out

    v = values(phis)
    fv, gv = v["f"], v["g"]
    ip = lambda a, b, w: jnp.sum(w * jnp.conj(a) * b)
    norm = {m: ip(fv, gv, w) for m, w in weights.items()}
    assert min(abs(x) for x in norm.values()) > 1e-3
    scale = {m: jnp.sqrt(ip(fv, fv, w) * ip(gv, gv, w)).real for m, w in weights.items()}

    def defect(name, a, b, measure):
        xf, xg = v[name][0][:, a, b], v[name][1][:, a, b]
        w = weights[measure]
        return ip(fv, xg, w) - ip(xf, gv, w)

    tol = lambda m: 1e-9 * scale[m]
    for a in range(n):
        for b in range(n):
            for name in ("sigma", "sigma_hat"):
                assert abs(defect(name, a, b, "haar")) < tol("haar")
                expected = 1j * HBAR * n * (a == b) * norm["lebesgue"]
                assert abs(defect(name, a, b, "lebesgue") - expected) < tol("lebesgue")
                assert abs(defect(name + "_leb", a, b, "lebesgue")) < tol("lebesgue")
            assert abs(defect("pi", a, b, "lebesgue")) < tol("lebesgue")
            expected = 1j * HBAR * ip(fv, -n * v["inv"][:, a, b] * gv, weights["haar"])
            assert abs(expected) > 1e-3 * scale["haar"]
            assert abs(defect("pi", a, b, "haar") - expected) < tol("haar")
            assert abs(defect("pi_haar", a, b, "haar")) < tol("haar")


def test_lebesgue_corrections_are_the_unitary_change_of_measure():
    """(107): Sigma' = U Sigma U^-1 with U = |det phi|^(-n/2): L^2(Haar) -> L^2(Lebesgue); and
    the Haar pi is U^-1 pi U. n = 3, pointwise autodiff."""
    n = 3
    rng = np.random.default_rng(4)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    u = lambda ph: jnp.abs(jnp.linalg.det(ph)) ** (-n / 2)
    psi_x = lambda x, ph: psi(ph) * jnp.exp(1j * x @ ph[:, 0] - jnp.sum(x**2))
    x = jnp.asarray(rng.normal(size=n))

    @jax.jit
    def pairs(x, phi):
        p = ops.linear_momentum_op(psi_x, HBAR)(x, phi)
        return (
            (
                ops.affine_spin_op(psi, HBAR, "lebesgue")(phi),
                u(phi) * ops.affine_spin_op(lambda ph: psi(ph) / u(ph), HBAR)(phi),
            ),
            (
                ops.comoving_affine_spin_op(psi, HBAR, "lebesgue")(phi),
                u(phi) * ops.comoving_affine_spin_op(lambda ph: psi(ph) / u(ph), HBAR)(phi),
            ),
            (
                ops.canonical_momentum_op(psi, HBAR, "haar")(phi),
                ops.canonical_momentum_op(lambda ph: psi(ph) * u(ph), HBAR)(phi) / u(phi),
            ),
            (ops.comoving_linear_momentum_op(psi_x, HBAR)(x, phi), phi.T @ p),  # (92)
        )

    for lhs, rhs in pairs(x, phi):
        np.testing.assert_allclose(lhs, rhs, atol=1e-12)


# ----------------------------------------------------------------------------------------
# kinetic operators


def _complex_hessian(psi, phi):
    re = jax.hessian(lambda p: jnp.real(psi(p)))(phi)
    im = jax.hessian(lambda p: jnp.imag(psi(p)))(phi)
    return re + 1j * im


def laplace_beltrami(lagrangian, psi, phi):
    """(1/sqrt|g|) d_i (sqrt|g| g^ij d_j psi) for the metric g of T = lagrangian(phi, xi),
    g = Hessian in xi on R^{n^2} (independent of the quantum operators)."""
    n = phi.shape[-1]

    def metric(ph):
        return jax.hessian(lambda xi: lagrangian(ph, xi))(jnp.zeros((n, n))).reshape(n * n, n * n)

    def flux(ph):
        g = metric(ph)
        vol = jnp.sqrt(jnp.abs(jnp.linalg.det(g)))
        grad = jax.jacfwd(psi)(ph).reshape(n * n)
        return vol * jnp.linalg.solve(g, grad)

    div = jnp.trace(jax.jacfwd(flux)(phi).reshape(n * n, n * n))
    return div / jnp.sqrt(jnp.abs(jnp.linalg.det(metric(phi))))


def omega_hat(phi, xi):
    return jnp.linalg.solve(phi, xi)


def omega(phi, xi):
    return xi @ jnp.linalg.inv(phi)


def lagrangian_affine(I, A, B, spatial):  # noqa: E741
    """(72)-(74): I/2 Tr(W^T W) + A/2 Tr(W^2) + B/2 (Tr W)^2, W = Omega_hat or Omega."""

    def lag(phi, xi):
        w = omega(phi, xi) if spatial else omega_hat(phi, xi)
        return 0.5 * (I * jnp.trace(w.T @ w) + A * jnp.trace(w @ w) + B * jnp.trace(w) ** 2)

    return lag


@pytest.mark.parametrize("n", [2, 3])
def test_dalembert_is_weighted_laplacian(n):
    """(76a) with pi = (hbar/i) d/dphi: T = -(hbar^2/2) (J^-1)_ab d^2/dphi^j_a dphi^j_b."""
    rng = np.random.default_rng(20 + n)
    a = rng.normal(size=(n, n))
    J = jnp.asarray(a @ a.T + n * np.eye(n))
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n, positive=False)
    value = jax.jit(hm.dalembert_kinetic(J)(psi, HBAR))(phi)
    hess = jax.jit(_complex_hessian, static_argnums=0)(psi, phi)
    expected = -(HBAR**2) / 2 * jnp.einsum("jajb,ab->", hess, jnp.linalg.inv(J))
    assert abs(expected) > 1e-3
    np.testing.assert_allclose(value, expected, rtol=1e-10)


def _lb_cases():
    rng = np.random.default_rng(30)
    j3 = rng.normal(size=(3, 3))
    h2 = rng.normal(size=(2, 2))
    return [
        (
            "af-is",
            3,
            hm.affine_isotropic_kinetic(1.1, -0.3, 0.2, 3),
            lagrangian_affine(1.1, -0.3, 0.2, False),
        ),
        (
            "is-af",
            2,
            hm.isotropic_affine_kinetic(1.3, 0.4, -0.2, 2),
            lagrangian_affine(1.3, 0.4, -0.2, True),
        ),
        (
            "af-af",
            2,
            hm.affine_affine_kinetic(0.9, 0.5, 2),
            lagrangian_affine(0.0, 0.9, 0.5, False),
        ),
        (
            "af-J",
            3,
            hm.affine_J_kinetic(j3 @ j3.T + 3 * np.eye(3)),
            lambda phi, xi: (
                0.5
                * jnp.trace(omega_hat(phi, xi) @ (j3 @ j3.T + 3 * np.eye(3)) @ omega_hat(phi, xi).T)
            ),
        ),
        (
            "H-af",
            2,
            hm.H_affine_kinetic(h2 @ h2.T + 2 * np.eye(2)),
            lambda phi, xi: (
                0.5 * jnp.trace(omega(phi, xi) @ (h2 @ h2.T + 2 * np.eye(2)) @ omega(phi, xi).T)
            ),
        ),
    ]


@pytest.mark.parametrize("case", _lb_cases(), ids=lambda c: f"{c[0]}-n{c[1]}")
def test_affine_kinetic_operators_are_laplace_beltrami(case):
    """Substituting Sigma_hat / Sigma into (85), (84a), (72), (79a), (81a) (with the constants
    (86)) gives exactly -(hbar^2/2) Laplace-Beltrami of the classical metric (74), (73), (72),
    (65), (67): no ordering corrections (docs/theory/two-polar.md)."""
    _, n, kinetic, lagrangian = case
    rng = np.random.default_rng(40 + n)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    value = jax.jit(kinetic(psi, HBAR))(phi)
    expected = -(HBAR**2) / 2 * jax.jit(lambda ph: laplace_beltrami(lagrangian, psi, ph))(phi)
    assert abs(expected) > 1e-3
    np.testing.assert_allclose(value, expected, rtol=1e-9)


@pytest.mark.parametrize("side", ["left", "right"])
def test_kinetic_module_hamiltonians_quantise_to_laplace_beltrami(side):
    """l-af (70)/(82a) and r-af (71)/(83a) from affinebody.kinetic with a random SPD bi-tensor:
    its classical Hamiltonian, quantised by kinetic_operator_from_hamiltonian, equals
    -(hbar^2/2) Laplace-Beltrami of its Lagrangian's metric (independent computation)."""
    n = 2
    rng = np.random.default_rng(50 + len(side))
    a = rng.normal(size=(n * n, n * n))
    bitensor = jnp.asarray((a @ a.T + n * n * np.eye(n * n)).reshape(n, n, n, n))
    term = kinetic.LeftInvariant(bitensor) if side == "left" else kinetic.RightInvariant(bitensor)
    term.check()
    generator = "comoving_affine_spin" if side == "left" else "affine_spin"
    quantum = hm.kinetic_operator_from_hamiltonian(term.hamiltonian, n, generator)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)

    @jax.jit
    def both(phi):
        lb = laplace_beltrami(term.lagrangian, psi, phi)
        return quantum(psi, HBAR)(phi), -(HBAR**2) / 2 * lb

    value, expected = both(phi)
    assert abs(expected) > 1e-3
    np.testing.assert_allclose(value, expected, rtol=1e-9)


def test_affine_models_are_casimirs_plus_quadratic_term():
    """(85) = Tr(Sigma^2)/(2M) + (Tr Sigma)^2/(2B~) + sum_{a<b} V_ab^2/(2 I~) with the GL(n)
    Casimirs built from the *spatial* Sigma and V the vorticity; (84a) likewise with the spin;
    af-af (72) is the same operator from Sigma and from Sigma_hat. n = 3."""
    n = 3
    I, A, B = 1.2, 0.35, 0.25  # noqa: E741
    inv_i, _, inv_b = hm.tilde_constants(I, A, B, n)
    rng = np.random.default_rng(60)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    iu = np.triu_indices(n, 1)

    @jax.jit
    def check(phi):
        sig2 = ops.affine_spin_op(ops.affine_spin_op(psi, HBAR), HBAR)(phi)  # [a,b,c,d]
        casimir2 = jnp.einsum("abba->", sig2)
        casimir1 = jnp.einsum("aacc->", sig2)
        vort2 = ops.vorticity_op(ops.vorticity_op(psi, HBAR), HBAR)(phi)
        spin2 = ops.spin_op(ops.spin_op(psi, HBAR), HBAR)(phi)
        v_sq = jnp.sum(vort2[iu[0], iu[1], iu[0], iu[1]])
        s_sq = jnp.sum(spin2[iu[0], iu[1], iu[0], iu[1]])
        base = casimir2 / (2 * (I + A)) + inv_b * casimir1 / 2
        af_af_s = hm.affine_affine_kinetic(A, B, n, "affine_spin")(psi, HBAR)(phi)
        af_af_h = hm.affine_affine_kinetic(A, B, n)(psi, HBAR)(phi)
        af_af_expected = casimir2 / (2 * A) - B / (A * (A + n * B)) * casimir1 / 2
        return (
            hm.affine_isotropic_kinetic(I, A, B, n)(psi, HBAR)(phi) - base - inv_i * v_sq / 2,
            hm.isotropic_affine_kinetic(I, A, B, n)(psi, HBAR)(phi) - base - inv_i * s_sq / 2,
            af_af_s - af_af_h,
            af_af_s - af_af_expected,
            jnp.abs(v_sq - s_sq),
        )

    *defects, differ = check(phi)
    assert differ > 1e-3  # spin and vorticity terms genuinely differ
    np.testing.assert_allclose(np.asarray(defects), 0, atol=1e-10)


def test_translational_kinetic_forms_and_full_hamiltonian():
    """(77a): (1/2M) p^T p = (1/2M) p_hat^T G^-1 p_hat; (78a): (1/2M) p_hat^T p_hat =
    (1/2M) p^T C^-1 p; and H = T_tr + T_int + V (114), (115) for d'Alembert equals
    -(hbar^2/2M) Lap_x - (hbar^2/2) J^-1-Laplacian_phi + V (independent Hessians)."""
    n, mass = 2, 1.7
    rng = np.random.default_rng(70)
    inner = gaussian_wave(rng, n)
    k = jnp.asarray(rng.normal(size=n))
    psi = lambda x, phi: inner(phi) * jnp.exp(-0.5 * x @ phi @ phi.T @ x + 1j * k @ x) * (1 + x[0])
    x = jnp.asarray(rng.normal(size=n))
    phi = random_phi(rng, n)
    p_hat = lambda f: ops.comoving_linear_momentum_op(f, HBAR)
    p = lambda f: ops.linear_momentum_op(f, HBAR)
    J = jnp.asarray(np.diag([1.3, 0.8]))
    pot = lambda x, phi: jnp.sum(x**2) + jnp.linalg.det(phi) ** 2

    @jax.jit
    def values(x, phi):
        ginv = jnp.linalg.inv(phi.T @ phi)
        t_dal = hm.dalembert_translational_kinetic(mass, n)(psi, HBAR)(x, phi)
        via_g = jnp.einsum("ab,ab->", p_hat(p_hat(psi))(x, phi), ginv) / (2 * mass)
        t_aff = hm.affine_translational_kinetic(mass, n)(psi, HBAR)(x, phi)
        via_c = jnp.einsum("ab,ab->", p(p(psi))(x, phi), phi @ phi.T) / (2 * mass)
        H = hm.hamiltonian_op(
            psi, hm.dalembert_kinetic(J), hm.dalembert_translational_kinetic(mass, n), pot, HBAR
        )
        hx = _complex_hessian(lambda xx: psi(xx, phi), x)
        hphi = _complex_hessian(lambda ph: psi(x, ph), phi)
        expected = (
            -(HBAR**2) / (2 * mass) * jnp.trace(hx)
            - HBAR**2 / 2 * jnp.einsum("jajb,ab->", hphi, jnp.linalg.inv(J))
            + pot(x, phi) * psi(x, phi)
        )
        return t_dal, via_g, t_aff, via_c, H(x, phi), expected

    t_dal, via_g, t_aff, via_c, h_value, expected = values(x, phi)
    np.testing.assert_allclose(t_dal, via_g, rtol=1e-10)
    np.testing.assert_allclose(t_aff, via_c, rtol=1e-10)
    assert abs(t_aff - t_dal) > 1e-3
    np.testing.assert_allclose(h_value, expected, rtol=1e-10)


def test_lebesgue_and_haar_kinetic_operators_are_unitarily_equivalent():
    """T built from (107) is U T_Haar U^-1 with U = |det phi|^(-n/2) (af-is), and the Haar
    d'Alembert operator (Haar-Hermitian pi) is U^-1 T U."""
    n = 2
    rng = np.random.default_rng(80)
    psi = gaussian_wave(rng, n)
    phi = random_phi(rng, n)
    u = lambda ph: jnp.abs(jnp.linalg.det(ph)) ** (-n / 2)
    kin = hm.affine_isotropic_kinetic(1.3, 0.4, 0.3, n)
    dal = hm.dalembert_kinetic(jnp.eye(n))

    @jax.jit
    def pairs(phi):
        return (
            kin(psi, HBAR, "lebesgue")(phi),
            u(phi) * kin(lambda ph: psi(ph) / u(ph), HBAR)(phi),
            dal(psi, HBAR, "haar")(phi),
            dal(lambda ph: psi(ph) * u(ph), HBAR)(phi) / u(phi),
        )

    a, b, c, d = pairs(phi)
    np.testing.assert_allclose(a, b, rtol=1e-10)
    np.testing.assert_allclose(c, d, rtol=1e-10)
    assert abs(a - kin(psi, HBAR)(phi)) > 1e-3


def test_bad_input_raises_one_line_value_error():
    with pytest.raises(ValueError, match="measure"):
        ops.density_exponent("riemann", 2)
    with pytest.raises(ValueError, match="I != \\|A\\|"):
        hm.affine_isotropic_kinetic(0.5, 0.5, 0.1, 2)
    with pytest.raises(ValueError, match="positive definite"):
        hm.dalembert_kinetic(-jnp.eye(2))
