"""Spectra of the reduced quantum affine body (affinebody.quantum.spectra): exact oscillator
levels and degeneracies (n = 2, 3), an independent Cartesian solver in R^4, honesty about
continuous spectra, densities normalised under the right measure."""

import math
from itertools import product
from math import comb

import numpy as np
import pytest

from affinebody.quantum import spectra as sp
from affinebody.quantum.channels3 import auto_scale_haar3
from affinebody.quantum.config import ConfigError, compile_potential, parse
from affinebody.quantum.densities import densities
from affinebody.quantum.levels import AffineInertia
from affinebody.quantum.n2 import auto_scale_haar2, haar2_block
from oracles import cartesian_n2_levels

K_SPRING, INERTIA, HBAR = 1.3, 0.7, 0.9
OMEGA = np.sqrt(K_SPRING / INERTIA)


def oscillator(Q):
    return 0.5 * K_SPRING * np.sum(Q**2, axis=-1)


#: n = 2 potentials as expressions, so that the sector search can certify its stop
oscillator2 = compile_potential(f"0.5*{K_SPRING}*trG", 2)
anharmonic = compile_potential("0.5*trG + 0.1*(det - 1)**2", 2)


def test_n2_oscillator_levels_and_degeneracies_exact():
    """d'Alembert, J = I Id, V = k/2 Tr(phi^T phi): E = hbar w (N + 2), multiplicity C(N+3, 3)
    (the R^4 oscillator), assembled from the (spin, vorticity) sectors."""
    s = sp.solve("dalembert", 2, oscillator2, HBAR, inertia=INERTIA, levels=35,
                 settings=sp.Settings(basis_size=14))
    assert [lv.multiplicity for lv in s.levels] == [comb(N + 3, 3) for N in range(4)]
    for N, lv in enumerate(s.levels):
        assert abs(lv.energy - HBAR * OMEGA * (N + 2)) < 1e-9
        assert lv.error < 1e-7
        # the (spin, vorticity) content: in the conformal/anticonformal planes (z, w) the R^4
        # oscillator has #{(n1, n2): 2 n1 + 2 n2 = N - |m1| - |m2|} states of angular momenta
        # (m1, m2), spin = m1 + m2, vorticity = m1 - m2
        content = {}
        for sec in lv.sectors:
            content[(sec.spin, sec.vorticity)] = content.get((sec.spin, sec.vorticity), 0) + 1
        expected = {}
        for m1 in range(-N, N + 1):
            for m2 in range(-N, N + 1):
                rest = N - abs(m1) - abs(m2)
                if rest >= 0 and rest % 2 == 0:
                    expected[(m1 + m2, m1 - m2)] = rest // 2 + 1
        assert content == expected
    assert not s.unconverged


def _scalar_multiplicity_by_characters(N: int) -> int:
    """Multiplicity of the trivial SO(3) x SO(3) irrep in Sym^N(V1 (x) V1) (= R^9 oscillator
    level N), from the weights: m(0,0) = c(0,0) - c(1,0) - c(0,1) + c(1,1), c(a, b) the number
    of degree-N monomials in the 9 weight vectors (i, j), i, j in {-1, 0, 1}, of weight (a, b)."""
    weights = list(product((-1, 0, 1), repeat=2))
    # multisets of size N of the 9 weights, by dynamic programming over the weights
    table = {((0, 0), 0): 1}
    for w in weights:
        new = {}
        for (wt, deg), c in table.items():
            for extra in range(N - deg + 1):
                key = ((wt[0] + extra * w[0], wt[1] + extra * w[1]), deg + extra)
                new[key] = new.get(key, 0) + c
        table = new
    counts = {wt: c for (wt, deg), c in table.items() if deg == N}
    c = lambda a, b: counts.get((a, b), 0)
    return c(0, 0) - c(1, 0) - c(0, 1) + c(1, 1)


def test_product_potential_matrix_is_the_dense_quadrature_product():
    """The potential's Galerkin matrix summed one factor at a time (what the n = 2 blocks
    use since 2026-11-29: at basis_size 80 the dense product took minutes per block) equals
    the dense product (B1 x B2)^T diag(V) (B1 x B2), for two different factor bases and a
    potential that does not separate."""
    from affinebody.quantum.bases import Hermite1D, Radial2D, product_potential_matrix

    f1, f2 = Radial2D(1, 7, 0.8, 19), Hermite1D(5, 1.3, 0.2, 13)
    (r, B1), (y, B2) = f1.nodes(), f2.nodes()
    R, Y = np.meshgrid(r, y, indexing="ij")
    V = np.exp(-R * Y) + R**2 * np.cos(Y)
    B = (B1[:, None, :, None] * B2[None, :, None, :]).reshape(19 * 13, 7 * 5)
    dense = B.T @ (V.reshape(-1, 1) * B)
    got = product_potential_matrix(B1, B2, V)
    np.testing.assert_allclose(got, dense, rtol=0, atol=1e-13 * np.max(np.abs(dense)))
    np.testing.assert_allclose(got, got.T, rtol=0, atol=1e-13 * np.max(np.abs(dense)))


def test_check_bases_find_only_the_lowest_levels_and_agree_with_the_full_spectrum(monkeypatch):
    """solve_block's nested and widened check bases are diagonalised for their ``count`` lowest
    eigenvalues only (LAPACK's subset by index; the whole spectrum, cut short, was computed
    before), and the energies and error estimates are those of the full spectra to 1e-12
    relative (an anharmonic d'Alembert block, and a count above the nested basis's size)."""
    from scipy import linalg

    from affinebody.quantum import bases
    from affinebody.quantum.n2 import lebesgue2_block

    settings = sp.Settings(basis_size=12)

    def build(size, scale):
        return lebesgue2_block(anharmonic, 1.0, 1.0, 1, 2, size, scale)
    full_E = linalg.eigvalsh(build(12, 0.7)[0])
    asked = []
    plain = linalg.eigvalsh

    def recording(H, *args, **kwargs):
        window = kwargs.get("subset_by_index")
        asked.append(H.shape[0] if window is None else window[1] - window[0] + 1)
        return plain(H, *args, **kwargs)
    monkeypatch.setattr(bases.linalg, "eigvalsh", recording)
    for count in (9, 80):  # 80 > the 8 x 8 = 64 functions of the nested check basis
        E, vec, err, _ = bases.solve_block(build, 12, 0.7, count, settings)
        shrunk = plain(build(8, 0.7)[0])[:count]
        widened = plain(build(12, 0.7 * settings.check_widen)[0])[:count]
        k = min(len(E), len(shrunk))
        expected = np.full(len(E), np.inf)
        expected[:k] = np.maximum(np.abs(E[:k] - shrunk[:k]), np.abs(E[:k] - widened[:k]))
        expected = bases.level_errors(E, expected, settings)
        np.testing.assert_allclose(E, full_E[:count], rtol=1e-12)
        np.testing.assert_allclose(err, expected, rtol=1e-9, atol=1e-12 * np.max(np.abs(E)))
    assert asked and max(asked) <= 80 and asked[:2] == [9, 9]


@pytest.mark.parametrize("hbar,inertia,k", [(0.8, 1.3, 2.0), (1.0, 2.0, 8.0), (0.3, 0.7, 0.5)])
def test_auto_scale_of_an_oscillator_is_its_length(hbar, inertia, k):
    """For V = k Tr G / 2 the basis length is the oscillator's, b^2 = hbar / (2 I omega) with
    omega = sqrt(k / I) (the Gaussian exp(-(|z|^2 + |w|^2) / 2b^2) is the ground state). The
    small basis's lowest levels are flat in b to round-off there, and its minimum had been
    round-off's choice (1 % off after a change of summation order)."""
    from affinebody.quantum.n2 import auto_scale_lebesgue2

    exact = math.sqrt(hbar / (2 * inertia * math.sqrt(k / inertia)))
    b = auto_scale_lebesgue2(lambda q: 0.5 * k * np.sum(q**2, axis=-1), hbar, inertia)
    assert abs(b / exact - 1) < 2e-3


def test_character_count_matches_invariant_count():
    # sanity of the group theory used below: Chevalley (invariants of degrees 2, 3, 4)
    for N in range(9):
        invariants = sum(1 for i in range(5) for j in range(4) for k in range(3)
                         if 2 * i + 3 * j + 4 * k == N)
        assert _scalar_multiplicity_by_characters(N) == invariants


def test_n3_scalar_sector_oscillator_exact_with_group_theory_multiplicities():
    """n = 3 d'Alembert, spin = vorticity = 0: E = hbar w (N + 9/2) to 1e-9 with the multiplicity
    of the trivial SO(3) x SO(3) irrep in the R^9 level N; parity (-1)^(det-degree)."""
    s = sp.solve("dalembert", 3, oscillator, HBAR, inertia=INERTIA, levels=6, sectors="scalar",
                 settings=sp.Settings(basis_size=10, check_shrink=2))
    found = {}
    for lv in s.levels:
        N = (lv.energy / (HBAR * OMEGA)) - 4.5
        assert abs(N - round(N)) * HBAR * OMEGA < 1e-9
        found[round(N)] = found.get(round(N), 0) + lv.multiplicity
    assert max(found) >= 6
    for N in range(7):
        assert found.get(N, 0) == _scalar_multiplicity_by_characters(N)
    odd = [lv for lv in s.levels if round(lv.energy / (HBAR * OMEGA) - 4.5) == 3]
    assert all(sec.parity == -1 for lv in odd for sec in lv.sectors)


def test_reduced_solver_agrees_with_cartesian_solver_anharmonic():
    """An anharmonic rotation-invariant V on L(2, R): two-polar reduction vs a Hermite Galerkin
    solver in R^4 that evaluates V through an SVD of phi (no reduction)."""
    count = 15
    s = sp.solve("dalembert", 2, anharmonic, 1.0, inertia=1.0, levels=count,
                 settings=sp.Settings(basis_size=18))
    reduced = np.array(s.energies(count))
    cartesian = cartesian_n2_levels(anharmonic, 1.0, 1.0, count, size=16,
                                       scale=s.settings["scale"])
    assert len(reduced) == count
    assert np.max(np.abs(reduced - cartesian)) < 1e-8


def test_free_affine_motion_reports_no_bound_states():
    """af-is on GL+(2) with a potential of det phi alone: q1 - q2 is free (continuous spectrum
    above hbar^2/4M); the solver must flag the pseudo-levels instead of listing them."""
    V = lambda Q: 2.0 * np.log(np.abs(np.prod(Q, -1))) ** 2
    s = sp.solve("af-is", 2, V, 1.0, I=1.0, A=0.2, B=0.1, levels=4,
                 settings=sp.Settings(basis_size=12, max_spin=1, scale=1.0, scale_sigma=0.5,
                                      centre=0.0))
    assert s.levels == [] or all(lv.energy > 10 for lv in s.levels)
    assert s.unconverged


def test_given_affine_scales_are_used_for_a_potential_that_does_not_confine():
    """af-is with V = tr G: V -> 0 as det phi -> 0, so the dilatation is free there
    (continuous spectrum, no level may be claimed). With scale, scale_sigma and centre all
    given, the solver must use them as given: it ran the automatic search anyway, whose
    trial scales overflow tr G = e^(2 q1) + e^(2 q2), and stopped on LAPACK's refusal of a
    non-finite matrix."""
    s = sp.solve("af-is", 2, compile_potential("trG", 2), 1.0, I=1.0, A=0.2, B=0.3, levels=4,
                 settings=sp.Settings(basis_size=12, max_spin=1, scale=1.0, scale_sigma=1.0,
                                      centre=0.0))
    assert (s.settings["scale"], s.settings["scale_sigma"], s.settings["centre"]) == (1, 1, 0)
    assert s.levels == [] and s.unconverged


@pytest.mark.parametrize("auto_scale", [auto_scale_haar2, auto_scale_haar3], ids=["n2", "n3"])
def test_auto_scale_of_the_affine_basis_minimises_over_the_scales_not_given(auto_scale):
    """With some of (scale, scale_sigma, centre) given, the others minimise the same
    objective with those held (n = 3 had searched all three and then overridden): given the
    full minimiser's scale and centre, the free scale_sigma is the full minimiser's
    (V = c sum q_a^2, whose objective sets scale_sigma sharply)."""
    V = lambda Q: 1.5 * np.sum(np.log(np.abs(Q)) ** 2, axis=-1)
    inertia = AffineInertia("af-is", 1.0, 0.2, 0.3)
    full = auto_scale(V, 1.0, inertia)
    given = auto_scale(V, 1.0, inertia, (full[0], None, full[2]))
    assert (given[0], given[2]) == (full[0], full[2])
    assert abs(np.log(given[1] / full[1])) < 1e-2


def test_confined_affine_model_converges_and_respects_dilatation_separation():
    """af-is with V = c (q1^2 + q2^2) = c (sigma^2 + x^2)/2: the dilatation sigma = ln det phi
    separates and is an oscillator whose mass follows from m_q = n (I + A + n B) for
    q = ln(det phi)/n (docs/theory/exact-flows.md), so E_1 - E_0 of the scalar sector is its
    quantum."""
    I, A, B, c = 1.0, 0.2, 0.3, 1.5
    V = lambda Q: c * np.sum(np.log(np.abs(Q)) ** 2, axis=-1)
    inert = AffineInertia("af-is", I, A, B)
    mass = inert.dilatation / 2
    length = (1 / (mass * c)) ** 0.25  # oscillator length of the sigma mode: exact in sigma
    H, _ = haar2_block(V, 1.0, inert, 0, 0, (20, 12), (0.6, length), 0.0)
    E = np.linalg.eigvalsh(H)
    # sigma part: -(hbar^2/(M + 2B)) d^2/dsigma^2 + (c/2) sigma^2, i.e. mass (M + 2B)/2 and
    # spring c: hbar w with w = sqrt(2 c / (M + 2B))
    w_sigma = np.sqrt(2 * c / inert.dilatation)
    assert np.min(np.abs(E[1:6] - E[0] - w_sigma)) < 1e-9


def test_density_marginals_integrate_to_one():
    s = sp.solve("dalembert", 2, anharmonic, 1.0, inertia=1.0, levels=4,
                 settings=sp.Settings(basis_size=14))
    for state in (0, 3):
        d = densities(s, state)
        assert abs(d["normalisation"] - 1) < 1e-8
        for m in d["details"].values():
            assert abs(m.integral - 1) < 1e-10
            assert np.all(m.density >= 0)
        o = d["orientation"]
        assert abs(np.trapezoid(o["L_angle"], o["angle"]) - 1) < 1e-12


def test_potential_invariants_consistent():
    V = compile_potential("trG - K1 + det - Q1*Q2 + exp(q1) - Q1", 2)
    Q = np.array([[2.0, -0.5], [1.5, 0.3]])
    assert np.allclose(V(Q), 0.0, atol=1e-14)


@pytest.mark.parametrize("text, fragment", [
    ("[system]\nn = 2\n[quantum]\nhbar = -1\npotential = 'trG'\n", "quantum.hbar must be > 0"),
    ("[system]\nn = 2\n[quantum]\nkinetic = 'af-is'\nI = 0.2\nA = 0.5\npotential = 'trG'\n",
     "quantum.I must be > |quantum.A|"),
    ("[system]\nn = 2\n[quantum]\npotential = 'trG'\nfoo = 1\n", "quantum.foo"),
    ("[system]\nn = 2\n[quantum]\npotential = 'trG + x'\n", "quantum.potential"),
    ("[system]\nn = 2\n[quantum]\npotential = 'trG'\nsectors = 'spin1'\n", "quantum.sectors"),
    ("[system]\nn = 3\n[quantum]\npotential = 'trG'\nmax_spin = 9\n", "quantum.max_spin"),
])
def test_config_errors_are_one_line(text, fragment):
    with pytest.raises(ConfigError) as err:
        parse(text)
    message = str(err.value)
    assert fragment in message and "\n" not in message and message.startswith("config error")


@pytest.mark.parametrize("kwargs, needle", [
    ({"hbar": 0.0}, "hbar must be a finite number > 0"),  # returned unconverged candidates
    ({"hbar": float("nan")}, "hbar must be a finite number > 0"),  # a SciPy message before
    ({"inertia": 0.0}, "inertia must be > 0"),  # a ZeroDivisionError before
    ({"A": float("inf")}, "quantum.A must be finite"),
    ({"levels": 0}, "levels must be >= 1"),
])
def test_solve_refuses_bad_constants_naming_them(kwargs, needle):
    """From Python (affinebody.solve_spectrum): constants that have no spectrum are refused
    at once in one line naming them (found by an audit of the API)."""
    args = {"hbar": 1.0, **kwargs}
    hbar = args.pop("hbar")
    with pytest.raises(ValueError, match=needle):
        sp.solve("dalembert", 2, lambda q: 0.5 * np.sum(np.exp(2 * q), axis=-1), hbar, **args)
