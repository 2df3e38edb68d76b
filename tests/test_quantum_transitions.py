"""Transition strengths (quantum/transitions.py, docs/quantum-transitions.md) against the
oscillator's ladder-operator closed forms, the Thomas-Reiche-Kuhn sum rule (d'Alembert, any
potential) and its metric form for an affine model (the metric taken from the classical kinetic
energy, affinebody.kinetic), Hermiticity, the selection rules (a direct angular quadrature of
every element, no selection rule assumed), n = 3 invariants and components (phi, G, C and
their quadrupole parts, against the R^9 oscillator's ladder operators and TRK), and the
``affinebody transitions`` command (contract JSON, one-line errors, refusal of too much work)."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner

from affinebody.cli.quantum_dynamics import transitions as transitions_command
from affinebody.kinetic import AffineIsotropic, DAlembert
from affinebody.quantum import spectra as sp
from affinebody.quantum.intervals import ExpressionPotential
from affinebody.quantum.transitions import (
    Operator,
    amplitudes,
    harmonics,
    invariants_at,
    level_components,
    level_matrix,
    level_states,
    matrix_elements,
    reduced_quadrature,
    transitions,
    trk_sum,
)
from oracles import oscillator_config

HBAR, INERTIA, K = 0.7, 1.3, 0.8
OMEGA = math.sqrt(K / INERTIA)
#: <1|phi_ab|0>^2 of one Cartesian oscillator: hbar / (2 I omega)
U = HBAR / (2 * INERTIA * OMEGA)


@pytest.fixture(scope="module")
def oscillator():
    """R^4 oscillator (d'Alembert, n = 2): levels 0, 1, 2 with 1, 4, 10 states."""
    s = sp.solve("dalembert", 2, lambda Q: 0.5 * K * np.sum(Q * Q, -1), HBAR, inertia=INERTIA,
                 levels=15, settings=sp.Settings(basis_size=12, max_spin=2))
    assert [lv.multiplicity for lv in s.levels] == [1, 4, 10]
    return s


def strengths(spectrum, text, initial=0):
    return [t.strength for t in transitions(spectrum, Operator(text, 2), initial).transitions]


def deficits(table, target):
    """target - (partial energy-weighted sums), one per level with a nonzero strength."""
    partial, out = 0.0, []
    for t in table.transitions:
        partial += (t.E_final - t.E_initial) * t.strength
        if t.strength > 1e-12:
            out.append(target - partial)
    return out


def test_oscillator_closed_forms(oscillator):
    """phi_ab = sqrt(U)(a + a^dagger) per component: from the ground, phi11 reaches only the
    4-fold level 1 (strength U); from level 1 (average over its 4 states) it reaches level 0
    with U/4 and level 2 with (2 + 3)U/4 (the state with the quantum in 11 goes to |2> with 2U,
    the 3 others to |1,1> with U); trG = sum phi^2 has <0|trG|0> = 4U and reaches level 2 with
    4 x 2U^2; G11 = phi11^2 + phi21^2: 2U, 2 x 2U^2; phi12 phi21 only |1,1>: U^2;
    G12 + C11: <0|.|0> = 2U, to level 2: C11 gives 2 x 2U^2, G12 2 x U^2."""
    np.testing.assert_allclose(strengths(oscillator, "phi11"), [0, U, 0], atol=1e-12)
    np.testing.assert_allclose(strengths(oscillator, "phi11", 1), [U / 4, 0, 5 * U / 4],
                               atol=1e-12)
    np.testing.assert_allclose(strengths(oscillator, "trG"), [16 * U**2, 0, 8 * U**2],
                               atol=1e-12)
    np.testing.assert_allclose(strengths(oscillator, "G11"), [4 * U**2, 0, 4 * U**2],
                               atol=1e-12)
    np.testing.assert_allclose(strengths(oscillator, "phi12*phi21"), [0, 0, U**2], atol=1e-12)
    np.testing.assert_allclose(strengths(oscillator, "G12 + C11"), [4 * U**2, 0, 6 * U**2],
                               atol=1e-12)


def test_selection_rules_and_hermiticity(oscillator):
    """The harmonics of an operator are those group theory predicts (phi: (+-1, +-1); G = R
    diag(Q^2) R^T: (0, 0), (0, +-2); C: (0, 0), (+-2, 0)); every element between levels 1 and 2,
    computed by a direct quadrature over the angles with the states' phases (no selection rule
    used), vanishes to round-off where the rule forbids it and equals the reduced element where
    it allows it; and <f|O|i> = conj(<i|O|f>)."""
    s = oscillator
    y, w = reduced_quadrature(level_components(s, s.levels[1]))
    Q = invariants_at("lebesgue2", y)
    assert set(harmonics(Operator("phi21", 2), Q)) == {(1, 1), (1, -1), (-1, 1), (-1, -1)}
    assert set(harmonics(Operator("G12", 2), Q)) == {(0, 2), (0, -2)}
    assert set(harmonics(Operator("C11 - trG/2", 2), Q)) == {(2, 0), (-2, 0)}
    assert set(harmonics(Operator("G11 + det", 2), Q)) == {(0, 0), (0, 2), (0, -2)}

    op = Operator("phi11 + 0.3*G12 - 0.2*C12*Q1 + det", 2)
    M = matrix_elements(s, op, 1, 2)  # <f in level 2|O|i in level 1>
    np.testing.assert_allclose(M, matrix_elements(s, op, 2, 1).conj().T, atol=1e-13)
    ci, cf = level_components(s, s.levels[1]), level_components(s, s.levels[2])
    y, w = reduced_quadrature(ci + cf)
    Q = invariants_at("lebesgue2", y)
    t = 2 * np.pi * np.arange(12) / 12  # exact for the degree-3 operator and |Delta| <= 4
    A, B = np.meshgrid(t, t, indexing="ij")
    values = op(Q[:, None, None, :], A[None], B[None])
    averages = {}  # Delta -> the angular average of O e^{-i(Ds alpha - Dv beta)} at each node

    def average(ds, dv):
        if (ds, dv) not in averages:
            phase = np.exp(-1j * (ds * A - dv * B))
            averages[(ds, dv)] = np.mean(values * phase[None], axis=(1, 2))
        return averages[(ds, dv)]

    allowed = set(harmonics(op, Q))
    forbidden, checked = 0.0, 0
    row = 0
    for f in cf:
        af = amplitudes(f, y)[:, 0]
        for sf in f.sectors:
            col = 0
            for i in ci:
                ai = amplitudes(i, y)[:, 0]
                for si in i.sectors:
                    delta = (sf.spin - si.spin, sf.vorticity - si.vorticity)
                    direct = np.sum(w * af * ai * average(*delta))
                    if delta in allowed:
                        assert abs(direct - M[row, col]) < 1e-12
                        checked += 1
                    else:
                        assert M[row, col] == 0
                        forbidden = max(forbidden, abs(direct))
                    col += 1
            row += 1
    assert checked > 0 and forbidden < 1e-14


def test_trk_dalembert_non_oscillator_converges():
    """d'Alembert, V = trG/2 + 0.8 exp(-trG/2): sum_F (E_F - E_0) B(0 -> F) of phi11 and of
    phi21 tends to (hbar^2/2) g^-1(dphi_ab, dphi_ab) = hbar^2 H_kin(pi = E_ab) = hbar^2/(2I)
    (H_kin of affinebody.kinetic.DAlembert) as levels are added: the partial sums approach it,
    the deficit shrinking by more than 10x per contributing level."""
    hbar, inertia = 1.0, 1.0
    def potential(Q):
        trG = np.sum(Q * Q, -1)
        return 0.5 * trG + 0.8 * np.exp(-trG / 2)

    # the sectors reached from the ground are (+-1, +-1): shells |m1| + |m2| <= 2 suffice
    s = sp.solve("dalembert", 2, potential, hbar, inertia=inertia, levels=40,
                 settings=sp.Settings(basis_size=12, max_spin=2))
    model = DAlembert(J=jnp.eye(2)[None] * inertia)
    assert not s.certified  # max_spin cuts the search: the sum covers the sectors it reaches
    for a, b in ((0, 0), (1, 0)):
        pi = jnp.zeros((1, 2, 2)).at[0, a, b].set(1.0)
        target = hbar**2 * float(model.hamiltonian(jnp.eye(2)[None], pi)[0])
        assert abs(target - hbar**2 / (2 * inertia)) < 1e-14
        table = transitions(s, Operator(f"phi{a + 1}{b + 1}", 2), 0)
        d = deficits(table, target)
        assert len(d) >= 2
        assert all(x > 0 for x in d)  # each level adds positive weight below the limit
        assert all(later < earlier / 10 for earlier, later in zip(d, d[1:], strict=False))
        assert d[-1] < 5e-5 * target
        assert abs(trk_sum(table) - (target - d[-1])) < 1e-14


def test_trk_metric_form_affine():
    """af-is (74), V = (q1+q2)^2/4 + (q1-q2)^2/2 + 0.3 cosh(q1-q2): for F = sqrt(det phi) the
    energy-weighted sum tends to (hbar^2/2) <g^-1(dF, dF)> = hbar^2 <H_kin(phi, (dF/dphi)^T)>
    = hbar^2 <det/4> H_kin(phi, phi^-1), with H_kin of affinebody.kinetic.AffineIsotropic
    (constant in phi: the model is left-invariant), the deficit shrinking level by level; for
    F = ln det = q1 + q2 (separable, harmonic in sigma) it holds exactly with one level."""
    I, A, B, hbar = 0.5, 0.1, 0.1, 1.0  # noqa: E741
    def potential(Q):
        sigma, x = np.log(Q[..., 0] * Q[..., 1]), np.log(Q[..., 0] / Q[..., 1])
        return 0.25 * sigma**2 + 0.5 * x**2 + 0.3 * np.cosh(x)

    # an invariant reaches the sector (0, 0) only: shells max(|s|, |k|) <= 1 are solved
    s = sp.solve("af-is", 2, potential, hbar, I=I, A=A, B=B, levels=30,
                 settings=sp.Settings(basis_size=24, max_spin=1))
    model = AffineIsotropic(I=I, A=A, B=B)
    rng = np.random.default_rng(1)
    phis = jnp.asarray(np.eye(2) + 0.3 * rng.normal(size=(3, 2, 2)))
    H = np.asarray(model.hamiltonian(phis, jnp.linalg.inv(phis)))
    np.testing.assert_allclose(H, H[0], rtol=1e-13)
    mean_det = math.sqrt(strengths(s, "det")[0])  # <0|det|0> (the ground is non-degenerate)
    target = hbar**2 * mean_det / 4 * H[0]
    d = deficits(transitions(s, Operator("sqrt(det)", 2), 0), target)
    assert len(d) >= 5
    assert all(later < earlier / 3 for earlier, later in zip(d, d[1:], strict=False))
    assert 0 < d[-1] < 1e-4 * target
    assert abs(trk_sum(transitions(s, Operator("q1 + q2", 2), 0)) - hbar**2 * H[0]) < 1e-10


def test_n3_oscillator_scalar_operators():
    """R^9 oscillator (n = 3, scalar sector): <0|trG|0> = 9U, trG reaches the scalar level of
    N = 2 with 9 x 2U^2; det (odd under phi -> -phi) reaches only the parity -1 scalar state of
    N = 3, with 6 U^3 (six products of three distinct components)."""
    s = sp.solve("dalembert", 3, ExpressionPotential(f"0.5*{K}*trG", 3), HBAR, inertia=INERTIA,
                 levels=3, sectors="scalar", settings=sp.Settings(basis_size=6, check_shrink=2))
    E = [lv.energy for lv in s.levels]  # N = 0, 2, 3, then N >= 4
    np.testing.assert_allclose(np.diff(E[:3]), [2 * HBAR * OMEGA, HBAR * OMEGA], rtol=1e-10)
    assert s.levels[2].sectors[0].parity == -1
    trg = [t.strength for t in transitions(s, Operator("trG", 3), 0).transitions]
    zeros = [0] * (len(trg) - 3)  # trG|0> and det|0> have no component with N >= 4
    np.testing.assert_allclose(trg, [81 * U**2, 18 * U**2, 0, *zeros], atol=1e-12)
    det = [t.strength for t in transitions(s, Operator("det", 3), 0).transitions]
    np.testing.assert_allclose(det, [0, 0, 6 * U**3, *zeros], atol=1e-12)


@pytest.fixture(scope="module")
def oscillator3():
    """R^9 oscillator (d'Alembert, n = 3, every sector up to max(j, j') = 2): levels N = 0, 1,
    2 with 1, 9, 45 states (45 = (0, 0) + (1, 1) + (0, 2) + (2, 0) + (2, 2))."""
    s = sp.solve("dalembert", 3, ExpressionPotential(f"0.5*{K}*trG", 3), HBAR, inertia=INERTIA,
                 levels=55, settings=sp.Settings(basis_size=4, check_shrink=2, max_spin=2))
    assert [lv.multiplicity for lv in s.levels] == [1, 9, 45]
    return s


@pytest.fixture(scope="module")
def states3(oscillator3):
    return level_states(oscillator3)


def strengths3(spectrum, text, initial=0, states=None):
    table = transitions(spectrum, Operator(text, 3), initial, states)
    return table, [t.strength for t in table.transitions]


def test_n3_components_against_ladder_operators(oscillator3, states3):
    """phi^i_a = sqrt(U) (a + a^+) per component, U = hbar / (2 I omega), summed over the
    degenerate states of each level (Wigner D-functions of L and R integrated exactly):
    phi11 from N = 0 reaches N = 1 with U; from N = 1 (averaged over its 9 states) it reaches
    N = 0 with U / 9 and N = 2 with (2U + 8U) / 9 (sqrt 2 for the doubly occupied mode), and
    the energy-weighted sum is hbar^2 / (2 I) (TRK, up and down transitions together). The
    quadrupole part G11 - trG/3 = sum_k (2 phi_k1^2 - phi_k2^2 - phi_k3^2) / 3 has no ground
    expectation and reaches N = 2 with 3 x 2U^2 (4 + 1 + 1)/9 = 4U^2; C13 = sum_a phi_1a phi_3a
    reaches N = 2 with 3U^2 (checked together: the sum of the two)."""
    np.testing.assert_allclose(strengths3(oscillator3, "phi11", 0, states3)[1], [0, U, 0],
                               atol=1e-12)
    table, up_down = strengths3(oscillator3, "phi11", 1, states3)
    np.testing.assert_allclose(up_down, [U / 9, 0, 10 * U / 9], rtol=1e-9, atol=1e-12)
    assert abs(trk_sum(table) - HBAR**2 / (2 * INERTIA)) < 1e-10
    # the G quadrupole reaches (0, 2), C13 reaches (2, 0): different ranks, no interference
    table, quadrupoles = strengths3(oscillator3, "G11 - trG/3 + C13", 0, states3)
    np.testing.assert_allclose(quadrupoles, [0, 0, (4 + 3) * U**2], atol=1e-12)
    assert [t.allowed for t in table.transitions] == [True, False, True]  # N = 1: (1, 1) only


def test_n3_spin1_channel_and_linear_combinations():
    """The dedicated spin = vorticity = 1 channel (its own coordinates) gives the same ground
    strengths: phi12 -> U, and a combination sum c_ia phi^i_a -> |c|^2 U (no interference
    between the components after the sum over the multiplet). Expressions that are not
    polynomials in the components (infinite SO(3) ranks) have no finite expansion: they take
    the numerical projection (tests below)."""
    s = sp.solve("dalembert", 3, ExpressionPotential(f"0.5*{K}*trG", 3), HBAR, inertia=INERTIA,
                 levels=12, sectors="scalar+spin1",
                 settings=sp.Settings(basis_size=5, check_shrink=2))
    assert [lv.multiplicity for lv in s.levels] == [1, 9, 10]
    np.testing.assert_allclose(strengths3(s, "phi11 - 2*phi33 + phi21")[1], [0, 6 * U, 0],
                               atol=1e-12)
    for text in ("exp(G12)", "abs(phi11)", "sqrt(1 + C11**2)", "exp(-0.02*G11)"):
        assert Operator(text, 3).expansion is None


def test_n3_quadratic_operators_against_ladder_operators(oscillator3, states3):
    """Products of components (the general expansion in Wigner D functions): phi11 phi22 = U
    (a + a^+)(b + b^+) has no ground expectation and reaches N = 2 with U^2; inside N = 1 it
    is U (a^+ b + b^+ a): two elements U over the 9 states, 2U^2/9; phi11^2 has <0|.|0> = U
    and reaches N = 2 with 2U^2. A coefficient that is any function of the invariants:
    exp(-a trG) phi11 phi22 from the Gaussian ground state factorises over the nine modes,
    <1|x e^{-a x^2}|0> = s^3/U and <0|e^{-a x^2}|0> = (1 + 2aU)^{-1/2}, s^2 = U/(1 + 2aU)."""
    np.testing.assert_allclose(strengths3(oscillator3, "phi11*phi22", 0, states3)[1], [0, 0, U**2],
                               atol=1e-12)
    np.testing.assert_allclose(strengths3(oscillator3, "phi11*phi22", 1, states3)[1],
                               [0, 2 * U**2 / 9, 0], atol=1e-12)
    np.testing.assert_allclose(strengths3(oscillator3, "phi11**2", 0, states3)[1],
                               [U**2, 0, 2 * U**2], atol=1e-12)
    a = 0.1  # a Gaussian factor: the chamber quadrature of the states resolves it to ~1e-8
    s3 = (U / (1 + 2 * a * U)) ** 1.5
    element = (s3 / U) ** 2 * (1 + 2 * a * U) ** -3.5
    table, got = strengths3(oscillator3, f"exp(-{a}*trG)*phi11*phi22", 0, states3)
    np.testing.assert_allclose(got, [0, 0, element**2], rtol=1e-7, atol=1e-14)
    assert "(1, 1)" in table.selection_rule and "(2, 2)" in table.selection_rule


def test_n3_products_by_completeness_and_hermiticity(oscillator3, states3):
    """The element matrices of a product are the products of the factors' matrices summed over
    the intermediate levels (completeness; for the oscillator phi22 |N = 0> lies in N = 1, so
    the sum over the levels computed is exact), in the multiplet bases of level_matrix: the
    rank (1, 1) x (1, 1) coupling against the rank-2 expansion of the product. A Hermitian
    operator has a Hermitian matrix; elements forbidden by the ranks or by the parity
    phi -> -phi vanish to round-off."""
    A, B = Operator("phi11", 3), Operator("phi22 + 0.5*C12", 3)
    product = Operator("phi11*phi22 + 0.5*phi11*C12", 3)
    B0 = [level_matrix(oscillator3, B, 0, k, states3) for k in range(3)]
    for f in (0, 2):
        direct = level_matrix(oscillator3, product, 0, f, states3)
        summed = sum(level_matrix(oscillator3, A, k, f, states3) @ B0[k] for k in range(3))
        assert np.abs(direct - summed).max() < 1e-11
        assert np.abs(direct).max() > 0.1 * U or f == 0  # phi11 phi22 reaches N = 2
    mixed = Operator("exp(-trG)*phi12*phi21 + q1*G11 - det*C23", 3)
    for i, f in ((0, 2), (1, 2)):
        M = level_matrix(oscillator3, mixed, i, f, states3)
        T = level_matrix(oscillator3, mixed, f, i, states3)
        assert np.abs(M - T.T).max() < 1e-12 * max(1.0, np.abs(M).max())
    odd = level_matrix(oscillator3, Operator("phi11*G22", 3), 0, 0, states3)  # degree 3 in phi
    assert np.abs(odd).max() < 1e-14


def test_n2_non_polynomial_closed_forms(oscillator):
    """Operators that are not polynomials in the components (projected numerically on the
    angles, two grids compared), against one-mode Gaussian integrals of the R^4 oscillator
    (phi_ab i.i.d. normal of variance U in the ground state, |1> = x|0>/sqrt U, |2> =
    (x^2/U - 1)|0>/sqrt 2): <0|e^{-a x^2}|0> = (1 + 2aU)^{-1/2}, <2|e^{-a x^2}|0> =
    -aU sqrt 2 (1 + 2aU)^{-3/2}, <1|x e^{-a x^2}|0> = sqrt U (1 + 2aU)^{-3/2}, <n|e^{bx}|0> =
    (b sqrt U)^n e^{b^2 U/2}/sqrt n!. G11 = phi11^2 + phi21^2 (two modes): exp(-a G11) has
    B(0 -> 0) = (1 + 2aU)^{-2}, B(0 -> 2) = 2 (aU sqrt 2)^2 (1 + 2aU)^{-4}; exp(b phi11):
    e^{b^2 U} (b^2 U)^N / N! to level N; phi11 exp(-a G11) reaches only level 1 (of those
    computed), U (1 + 2aU)^{-4}; <0|G11/trG|0> = 1/2 by the symmetry G11 <-> G22."""
    a, b = 0.1, 0.3
    g = 1 + 2 * a * U
    states = level_states(oscillator)
    cases = {f"exp(-{a}*G11)": [g**-2, 0, 4 * a**2 * U**2 * g**-4],
             f"exp({b}*phi11)": [math.exp(b * b * U) * (b * b * U) ** N / math.factorial(N)
                                 for N in range(3)],
             f"phi11*exp(-{a}*G11)": [0, U * g**-4, 0]}
    for text, expected in cases.items():
        table = transitions(oscillator, Operator(text, 2), 0, states)
        got = [t.strength for t in table.transitions]
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-14)
        assert table.projection_error < 1e-13
    ratio = transitions(oscillator, Operator("G11/trG", 2), 0, states).transitions[0]
    assert abs(ratio.strength - 0.25) < 1e-13


def test_n2_non_polynomial_selection_rules_and_hermiticity(oscillator):
    """exp(-a G11)(1 + C12/2) inside level 2 (sectors with spin 0, +-2): at phi = R(alpha)
    diag(Q) R(beta)^T, G11 = Q1^2 cos^2 beta + Q2^2 sin^2 beta depends on beta alone and
    C12 = (Q1^2 - Q2^2) cos alpha sin alpha on alpha alone, so O_Delta = c_{Delta s}(Q)
    g_{-Delta v}(Q) with c, g one-angle Fourier coefficients, computed here apart (64-point
    trapezoid per angle, from these formulas, no selection rule used): c_{+-4} = 0, so the
    elements with Delta s = +-4 vanish; every other element equals the reduced one; the matrix
    is Hermitian."""
    s, a = oscillator, 0.1
    M = matrix_elements(s, Operator(f"exp(-{a}*G11)*(1 + 0.5*C12)", 2), 2, 2)
    np.testing.assert_allclose(M, M.conj().T, atol=1e-13)
    comps = level_components(s, s.levels[2])
    y, w = reduced_quadrature(comps)
    Q = invariants_at("lebesgue2", y)
    t = 2 * np.pi * np.arange(64) / 64
    P1, P2 = Q[:, :1] ** 2, Q[:, 1:] ** 2
    g = np.fft.fft(np.exp(-a * (P1 * np.cos(t) ** 2 + P2 * np.sin(t) ** 2)), axis=1) / 64
    c = np.fft.fft(1 + 0.5 * (P1 - P2) * np.cos(t) * np.sin(t), axis=1) / 64
    states = [(amplitudes(k, y)[:, 0], sec) for k in comps for sec in k.sectors]
    forbidden, checked = 0.0, 0
    for row, (af, sf) in enumerate(states):
        for col, (ai, si) in enumerate(states):
            ds, dv = sf.spin - si.spin, sf.vorticity - si.vorticity
            direct = np.sum(w * af * ai * c[:, ds % 64] * g[:, -dv % 64])
            if abs(ds) == 4:
                forbidden = max(forbidden, abs(direct))
                assert M[row, col] == 0
            else:
                assert abs(direct - M[row, col]) < 1e-12
                checked += 1
    assert checked > 50 and forbidden < 1e-14


def test_n3_numerical_projection_agrees_with_expansion(oscillator3, states3):
    """The numerical projection (method="quadrature": Euler-angle grids on L and R at the
    nodes of a chamber rule of its own, fed to the same contraction) against the exact
    expansion in Wigner D functions, for polynomial operators: G12^2 - trG G33 (ranks (0, 0),
    (0, 2), (0, 4); R only) and phi12 (rank (1, 1), both rotations: the other ranks it computes
    vanish to round-off, and phi12 |0> has no component in N = 2 by parity)."""
    for text in ("G12**2 - trG*G33", "phi12"):
        exact = strengths3(oscillator3, text, 0, states3)[1]
        table = transitions(oscillator3, Operator(text, 3, method="quadrature"), 0, states3)
        got = [t.strength for t in table.transitions]
        np.testing.assert_allclose(got, exact, rtol=1e-12, atol=1e-14)
        assert table.projection_error < 1e-11
    assert "{(1, 1)}" in table.selection_rule
    assert got[2] < 1e-28


def test_n3_non_polynomial_closed_forms_and_hermiticity(oscillator3, states3):
    """n = 3, the R^9 oscillator: exp(-a G11), G11 = phi11^2 + phi21^2 + phi31^2 (three modes,
    the one-mode integrals of test_n2_non_polynomial_closed_forms): B(0 -> 0) = (1 + 2aU)^-3,
    B(0 -> N = 2) = 3 (aU sqrt 2)^2 (1 + 2aU)^{-5} (one mode in |2>), and N = 1 is not reached
    (ranks (0, l') cannot couple (0, 0) to (1, 1)); exp(b phi11) and phi11 exp(-a G11), which
    depend on both rotations (one row of each: the reduced Euler rules). The values to excited
    levels hold to the accuracy of the eigenvectors (measured 7e-10 for phi11 exp(-0.1 G11):
    an operator that is not a polynomial also reaches N = 3, 4, of which the computed N <= 2
    eigenvectors hold a trace; polynomial operators do not). G11/trG (a
    polynomial with a coefficient in the invariants: the exact path): <0|.|0> = 1/3 by
    symmetry. The element matrix of a non-polynomial operator inside N = 1 (9 states) is
    symmetric, not diagonal."""
    a = 0.02
    g = 1 + 2 * a * U
    table = transitions(oscillator3, Operator(f"exp(-{a}*G11)", 3), 0, states3)
    got = [t.strength for t in table.transitions]
    assert abs(got[0] - g**-3) < 1e-13 and got[1] == 0 and not table.transitions[1].allowed
    assert abs(got[2] / (6 * a**2 * U**2 * g**-5) - 1) < 1e-8
    assert table.projection_error < 1e-10
    # from N = 1 (9 states, a quantum in one mode): inside N = 1 only the diagonal elements,
    # <1|e^{-ax^2}|1> = g^{-3/2} times g^{-1} (the two other modes of G11) for the 3 modes of
    # G11 and g^{-3/2} for the 6 others; N = 0 and N = 2 have the wrong parity
    got = [t.strength for t in transitions(oscillator3, Operator(f"exp(-{a}*G11)", 3), 1,
                                           states3).transitions]
    np.testing.assert_allclose(got, [0, (3 * g**-5 + 6 * g**-3) / 9, 0], rtol=1e-10,
                               atol=1e-20)
    # both rotations: exp(b phi11), one mode, (b^2 U)^N e^{b^2 U} / N! to level N; phi11
    # exp(-a G11): sqrt U g^{-3/2} from the mode phi11, g^{-1/2} from phi21 and phi31
    b = 0.2
    table = transitions(oscillator3, Operator(f"exp({b}*phi11)", 3), 0, states3)
    np.testing.assert_allclose([t.strength for t in table.transitions],
                               [math.exp(b * b * U) * (b * b * U) ** N / math.factorial(N)
                                for N in range(3)], rtol=1e-10)
    got = strengths3(oscillator3, f"phi11*exp(-{a}*G11)", 0, states3)[1]
    assert abs(got[1] / (U * g**-5) - 1) < 1e-8 and got[0] == 0 and got[2] < 1e-28
    assert abs(strengths3(oscillator3, "G11/trG", 0, states3)[1][0] - 1 / 9) < 1e-13
    M = level_matrix(oscillator3, Operator(f"exp(-{a}*G11) + 0.1*G12/trG", 3), 1, 1, states3)
    assert np.abs(M - np.diag(np.diag(M))).max() > 1e-3 and np.abs(M - M.T).max() < 1e-13


def test_n3_non_polynomial_refusals(oscillator3, states3):
    """A kink (abs) has an angular spectrum that does not decay: refused in one line; an
    operator wide in both rotations, through two rows of each, is refused for the work its
    projection needs."""
    for text, needle in (("abs(G12)", "does not decay"),
                         ("exp(0.3*(phi11 + phi22))", "more than the")):
        with pytest.raises(ValueError, match=needle) as err:
            transitions(oscillator3, Operator(text, 3), 0, states3)
        assert "\n" not in str(err.value)


CONFIG = oscillator_config(HBAR, INERTIA, K, "levels = 15\nbasis_size = 12")


def test_cli_transitions_json_and_errors(tmp_path):
    path = tmp_path / "osc.toml"
    path.write_text(CONFIG)
    result = CliRunner().invoke(transitions_command, [str(path), "--operator", "phi11", "--from",
                                                      "1", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    rows = data["transitions"]
    assert [r["final"] for r in rows] == [0, 1, 2] and {r["initial"] for r in rows} == {1}
    np.testing.assert_allclose([r["strength"] for r in rows], [U / 4, 0, 5 * U / 4],
                               atol=1e-12)
    np.testing.assert_allclose([r["E_final"] - r["E_initial"] for r in rows],
                               [-HBAR * OMEGA, 0, HBAR * OMEGA], atol=1e-12)
    assert len(rows[2]["sector_final"]) == 10 and rows[1]["allowed"] is False
    assert "(+1, +1)" in data["selection_rule"]
    assert data["projection_error"] < 1e-13  # a polynomial: the two angular grids agree
    for args, needle in ((["--operator", "phi11 + foo"], "unknown name 'foo'"),
                         (["--operator", "phi11", "--from", "7"], "--from 7 is not a level"),
                         (["--operator", "abs(phi11)"], "harmonics do not decay"),
                         (["--operator", "phi11", "--levels", "100000"], "at most 2000"),
                         (["--operator", "phi11", "--levels", "0"], "--levels must be >= 1")):
        bad = CliRunner().invoke(transitions_command, [str(path), *args])
        assert bad.exit_code == 1, (args, bad.output)
        assert needle in bad.output and len(bad.output.strip().splitlines()) == 1
    n3 = tmp_path / "n3.toml"  # refused before any solving
    n3.write_text(CONFIG.replace("n = 2", "n = 3"))
    bad = CliRunner().invoke(transitions_command, [str(n3), "--operator", "exp(G12) * foo"])
    assert bad.exit_code == 1 and "unknown name 'foo'" in bad.output
    assert len(bad.output.strip().splitlines()) == 1


def test_levels_and_states_are_numbered_alike_by_spectrum_transitions_and_density(tmp_path):
    """The oscillator's levels 0, 1, 2 hold the states 0, 1-4, 5-14: spectrum's table gives
    both numbers of each level, transitions (which counts levels) says which states its
    levels are, and density (which counts states) which level its state is in. Before, the
    table's '#' was the first state (0, 1, 5) and transitions --from 5 read it as a level."""
    from affinebody.quantum.cli import density as density_command
    from affinebody.quantum.cli import spectrum as spectrum_command

    path = tmp_path / "osc.toml"
    path.write_text(CONFIG.replace("levels = 15", "levels = 5"))
    table = CliRunner().invoke(spectrum_command, [str(path)])
    assert table.exit_code == 0, table.output
    rows = [line.split("│")[1:3] for line in table.output.splitlines() if "│" in line]
    assert [[c.strip() for c in row] for row in rows] == [["0", "0"], ["1", "1-4"]]
    assert "transitions --from" in table.output and "density --state" in table.output
    text = CliRunner().invoke(transitions_command, [str(path), "--operator", "phi11", "--from",
                                                    "1"])
    assert text.exit_code == 0, text.output
    assert "level 1 (states 1-4" in " ".join(text.output.split())
    final = [line.split("│")[1:3] for line in text.output.splitlines() if "│" in line]
    assert [[c.strip() for c in row] for row in final if row[0].strip()] == [
        ["0", "0"], ["1", "1-4"]]  # (a row's sectors may wrap onto a line of its own)
    data = json.loads(CliRunner().invoke(transitions_command, [
        str(path), "--operator", "phi11", "--from", "1", "--json"]).output)
    assert [(r["states_initial"], r["states_final"]) for r in data["transitions"]] == [
        ([1, 2, 3, 4], [0]), ([1, 2, 3, 4], [1, 2, 3, 4])]
    dens = CliRunner().invoke(density_command, [str(path), "--state", "3", "-o",
                                                str(tmp_path / "d")])
    assert dens.exit_code == 0, dens.output
    assert "state 3 (level 1: transitions --from 1)" in " ".join(dens.output.split())
