"""n = 3: every SO(3) x SO(3) sector (j, j') of the two-polar reduction (quantum/covariants3.py,
quantum/n3.py): representation theory checked against itself and the group, restricted
covariants against the wall conditions of smooth wave functions, sector spectra against the
R^9 oscillator (all degeneracies) and against an independent R^9 radial solver."""

import json
from itertools import product
from math import comb

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import linalg

from affinebody.quantum import channels3 as ch3
from affinebody.quantum import covariants3 as cov
from affinebody.quantum import n3
from affinebody.quantum import spectra as sp
from affinebody.quantum.cli import density, spectrum
from affinebody.quantum.config import compile_potential
from affinebody.quantum.levels import AffineInertia
from oracles import r9_radial_levels

PAIRS = ((0, 1), (0, 2), (1, 2))


def so3_generator(a, b):
    K = np.zeros((3, 3))
    K[b, a], K[a, b] = 1.0, -1.0
    return K


@pytest.mark.parametrize("j", [0, 1, 2, 3, 4])
def test_rotation_generators_represent_so3(j):
    """K_ab on V_j: antisymmetric, Casimir -j(j+1), and a Lie algebra homomorphism
    [K_g, K_h] = K_[g, h] (the bracket computed in the defining representation)."""
    K = cov.rotation_generators(j)
    assert np.allclose(K, -K.transpose(0, 2, 1), atol=1e-12)
    assert np.allclose(sum(k @ k for k in K), -j * (j + 1) * np.eye(2 * j + 1), atol=1e-10)
    defining = [so3_generator(a, b) for a, b in PAIRS]
    basis = np.array([d.ravel() for d in defining]).T
    for g, h in product(range(3), repeat=2):
        bracket = defining[g] @ defining[h] - defining[h] @ defining[g]
        c = np.linalg.lstsq(basis, bracket.ravel(), rcond=None)[0]
        assert np.allclose(K[g] @ K[h] - K[h] @ K[g], np.tensordot(c, K, 1), atol=1e-10)


def test_harmonic_basis_is_orthonormal_and_harmonic_by_quadrature():
    """Y_j orthonormal under dOmega/4pi (checked by a product Gauss quadrature on S^2, not by
    the moment formula used to build it)."""
    z, wz = np.polynomial.legendre.leggauss(12)
    phi = np.linspace(0, 2 * np.pi, 25)[:-1]
    Z, P = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z**2)
    u = np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3)
    w = (wz[:, None] * np.full(phi.shape, 1 / len(phi))).ravel() / 2
    for j in range(5):
        mono = np.array([np.prod(u ** np.array(e), -1) for e in cov.monomials(j)]).T
        Y = mono @ cov.harmonic_basis(j)
        assert np.allclose(Y.T @ (w[:, None] * Y), np.eye(2 * j + 1), atol=1e-12)


@pytest.mark.parametrize("degree", range(7))
def test_multiplicities_add_up_to_the_polynomial_dimension(degree):
    """sum over (j, j') of multiplicity x (2j+1)(2j'+1) = dim of the degree-d polynomials on
    R^9 = C(d + 8, 8): the weight counting is complete and consistent."""
    total = sum(cov.polynomial_multiplicity(j, jp, degree) * (2 * j + 1) * (2 * jp + 1)
                for j in range(degree + 1) for jp in range(degree + 1))
    assert total == comb(degree + 8, 8)


@pytest.mark.parametrize("j, jp", [(0, 0), (1, 1), (0, 2), (1, 2), (2, 1), (2, 2), (0, 3),
                                   (1, 3), (3, 3), (2, 4)])
def test_covariant_module_is_free_with_kostant_rallis_rank(j, jp):
    """The generators number dim (V_j (x) V_j')^M, and generators x invariant monomials
    (p2, e3, p4) count, degree by degree, exactly the multiplicity of (j, j') in the
    polynomials of that degree: the module is free on them (Hilbert series agree to d = 14)."""
    gens = cov.module_generators(j, jp)
    assert len(gens) == cov.fixed_dimension(j, jp)
    for d in range(15):
        products = sum(1 for gd, _ in gens for a, b, c in product(range(8), range(5), range(4))
                       if gd + 2 * a + 3 * b + 4 * c == d)
        assert products == cov.polynomial_multiplicity(j, jp, d), d


@pytest.mark.parametrize("j, jp", [(1, 1), (0, 2), (1, 2), (2, 2), (1, 3)])
def test_restricted_covariants_satisfy_the_wall_conditions(j, jp):
    """On the wall x_a = x_b the joint rotation of L and R fixes diag x, so every restricted
    covariant is annihilated by K_ab (x) 1 + 1 (x) K_ab there; on x_a = -x_b by the
    difference. Off the walls neither vanishes (the check can fail)."""
    alg = n3.sector_algebra(j, jp)
    E = alg.E
    Kj, Kjp = cov.rotation_generators(j), cov.rotation_generators(jp)
    rng = np.random.default_rng(7)
    for g, (a, b) in enumerate(PAIRS):
        plus = (np.kron(Kj[g], np.eye(2 * jp + 1)) + np.kron(np.eye(2 * j + 1), Kjp[g])) @ E
        minus = (np.kron(Kj[g], np.eye(2 * jp + 1)) - np.kron(np.eye(2 * j + 1), Kjp[g])) @ E
        x = rng.normal(size=(4, 3))
        on = x.copy()
        on[:, b] = on[:, a]
        anti = x.copy()
        anti[:, b] = -anti[:, a]
        for pts, A in ((on, plus), (anti, minus)):
            f, _, _ = n3.generator_values(alg, pts)
            assert np.abs(np.einsum("mr,prk->pmk", A, f)).max() < 1e-11 * np.abs(f).max()
        f, _, _ = n3.generator_values(alg, x)
        assert np.abs(np.einsum("mr,prk->pmk", plus, f)).max() > 1e-3 * np.abs(f).max()


@pytest.fixture(scope="module")
def chamber_grid():
    quad = ch3.ChamberQuadrature.build(8.0 + 0.75 * np.sqrt(5), n_rho=48, n_angle=20)
    return ch3.Grid3(quad.nodes, quad.weights)


def test_r9_oscillator_every_sector_exact_with_full_degeneracies(chamber_grid):
    """d'Alembert, J = Id, V = Tr(phi^T phi)/2: every sector's levels are N + 9/2 to 1e-9, and
    summing (2j+1)(2j'+1) over the sectors gives the R^9 degeneracies C(N+8, 8) for
    N = 0..4 (1, 9, 45, 165, 495)."""
    def V(Q):
        return 0.5 * np.sum(Q**2, -1)
    states: dict[int, int] = {}
    for shell in n3.sectors_by_shell(4):
        for j, jp in shell:
            H, _ = n3.sector_block("lebesgue3", V, 1.0, 1.0, chamber_grid, j, jp, 4, 1.0)
            if H.size == 0:
                continue
            N = linalg.eigvalsh(H) - 4.5
            assert np.abs(N - np.round(N)).max() < 1e-9
            for k in np.round(N).astype(int):
                states[k] = states.get(k, 0) + n3.sector_dimension(j, jp)
    assert states == {N: comb(N + 8, 8) for N in range(5)}


def test_sector_spectra_equal_r9_radial_spectra_for_an_anharmonic_potential(chamber_grid):
    """V = r^2/2 + 0.8 exp(-r^2/2), r = |phi|: the R^9 problem separates in hyperspherical
    harmonics, whose (j, j') content at degree l is mult(l) - mult(l - 2); so each sector's
    levels are radial levels E(l, k) with those multiplicities. Independent of the reduction."""
    def Vr(r):
        return 0.5 * r**2 + 0.8 * np.exp(-(r**2) / 2)

    def VQ(Q):
        return Vr(np.sqrt(np.sum(Q**2, -1)))
    radial = {ell: r9_radial_levels(Vr, ell, 4) for ell in range(7)}

    def harmonic_content(j, jp, ell):
        lower = cov.polynomial_multiplicity(j, jp, ell - 2) if ell >= 2 else 0
        return cov.polynomial_multiplicity(j, jp, ell) - lower
    errors = {}
    for degree in (6, 8):
        worst = 0.0
        for j, jp in ((0, 0), (1, 1), (0, 2), (1, 2), (2, 2)):
            H, _ = n3.sector_block("lebesgue3", VQ, 1.0, 1.0, chamber_grid, j, jp, degree, 1.0)
            E = linalg.eigvalsh(H)[:3]
            expected = sorted(e for ell in range(7) for e in radial[ell]
                              for _ in range(harmonic_content(j, jp, ell)))[:3]
            worst = max(worst, np.abs(E - expected).max())
        errors[degree] = worst
    # algebraic convergence of Gaussian x polynomial bases for a non-polynomial V; a wrong
    # centrifugal coupling or sector content would be off by O(0.1)
    assert errors[8] < 2e-4 and errors[8] < errors[6] / 3


def test_affine_models_are_each_others_transpose_in_every_sector():
    """phi -> phi^T swaps spin and vorticity and af-is (74) with is-af (73): the sector (j, j')
    of af-is has the spectrum of (j', j) of is-af; (j, j') and (j', j) of af-is differ (the
    vorticity Casimir term hbar^2 j'(j'+1)/(2 I~) is not symmetric)."""
    def V(Q):
        q = np.log(Q)
        return 0.5 * np.sum(q**2, -1) + 0.3 * np.sum(q, -1) ** 2
    grid = ch3.haar3_grid(0.7, 0.7, 0.0, 24, 12, 8)
    spectra = {}
    for model in ("af-is", "is-af"):
        inertia = AffineInertia(model, 1.0, 0.3, 0.2)
        for jj in ((0, 2), (2, 0), (1, 2), (2, 1)):
            H, _ = n3.sector_block("haar3", V, 1.0, inertia, grid, *jj, 4, 0.7, 0.7, 0.0)
            spectra[model, jj] = linalg.eigvalsh(H)[:4]
    for jj in ((0, 2), (1, 2)):
        assert np.allclose(spectra["af-is", jj], spectra["is-af", jj[::-1]], atol=1e-10)
        assert np.abs(spectra["af-is", jj] - spectra["af-is", jj[::-1]]).max() > 0.1


def test_general_sector_machinery_reproduces_the_dedicated_spin1_channel(chamber_grid):
    """(1, 1) by the covariant basis and generator matrices equals the dedicated spin-1
    channel (Cartesian F = diag f, divided differences) on an anharmonic d'Alembert potential:
    two implementations of the same reduced operator."""
    def V(Q):
        return 0.5 * np.sum(Q**2, -1) + 0.05 * np.prod(Q, -1) + 0.02 * np.sum(Q**4, -1)
    H_new, _ = n3.sector_block("lebesgue3", V, 1.0, 1.0, chamber_grid, 1, 1, 8, 0.9)
    H_old, _ = ch3.channel3_block("lebesgue3", V, 1.0, 1.0, chamber_grid, 8, 0.9, spin1=True)
    assert np.allclose(linalg.eigvalsh(H_new)[:6], linalg.eigvalsh(H_old)[:6], atol=1e-9)


N3_ALL = """
[system]
n = 3
[quantum]
kinetic = "dalembert"
inertia = 1.0
potential = "0.5*trG"
basis_size = 4
scale = 1.0
"""


def test_spectrum_cli_n3_default_is_every_sector_with_oscillator_degeneracies(tmp_path):
    """`affinebody spectrum` for n = 3 (default sectors = all): the lowest 55 states of the R^9
    oscillator are 1 x 9/2, 9 x 11/2, 45 x 13/2 with their sector labels; the density of a
    state of the (2, 2) sector integrates to 1."""
    path = tmp_path / "n3.toml"
    path.write_text(N3_ALL)
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "55", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    expected = [N + 4.5 for N, m in ((0, 1), (1, 9), (2, 45)) for _ in range(m)]
    assert np.allclose(data["energies"], expected, atol=1e-9, rtol=0)
    assert [s["multiplicity"] for s in data["states"]] == [1, 9, 45]
    labels = {(s["spin"], s["vorticity"]) for s in data["states"][2]["sectors"]}
    assert labels == {(0, 0), (0, 2), (2, 0), (1, 1), (2, 2)}
    assert data["sectors"] == "all" and not data["warnings"]
    # the expression potential has a certified bound per sector (j, j'): the list is complete
    assert data["certified"] is True and data["complete"] is True
    assert data["certificate"].startswith("certified") and data["unknown_states"] == []
    out = tmp_path / "dens"
    state = next(i for i, e in enumerate(data["energies"]) if e > 6)
    result = CliRunner().invoke(density, [str(path), "--state", str(state), "-o", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "densities.json").read_text())
    assert abs(summary["normalisation"] - 1) < 1e-8


def test_progress_names_every_sector_solved():
    """The progress callback (a status line in the CLI) is called once per sector solved, and
    the search stops on the certificate: a sector is solved only if its certified bound
    sqrt(d (d + 7)) (V = |Q|^2/2, d its lowest degree) does not exceed the 10th state 11/2,
    so d <= 3 (sqrt 30 = 5.48 < 5.5 < sqrt 44)."""
    lines = []
    s = sp.solve("dalembert", 3, compile_potential("0.5*trG", 3), 1.0, levels=10,
                 settings=sp.Settings(basis_size=4, scale=1.0, check_shrink=2),
                 progress=lines.append)
    solved = {(k[1], k[2]) for k in s.blocks}
    assert len(lines) == len(solved)
    in_order = sorted(solved, key=lambda p: (max(p), p))
    assert all(f"({j}, {jp})" in line for line, (j, jp) in zip(lines, in_order, strict=True))
    assert {n3.lowest_degree(*p) for p in solved} == {0, 1, 2, 3}
    assert s.certified and s.complete()
    assert s.energies() == pytest.approx([4.5] + [5.5] * 9, abs=1e-10)


def test_sector_basis_is_orthonormal_and_independent_of_chunking(chamber_grid):
    """The basis evaluated on demand is orthonormal under the measure, and the Hamiltonian does
    not depend on how the nodes are chunked (tall-skinny QR of the chunks' R factors; the
    blocks agree up to the signs of the basis functions)."""
    def V(Q):
        return 0.5 * np.sum(Q**2, -1) + 0.05 * np.prod(Q, -1)
    H, basis = n3.sector_block("lebesgue3", V, 1.0, 1.0, chamber_grid, 2, 2, 6, 1.0,
                               chunk_floats=2**14)
    H_one, _ = n3.sector_block("lebesgue3", V, 1.0, 1.0, chamber_grid, 2, 2, 6, 1.0,
                               chunk_floats=2**30)
    v = basis.values()
    gram = np.einsum("prk,p,prl->kl", v, chamber_grid.weights, v)
    assert np.allclose(gram, np.eye(len(gram)), atol=1e-12)
    assert np.allclose(np.abs(H), np.abs(H_one), atol=1e-12)
    assert np.allclose(linalg.eigvalsh(H), linalg.eigvalsh(H_one), atol=1e-12)


def test_every_sector_of_a_continuous_spectrum_is_flagged():
    """af-is on GL+(3) with V = 2 (ln det phi)^2: the SL(3) part is free (no discrete series),
    so with every sector searched no level is reported; each candidate moves with the basis."""
    def V(Q):
        return 2.0 * np.sum(np.log(Q), -1) ** 2
    s = sp.solve("af-is", 3, V, 1.0, I=1.0, A=0.3, B=0.2, levels=6,
                 settings=sp.Settings(basis_size=6, check_shrink=2, scale=3.0, scale_sigma=0.84,
                                      centre=0.0, max_spin=1))
    assert s.levels == [] and s.sectors == "all" and not s.certified
    assert len({(k[1], k[2]) for k in s.blocks}) >= 2
    assert len(s.unconverged) >= 6 and min(lv.error for lv in s.unconverged) > 1e-3


#: README's n = 3 potential: with an affine kinetic energy it tends to 0.8 as det phi -> 0
#: (trG -> 0) and is at least 0.8 everywhere (0.5 x + 0.8 e^(-x/2) >= 0.8 for x = trG >= 0),
#: so the body collapses freely in sigma = ln det phi: a continuous spectrum, no level
README_N3 = "0.5*trG + 0.8*exp(-trG/2) + 0.5*det**2*exp(-trG/2)"


def test_affine_potential_that_does_not_confine_is_refused_before_any_sector():
    """af-is with README's n = 3 potential: the automatic basis drifts to the clip of its
    scales and a centre of -124 (a flat objective), and the search over every sector used
    over 12 min of CPU to report the ground state 'not converged' (error 7e-3, a
    pseudo-level). Now refused before any sector is solved (progress never called), in one
    line naming what to change; the same potential with a confining term in ln det phi is not
    refused."""
    import re

    lines = []
    with pytest.raises(ValueError) as err:
        sp.solve("af-is", 3, compile_potential(README_N3, 3), 1.0, I=1.0, A=0.2, B=0.1,
                 levels=1, settings=sp.Settings(basis_size=8, check_shrink=2, max_spin=0),
                 progress=lines.append)
    message = str(err.value)
    assert lines == [] and "\n" not in message
    assert message.startswith("the automatic basis of the n = 3 af-is model ran away")
    assert all(f"quantum.{key}" in message for key in ("potential", "scale", "scale_sigma",
                                                        "centre"))
    assert float(re.search(r"centre (\S+),", message).group(1)) < -50
    confined = ch3.setup3("af-is", compile_potential(README_N3 + " + 0.5*log(det)**2", 3), 1.0,
                          1.0, AffineInertia("af-is", 1.0, 0.2, 0.1),
                          sp.Settings(basis_size=8, check_shrink=2, scale=0.85, scale_sigma=1.0))
    assert abs(confined.centre) < 3  # automatic, a minimum: -1.2


@pytest.mark.parametrize("model", ["dalembert", "af-is", "is-af", "af-af"])
def test_sector_weak_form_is_the_reduced_operator_of_reduction_py(model):
    """The centrifugal and Casimir part of the weak form (r x r matrices on the M-fixed
    coordinates) equals E^T U_sector E of reduction.py -- whose operator is checked pointwise
    against the full operator on R^9 / GL(3) in test_quantum_reduction.py -- with rho, tau the
    spin-j, spin-j' generator matrices of covariants3 (same K_ab convention)."""
    from affinebody.quantum.reduction import Channel, TwoPolarReduction

    I_, A, B = (1.3, 0.0, 0.0) if model == "dalembert" else (1.0, 0.3, 0.2)
    red = TwoPolarReduction(model, 3, I=I_, A=A, B=B, hbar=0.8)
    inertia = I_ if model == "dalembert" else AffineInertia(model, I_, A, B)
    kind = "lebesgue3" if model == "dalembert" else "haar3"
    x = np.array([[1.3, 0.4, -0.2], [0.9, 0.5, 0.1]])
    for j, jp in ((2, 1), (2, 2), (0, 3)):
        Kj, Kjp = cov.rotation_generators(j), cov.rotation_generators(jp)
        channel = Channel(rho=np.array([np.kron(k, np.eye(2 * jp + 1)) for k in Kj]),
                          tau=np.array([np.kron(np.eye(2 * j + 1), k) for k in Kjp]))
        E = n3.sector_algebra(j, jp, "matrix" if kind == "lebesgue3" else "symmetric").E
        alg = n3.sector_algebra(j, jp)
        co = n3.sector_coefficients(kind, x, np.ones(len(x)), 0.8, inertia, j, jp)
        for p in range(len(x)):
            U = np.real(np.asarray(red.sector_potential(x[p], channel)))
            ours = (np.tensordot(co.c_plus[p], alg.N_plus, 1)
                    + np.tensordot(co.c_minus[p], alg.N_minus, 1) + co.casimir * np.eye(len(E.T)))
            assert np.allclose(E.T @ U @ E, ours, rtol=1e-12, atol=1e-12)


def test_spectrum_table_lists_unconverged_candidates_separately(tmp_path):
    """A potential the small basis cannot resolve to the tolerance: the table reports no level
    and lists the candidates, with error estimates above the tolerance, in a separate table;
    the command exits 3 (no level converged)."""
    path = tmp_path / "hard.toml"
    path.write_text(N3_ALL.replace('"0.5*trG"', '"0.5*trG + 0.1*(det - 1)**2"'))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "2"])
    assert result.exit_code == 3, result.output  # no level converged: written, then exit 3
    assert "only 0 of 2 states converged" in result.output
    assert "unconverged candidates" in result.output and "raise quantum.basis_size" in result.output
    data = json.loads(CliRunner().invoke(spectrum, [str(path), "--levels", "2", "--json"]).stdout)
    assert data["states"] == [] and all(u["error"] > 1e-7 for u in data["unconverged"])
