"""Densities of the invariants (quantum/densities.py) against closed forms derived from the
Gaussian ground state of the oscillator (docs/theory/densities.md), symmetries, normalisation
and the honesty of the error estimate."""

import math

import numpy as np
import pytest
from scipy import integrate, special

from affinebody.quantum import spectra as sp
from affinebody.quantum.densities import density_at, joint_density, marginal_densities


def oscillator(k):
    return lambda Q: 0.5 * k * np.sum(Q**2, axis=-1)


HBAR, INERTIA, K = 0.8, 1.3, 2.0
#: variance of each entry of phi in the ground state: hbar / (2 I omega), omega = sqrt(k / I)
S2 = HBAR / (2 * INERTIA * math.sqrt(K / INERTIA))


@pytest.fixture(scope="module")
def n2_oscillator():
    return sp.solve("dalembert", 2, oscillator(K), HBAR, inertia=INERTIA, levels=5,
                    settings=sp.Settings(basis_size=12))


def _level(spectrum, key, index=0):
    block = spectrum.blocks[key]
    return sp.Level(float(block.energies[index]), 1, block.sectors, 0.0, key, index)


def _check(d, tol=1e-8):
    """Every density converged, integrates to 1 and is nonnegative."""
    assert abs(d["normalisation"] - 1) < 1e-10
    for name, m in d["details"].items():
        assert m.converged and m.error <= tol * np.max(m.density), name
        assert abs(m.integral - 1) < 1e-9, (name, m.integral)
        assert np.all(m.density >= -1e-14), name


def test_n2_ground_state_marginals_match_closed_forms(n2_oscillator):
    """det phi: Laplace e^{-|y|/s^2}/(2 s^2); Tr G: s^2 chi^2_4; Q1, Q2 from the joint density
    (Q1^2 - Q2^2) e^{-|Q|^2/2s^2} / (2 s^4) on Q1 > |Q2| in erf form; pointwise to 1e-8."""
    d = marginal_densities(n2_oscillator, n2_oscillator.levels[0])
    _check(d)
    assert d["variables"] == "Q"
    s2, s = S2, math.sqrt(S2)
    x, p = d["marginals"]["det"]
    assert np.max(np.abs(p - np.exp(-np.abs(x) / s2) / (2 * s2))) < 1e-8
    assert 0.0 in x and np.max(np.abs(p - p[::-1])) < 1e-13  # symmetric under det -> -det
    x, p = d["marginals"]["trG"]
    assert np.max(np.abs(p - (x / s2) * np.exp(-x / (2 * s2)) / (4 * s2))) < 1e-8
    x, p = d["marginals"]["Q1"]
    e0 = s * math.sqrt(2 * math.pi) * special.erf(x / (s * math.sqrt(2)))
    e2 = s2 * (e0 - 2 * x * np.exp(-x**2 / (2 * s2)))
    assert np.max(np.abs(p - np.exp(-x**2 / (2 * s2)) * (x**2 * e0 - e2) / (2 * s2**2))) < 1e-8
    x, p = d["marginals"]["Q2"]
    a = np.abs(x)
    g0 = s * math.sqrt(math.pi / 2) * special.erfc(a / (s * math.sqrt(2)))
    g2 = s2 * (a * np.exp(-a**2 / (2 * s2)) + g0)
    assert np.max(np.abs(p - np.exp(-x**2 / (2 * s2)) * (g2 - x**2 * g0) / (2 * s2**2))) < 1e-8
    o = d["orientation"]
    assert np.all(o["L_angle"] == 1 / (2 * np.pi)) and np.all(o["R_angle"] == 1 / (2 * np.pi))


def test_n2_excited_conformal_state_has_the_asymmetric_det_density(n2_oscillator):
    """Sector (m1, m2) = (1, 0), Psi ~ z x Gaussian: |z|^2 ~ Gamma(2, s^2), |w|^2 ~ Exp(s^2),
    so det = |z|^2 - |w|^2 has e^{-y/s^2}(y/(2 s^4) + 1/(4 s^2)) for y >= 0 and
    e^{y/s^2}/(4 s^2) below, and Tr G = 2(|z|^2 + |w|^2) with |z|^2 + |w|^2 ~ Gamma(3, s^2)."""
    lv = _level(n2_oscillator, (1, 0))
    assert abs(lv.energy - 3 * HBAR * math.sqrt(K / INERTIA)) < 1e-9
    d = marginal_densities(n2_oscillator, lv)
    _check(d)
    s2 = S2
    x, p = d["marginals"]["det"]
    ref = np.where(x >= 0, np.exp(-np.abs(x) / s2) * (x / (2 * s2**2) + 1 / (4 * s2)),
                   np.exp(np.minimum(x, 0) / s2) / (4 * s2))
    assert np.max(np.abs(p - ref)) < 1e-8
    x, p = d["marginals"]["trG"]
    R = x / 2
    assert np.max(np.abs(p - R**2 * np.exp(-R / s2) / (2 * s2**3) / 2)) < 1e-8


ANHARMONIC = "0.5*trG + 0.1*det**2 + 0.05*trG**2"


def _anharmonic(extra):
    from affinebody.quantum.config import compile_potential

    return sp.solve("dalembert", 2, compile_potential(ANHARMONIC + extra, 2), 1.0, inertia=1.0,
                    levels=1, settings=sp.Settings(basis_size=16))


def test_n2_reflection_symmetric_state_gives_symmetric_densities_and_honest_errors():
    """V(Q1, Q2) = V(Q1, -Q2) (phi -> phi diag(1, -1)): the ground state's densities of det and
    Q2 are even to round-off; adding 0.3 det breaks it visibly. The reported error bounds the
    difference to a 4x finer rule."""
    s = _anharmonic("")
    d = marginal_densities(s, s.levels[0])
    _check(d)
    for name in ("det", "Q2"):
        x, p = d["marginals"][name]
        assert np.all(x == -x[::-1])
        assert np.max(np.abs(p - p[::-1])) < 1e-13 * np.max(p)
        m = d["details"][name]
        fine = density_at(joint_density(s, s.levels[0]), name, x, 4 * m.nodes)
        assert np.max(np.abs(fine - p)) <= max(m.error, 1e-12 * np.max(p))
    t = _anharmonic(" + 0.3*det")
    x, p = marginal_densities(t, t.levels[0])["marginals"]["det"]
    assert np.max(np.abs(p - p[::-1])) > 1e-3


def _affine_sigma_check(n, settings, c=1.5, I=1.0, A=0.2, B=0.3):  # noqa: E741
    """af-is with V = c sum q_a^2: det phi is log-normal, <(ln det)^2> = l^2/2 with
    l^2 = hbar / sqrt(mass x spring), mass (I + A + nB)/n, spring 2c/n."""
    from affinebody.quantum.config import compile_potential

    # an expression (not a Python function): the sector search can certify its bounds and stop
    V = compile_potential(f"{c}*(" + " + ".join(f"q{a}**2" for a in range(1, n + 1)) + ")", n)
    s = sp.solve("af-is", n, V, 1.0, I=I, A=A, B=B, levels=1, settings=settings,
                 sectors="scalar" if n == 3 else "auto")
    d = marginal_densities(s, s.levels[0])
    _check(d)
    assert d["variables"] == "q"
    l2 = 1 / math.sqrt((I + A + n * B) / n * 2 * c / n)
    x, p = d["marginals"]["det"]
    ref = np.exp(-np.log(x) ** 2 / l2) / (math.sqrt(math.pi * l2) * x)
    assert np.max(np.abs(p - ref)) < 1e-8
    return s, d


def test_n2_affine_dilatation_is_log_normal_and_q1_mirrors_q2():
    s, _ = _affine_sigma_check(2, sp.Settings(basis_size=16, centre=0.0))
    joint = joint_density(s, s.levels[0])
    y = np.linspace(-2.0, 2.0, 9)
    # V even under q -> -q: (q1, q2) -> (-q2, -q1)
    assert np.max(np.abs(density_at(joint, "q1", y, 96) - density_at(joint, "q2", -y, 96))) < 1e-13


N3 = dict(hbar=1.0, inertia=1.0, k=1.0)


@pytest.fixture(scope="module")
def n3_ground():
    s = sp.solve("dalembert", 3, oscillator(N3["k"]), N3["hbar"], inertia=N3["inertia"],
                 levels=1, settings=sp.Settings(basis_size=4, scale=1.0, check_shrink=2),
                 sectors="scalar")
    return marginal_densities(s, s.levels[0])


def _chamber_inner(Q1, Q2, s2):
    """int_{-Q2}^{Q2} (Q1^2 - Q3^2)(Q2^2 - Q3^2) e^{-Q3^2/2s^2} dQ3 in closed form."""
    s, e = math.sqrt(s2), math.exp(-Q2 * Q2 / (2 * s2))
    m0 = s * math.sqrt(2 * math.pi) * math.erf(Q2 / (s * math.sqrt(2)))
    m2 = s2 * (m0 - 2 * Q2 * e)
    m4 = s2 * (3 * m2 - 2 * Q2**3 * e)
    return Q1**2 * Q2**2 * m0 - (Q1**2 + Q2**2) * m2 + m4


def test_n3_ground_state_marginals_match_closed_forms(n3_ground):
    """phi 3x3 Gaussian, entries of variance s^2 = 1/2: Tr G = s^2 chi^2_9; det phi by the
    row expansion (docs/theory/densities.md); Q1, Q2 from the joint density
    prod (Q_a^2 - Q_b^2) e^{-|Q|^2/2s^2} on the chamber (inner integral in closed form, the
    rest by scipy quad); pointwise to 1e-8; det even to round-off."""
    d = n3_ground
    _check(d)
    s2 = N3["hbar"] / (2 * N3["inertia"] * math.sqrt(N3["k"] / N3["inertia"]))
    s = math.sqrt(s2)
    x, p = d["marginals"]["trG"]
    ref = x**3.5 * np.exp(-x / (2 * s2)) / (2**4.5 * special.gamma(4.5) * s**9)
    assert np.max(np.abs(p - ref)) < 1e-8
    x, p = d["marginals"]["det"]
    assert 0.0 in x and np.max(np.abs(p - p[::-1])) < 1e-13
    pick = np.arange(0, len(x), 7)
    ref = [integrate.quad(lambda a, y=y: math.exp(-abs(y) / (s**3 * math.sqrt(a)) - a / 2), 0,
                          np.inf, epsabs=1e-13, epsrel=1e-12)[0] for y in x[pick]]
    ref = np.array(ref) / (2 * s**3 * math.sqrt(2 * math.pi))
    assert np.max(np.abs(p[pick] - ref)) < 1e-8

    def weight(Q1, Q2):
        return (Q1**2 - Q2**2) * math.exp(-(Q1**2 + Q2**2) / (2 * s2)) * _chamber_inner(Q1, Q2,
                                                                                        s2)

    def q1_raw(y):
        return integrate.quad(lambda u: weight(y, u), 0, y, epsabs=1e-14, epsrel=1e-12)[0]

    Z = integrate.quad(q1_raw, 0, np.inf, epsabs=1e-14, epsrel=1e-12)[0]
    for name, raw in (("Q1", q1_raw),
                      ("Q2", lambda y: integrate.quad(lambda u: weight(u, y), y, np.inf,
                                                      epsabs=1e-14, epsrel=1e-12)[0])):
        x, p = d["marginals"][name]
        pick = np.arange(3, len(x), 9)
        ref = np.array([raw(y) for y in x[pick]]) / Z
        assert np.max(np.abs(p[pick] - ref)) < 1e-8, name
    x, p = d["marginals"]["Q3"]
    assert np.max(np.abs(p - p[::-1])) < 1e-13 * np.max(p)
    o = d["orientation"]
    assert np.allclose(o["L_angle"], (1 - np.cos(o["angle"])) / np.pi, rtol=0, atol=1e-15)


def test_n3_affine_dilatation_is_log_normal_and_q_mirror_symmetric():
    """af-is, n = 3, V = c sum q_a^2 (basis centred at sigma = 0 with the sigma width of the
    exact Gaussian): det phi log-normal; V even under q -> -(q3, q2, q1), so p_q1(y) =
    p_q3(-y) and p_q2 is even; the moments of Tr G (a spherical-triangle rule in Q = e^q)
    equal those of the joint density."""
    c, I, A, B = 1.5, 1.0, 0.2, 0.3  # noqa: E741
    l2 = 1 / math.sqrt((I + A + 3 * B) / 3 * 2 * c / 3)
    s, _ = _affine_sigma_check(3, sp.Settings(basis_size=6, centre=0.0,
                                              scale_sigma=math.sqrt(l2)))
    joint = joint_density(s, s.levels[0])
    y = np.linspace(-1.5, 1.5, 5)
    assert np.max(np.abs(density_at(joint, "q1", y, 36) - density_at(joint, "q3", -y, 36))) \
        < 1e-12
    assert np.max(np.abs(density_at(joint, "q2", y, 36) - density_at(joint, "q2", -y, 36))) \
        < 1e-12
    _moments_agree(s, s.levels[0], ("q2", "trG"), 54, 1e-11)


@pytest.mark.parametrize("sectors", ["spin1", "all"])
def test_n3_spin1_multiplet_trG_matches_the_weighted_chi_squared(sectors):
    """The N = 1 level of the R^9 oscillator is the spin = vorticity = 1 multiplet spanned by
    the entries phi_ij x Gaussian; summed over its 9 states |Psi|^2 ~ |phi|^2 x Gaussian, so
    Tr G / s^2 is chi^2_11 (the chi^2_9 density weighted by Tr G). Through the dedicated
    spin-1 basis (values on a grid, re-evaluated off it) and the general sector basis (a
    recipe); det is even (parity)."""
    hbar, inertia, k = 0.9, 0.7, 1.3
    s = sp.solve("dalembert", 3, oscillator(k), hbar, inertia=inertia, levels=10,
                 sectors=sectors, settings=sp.Settings(basis_size=4, check_shrink=2,
                                                       scale=(hbar**2 / (inertia * k)) ** 0.25))
    level = next(lv for lv in s.levels if lv.multiplicity == 9)
    assert (level.sectors[0].spin, level.sectors[0].vorticity) == (1, 1)
    d = marginal_densities(s, level)
    _check(d)
    s2 = hbar / (2 * inertia * math.sqrt(k / inertia))
    x, p = d["marginals"]["trG"]
    ref = x**4.5 * np.exp(-x / (2 * s2)) / (special.gamma(5.5) * (2 * s2) ** 5.5)
    assert np.max(np.abs(p - ref)) < 1e-8
    x, p = d["marginals"]["det"]
    assert np.max(np.abs(p - p[::-1])) < 1e-13 * np.max(p)


def test_n3_polynomial_form_is_used_only_when_exact():
    """The fast n = 3 evaluation (front x polynomial of degree <= d, fitted at the nodes) must
    reproduce the amplitude off the nodes; a non-polynomial amplitude is kept as it is."""
    from affinebody.quantum.channels3 import ChamberQuadrature
    from affinebody.quantum.densities import _front3, _polynomial_form

    quad = ChamberQuadrature.build(6.0, 24, 12)
    x, w = quad.nodes, np.ones(len(quad.nodes))
    front = lambda p: _front3("lebesgue3", p, 0.9, 1.0, 0.0)  # noqa: E731
    poly = lambda p: front(p) * (p[:, 0] ** 3 * p[:, 2] - 2 * p[:, 1] ** 2 + 0.5)  # noqa: E731
    fast = _polynomial_form("lebesgue3", poly, x, w, 4, 0.9, 1.0, 0.0)
    assert fast is not poly
    p = np.random.default_rng(3).normal(size=(50, 3))
    assert np.max(np.abs(fast(p)[:, 0] - poly(p))) < 1e-12
    wavy = lambda p: front(p) * np.sin(p[:, 0])  # noqa: E731
    assert _polynomial_form("lebesgue3", wavy, x, w, 4, 0.9, 1.0, 0.0) is wavy


def _moments_agree(spectrum, level, names, nodes, rtol):
    """<u^k> (k = 0, 1, 2) from the marginal of u equals <u^k> of the joint density on a
    quadrature of the reduced domain: the change of variables and its Jacobian, checked
    without a closed form. The marginal is integrated by 200-node Gauss-Legendre over the
    support of u (in ln u for the affine det and Tr G; split at 0 otherwise)."""
    joint = joint_density(spectrum, level)
    invariants = {
        "lebesgue2": {"Q1": lambda r: r[:, 0] + r[:, 1], "Q2": lambda r: r[:, 0] - r[:, 1],
                      "det": lambda r: r[:, 0] ** 2 - r[:, 1] ** 2,
                      "trG": lambda r: 2 * (r[:, 0] ** 2 + r[:, 1] ** 2)},
        "haar2": {"q1": lambda p: (p[:, 1] + p[:, 0]) / 2, "det": lambda p: np.exp(p[:, 1]),
                  "trG": lambda p: 2 * np.exp(p[:, 1]) * np.cosh(p[:, 0])},
        "haar3": {"q2": lambda q: q[:, 1], "det": lambda q: np.exp(q.sum(-1)),
                  "trG": lambda q: np.sum(np.exp(2 * q), -1)}}[joint.model]
    mass = joint.weights * joint(joint.nodes)
    t, w = np.polynomial.legendre.leggauss(200)
    for name in names:
        u = invariants[name](joint.nodes)
        seen = u[mass > 1e-18 * np.max(mass)]
        a, b = float(np.min(seen)), float(np.max(seen))
        if joint.model.startswith("haar") and name in ("det", "trG"):
            s = np.log(a) + (np.log(b) - np.log(a)) * (t + 1) / 2
            y, wy = np.exp(s), w * np.exp(s) * (np.log(b) - np.log(a)) / 2
        else:
            pieces = [(a, 0.0), (0.0, b)] if a < 0 < b else [(a, b)]
            y = np.concatenate([lo + (hi - lo) * (t + 1) / 2 for lo, hi in pieces])
            wy = np.concatenate([w * (hi - lo) / 2 for lo, hi in pieces])
        p = density_at(joint, name, y, nodes)
        for k in (0, 1, 2):
            lhs, rhs = np.sum(wy * y**k * p), np.sum(mass * u**k)
            assert abs(lhs - rhs) <= rtol * max(abs(rhs), 1.0), (name, k, lhs, rhs)


@pytest.mark.parametrize("model", ["dalembert", "af-is"])
def test_n2_marginal_moments_equal_joint_moments_for_an_asymmetric_anharmonic_state(model):
    """No closed form and no symmetry: V with a term odd in det (d'Alembert) or in q1
    (af-is); the first excited state."""
    from affinebody.quantum.config import compile_potential

    if model == "dalembert":
        V = compile_potential(ANHARMONIC + " + 0.3*det", 2)
        s = sp.solve("dalembert", 2, V, 1.0, inertia=1.0, levels=2,
                     settings=sp.Settings(basis_size=16))
        names = ("Q1", "Q2", "det", "trG")
    else:
        V = compile_potential("1.5*(q1**2 + q2**2) + 0.3*q1", 2)
        # the identity holds for any eigenvector: a few shells are enough
        s = sp.solve("af-is", 2, V, 1.0, I=1.0, A=0.2, B=0.3, levels=2,
                     settings=sp.Settings(basis_size=16, max_spin=4))
        names = ("q1", "det", "trG")
    # the second state found, converged or not: the identity holds for any eigenvector
    level = sorted(s.levels + s.unconverged, key=lambda lv: lv.energy)[1]
    _moments_agree(s, level, names, 108, 1e-11)


def test_n3_harmonic_basis_density_of_an_excited_state_matches_the_chi_squared():
    """quantum.radial_size (n3.HarmonicBasis, amplitudes summed per harmonic by
    HarmonicBasis.combination): for the R^9 oscillator the (0, 0) state with one radial node
    (energy 13/2 hbar omega: 2 quanta in rho, none in the angles) has Tr G = s^2 t with t
    distributed as (t/2 - 9/2)^2 / (9/2) times the chi^2_9 density (the radial function
    L_1^(7/2)(t/2) e^(-t/4) squared, normalised); pointwise to 1e-8."""
    s = sp.solve("dalembert", 3, oscillator(1.0), 1.0, inertia=1.0, levels=12,
                 settings=sp.Settings(basis_size=2, radial_size=6, scale=1.0))
    key = ("sector", 0, 0, 1)  # the second level of (0, 0)
    assert abs(s.blocks[key].energies[0] - 6.5) < 1e-10
    d = marginal_densities(s, _level(s, key))
    _check(d)
    x, p = d["marginals"]["trG"]
    t = x / 0.5
    chi = t**3.5 * np.exp(-t / 2) / (2**4.5 * special.gamma(4.5)) / 0.5
    assert np.max(np.abs(p - chi * (t / 2 - 4.5) ** 2 / 4.5)) < 1e-8


def test_n2_g_components_at_the_default_basis_size_match_closed_forms():
    """The default n = 2 basis (24) of the oscillator 0.5 tr G (hbar = I = 1, so phi's entries
    are iid N(0, 1/2)): G11 = |phi e1|^2 is exponential with mean 1 and G12 Laplace
    e^{-2|y|}, to 1e-6 of their peak 1 as at basis 9 (test_quantum_orientations). The G rule
    evaluates the basis at rho^2 = y / g with g -> 0 at its end points (rho^2/b^2 up to
    ~1e17): the plain Laguerre recurrence overflowed there before e^{-t/2} = 0 was applied,
    and every G density was nan."""
    from affinebody.quantum.config import compile_potential
    from affinebody.quantum.densities import g_component_densities, pure_state

    s = sp.solve("dalembert", 2, compile_potential("0.5*trG", 2), 1.0, inertia=1.0, levels=1,
                 settings=sp.Settings(basis_size=24))
    g = g_component_densities([(1.0, pure_state(s, {0: 1.0}))], points=13,
                              components=("G11", "G12"))
    g11, g12 = g["G11"], g["G12"]
    assert g11.converged and g12.converged
    assert np.abs(g11.density - np.exp(-g11.x)).max() < 1e-6
    assert np.abs(g12.density - np.exp(-2 * np.abs(g12.x))).max() < 1e-6


def test_n2_g_grid_reaches_the_peak_at_zero_and_refines_only_the_points_that_need_it():
    """The default grid of 51 points for the oscillator's ground state (G11 = e^-y, G12 =
    e^-2|y|, peaks 1 at y = 0): graded towards 0, its first point shows more than 0.9 and 0.8
    of the peak (0.60 on an even grid), and every point is within 1e-8 of the closed form
    though each stops at the first rule that changed it by at most 1e-6 of the peak (the
    finer value is kept); the tail stopped on a coarser rule than the points near 0 (the
    reported node count is the finest used)."""
    from affinebody.quantum.config import compile_potential
    from affinebody.quantum.densities import (
        ORIENTATION_NODES,
        _g_density,
        g_component_densities,
        pure_state,
    )

    s = sp.solve("dalembert", 2, compile_potential("0.5*trG", 2), 1.0, inertia=1.0, levels=1,
                 settings=sp.Settings(basis_size=24))
    pure = pure_state(s, {0: 1.0})
    g = g_component_densities([(1.0, pure)], components=("G11", "G12"))
    g11, g12 = g["G11"], g["G12"]
    assert len(g11.x) == 51 and len(g12.x) == 50
    assert g11.density[0] > 0.9 and np.max(g12.density) > 0.8
    assert np.abs(g11.density - np.exp(-g11.x)).max() < 1e-8
    assert np.abs(g12.density - np.exp(-2 * np.abs(g12.x))).max() < 1e-8
    assert g11.converged and g12.converged and g11.error <= 1e-6 * np.max(g11.density)
    for m in (g11, g12):  # the whole mass, y = 0 included (the points' trapezoid gave 0.94)
        assert abs(m.integral - 1) <= m.integral_error < 1e-5
    far = g11.x[-10:]  # the tail stopped on a coarser rule than the points near 0
    used = [nr for nb, nr in ORIENTATION_NODES[1:]
            if np.array_equal(_g_density([(1.0, pure)], "G11", far, nb, nr), g11.density[-10:])]
    assert used and used[0] < g11.nodes


def test_af_is_g12_density_is_shown_converged_at_the_default_tolerance():
    """The af-is ground state (V = 1.5 (q1^2 + q2^2), hbar = I = 1, A = 0.2, B = 0.3): at the
    smallest |y| of the G12 grid the rules change by 4.8e-4, 1.6e-6 and 1.9e-10 of the peak
    (the change estimates the coarser rule's error); with four rules the density was flagged
    (1.6e-6 > the default 1e-6) though the fourth was accurate to 2e-10. It is converged now,
    within 1e-9 of the peak of a much finer rule on both sides of 0 (a sector state: even in
    y)."""
    from affinebody.quantum.config import compile_potential
    from affinebody.quantum.densities import _g_density, g_component_densities, pure_state

    s = sp.solve("af-is", 2, compile_potential("1.5*(q1**2 + q2**2)", 2), 1.0, I=1.0, A=0.2,
                 B=0.3, levels=1, settings=sp.Settings(basis_size=12, tolerance=1e-3, scale=1.0,
                                                       scale_sigma=0.93, centre=0.0))
    pure = pure_state(s, {0: 1.0})
    g12 = g_component_densities([(1.0, pure)], points=3, components=("G12",))["G12"]
    peak = np.max(g12.density)
    assert g12.converged and g12.error <= 1e-6 * peak
    assert abs(g12.integral - 1) <= g12.integral_error < 1e-4  # through y = 0, 3 points
    # even in y (computed for y > 0 and mirrored): both smallest |y| against a finer rule
    smallest = np.argsort(np.abs(g12.x))[:2]
    assert g12.x[smallest[0]] == -g12.x[smallest[1]]
    fine = _g_density([(1.0, pure)], "G12", g12.x[smallest], 729, 546)
    assert np.abs(g12.density[smallest] - fine).max() < 1e-9 * peak


def test_basis_functions_far_outside_their_support_are_zero_not_nan():
    """Radial2D and Hermite1D at large degree: the closed forms (scipy's Laguerre and Hermite
    polynomials) where the functions live, exactly 0 far out (e^{-t/2} t^j underflows), with
    no overflow on the way (the recurrence is rescaled by powers of two)."""
    from affinebody.quantum.bases import Hermite1D, Radial2D

    m, b, size = 2, 0.8, 60
    radial = Radial2D(m, size, b, size)
    r = np.array([0.3, 2.0, 6.0])
    t = (r / b) ** 2
    for j in (0, 7, size - 1):
        norm = math.exp(0.5 * (special.gammaln(j + 1) - special.gammaln(j + m + 1)))
        ref = math.sqrt(2) / b * t ** (m / 2) * np.exp(-t / 2) * norm \
            * special.eval_genlaguerre(j, m, t)
        assert np.max(np.abs(radial.evaluate(r)[:, j] - ref)) < 1e-12
    hermite = Hermite1D(size, 0.5, 0.3, size)
    x = np.array([-2.0, 0.3, 1.1])
    y = (x - 0.3) / 0.5
    for j in (0, 7, size - 1):
        ref = np.exp(-y * y / 2 - 0.5 * special.gammaln(j + 1) - j / 2 * math.log(2)) \
            * special.eval_hermite(j, y) / (math.pi**0.25 * math.sqrt(0.5))
        assert np.max(np.abs(hermite.evaluate(x)[:, j] - ref)) < 1e-12
    with np.errstate(over="raise", invalid="raise"):
        far_r = radial.evaluate(np.array([1e3, 1e9, 1e60, 1e200, np.inf]))
        far_x = hermite.evaluate(np.array([-np.inf, -1e100, 1e3, 1e9, 1e300]))
    assert np.all(far_r == 0) and np.all(far_x == 0)


def test_separable_values_are_the_double_sum_and_leave_out_only_round_off():
    """f_s(x) = sum_ij u_i(x0) C_sij v_j(x1) of states stacked per block, evaluated by
    blocks of points from the first functions of each factor: equal to the plain double sum
    over all 24 x 24 coefficients to round-off, also where the coefficients end (zero past a
    row and a column, or 1e-17 of the largest there); the truncated recurrence gives the
    first functions of the full one bit for bit."""
    from affinebody.quantum.bases import Hermite1D, Radial2D
    from affinebody.quantum.densities import coefficient_extent, separable_values

    rng = np.random.default_rng(5)
    radial, hermite = Radial2D(1, 24, 0.9, 40), Hermite1D(24, 0.7, 0.2, 40)
    x = np.stack([rng.uniform(0, 4, 5000), rng.uniform(-3, 3, 5000)], -1)
    u, v = radial.evaluate(x[:, 0]), hermite.evaluate(x[:, 1])
    assert np.array_equal(radial.evaluate(x[:, 0], 7), u[:, :7])
    assert np.array_equal(hermite.evaluate(x[:, 1], 5), v[:, :5])
    C = np.zeros((3, 24, 24))
    C[0, :6, :4] = rng.normal(size=(6, 4))
    C[1, :3, :5] = rng.normal(size=(3, 5))
    C[2] = rng.normal(size=(24, 24)) * np.exp(-0.5 * np.add.outer(np.arange(24), np.arange(24)))
    C[2, 23, 23] = 0.0
    C[1, 8, 2] = 1e-17 * np.abs(C[1]).max()  # below round-off of its state: left out
    assert coefficient_extent(C[:2]) == (6, 5)
    assert coefficient_extent(C) == (24, 24)
    for stack in (C[:2], C, C[1:2]):
        rows, cols = coefficient_extent(stack)
        got = separable_values(u[:, :rows], v[:, :cols], stack[:, :rows, :cols])
        exact = np.einsum("pi,sij,pj->ps", u, stack, v)
        size = np.einsum("pi,sij,pj->ps", np.abs(u), np.abs(stack), np.abs(v)).max()
        assert got.shape == exact.shape and np.max(np.abs(got - exact)) < 1e-14 * size


def test_density_command_exits_3_on_a_non_finite_g_density(tmp_path, monkeypatch):
    """A G density that is not finite (as all were at the default n = 2 basis before the
    recurrence was rescaled) is written flagged, warned in one line and the command exits 3
    (EXIT_STOPPED), not 0: --state with --orientation took its exit status from the
    invariants' densities only."""
    from click.testing import CliRunner

    from affinebody.cli.common import EXIT_STOPPED
    from affinebody.quantum import densities as dens
    from affinebody.quantum.cli import density

    path = tmp_path / "osc.toml"
    path.write_text('[system]\nn = 2\n[quantum]\nkinetic = "dalembert"\ninertia = 1.0\n'
                    'potential = "0.5*trG"\nbasis_size = 9\ndensity_points = 11\n')
    monkeypatch.setattr(dens, "_g_density", lambda pure, name, y, nb, nr: np.full(len(y), np.nan))
    result = CliRunner().invoke(density, [str(path), "--state", "0", "--orientation", "-o",
                                          str(tmp_path / "o")])
    assert result.exit_code == EXIT_STOPPED, result.output
    lines = [line for line in result.output.splitlines() if "not finite" in line]
    assert len(lines) == 3 and all(line.startswith("warning: density of G") for line in lines)
    # the file holds them as null: strict JSON (Python wrote the token NaN, which jq refuses)
    import json

    def refuse(token):
        raise ValueError(f"not JSON: {token}")

    written = json.loads((tmp_path / "o" / "orientation.json").read_text(),
                         parse_constant=refuse)
    assert written["densities"]["G11"]["density"] == [None] * 11
    assert written["densities"]["G11"]["converged"] is False


def test_an_unconverged_density_is_said_relative_to_its_peak():
    """The tolerance is relative to the density's peak: the warning gives the error in that
    unit (it gave the absolute error next to 'tolerance x peak', as '1.0e-06 above tolerance
    1e-06 x peak 0.628', which reads as an error within the tolerance)."""
    from affinebody.quantum import densities as dens

    m = dens.Marginal(np.linspace(0, 1, 3), np.array([0.1, 0.628, 0.2]), 1.02e-6, 1.0, 24,
                      False)
    message = dens._density_warning("G12", m, 1e-6)
    assert "error 1.6e-06 of its peak 0.628, above the tolerance 1e-06" in message
    assert "\n" not in message


def test_kronrod_panels_are_exact_to_their_degrees():
    """The (7, 15) Gauss-Kronrod pair of the G-density integrals on two uneven panels: the
    Kronrod sum exact for every monomial up to degree 22, the Gauss sum up to 13 and not at
    14 (so their difference is an error estimate), the Gauss rule's nodes among the Kronrod
    ones with numpy's Gauss-Legendre weights."""
    from affinebody.quantum.densities import kronrod_panels

    x, wk, wg = kronrod_panels([-0.5, 0.25, 2.0])
    for degree in range(23):
        exact = (2.0 ** (degree + 1) - (-0.5) ** (degree + 1)) / (degree + 1)
        assert abs(np.sum(wk * x**degree) - exact) < 1e-14 * max(1.0, abs(exact))
        if degree <= 13:
            assert abs(np.sum(wg * x**degree) - exact) < 1e-14 * max(1.0, abs(exact))
    exact14 = (2.0**15 - 0.5**15) / 15
    assert abs(np.sum(wg * x**14) - exact14) > 1e-10 * exact14
    gx, gw = np.polynomial.legendre.leggauss(7)
    on = wg[0] != 0
    np.testing.assert_allclose(x[0][on], -0.5 + 0.75 * (gx + 1) / 2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(wg[0][on], 0.75 * gw / 2, rtol=0, atol=1e-15)
