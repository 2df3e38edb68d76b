"""n = 3 (issues 16 and 20): the d'Alembert sectors in hyperspherical harmonics x Laguerre radial
functions (n3.harmonic_block, ``quantum.radial_size``) against the independent R^9 radial solver,
and the certified lower bounds per sector (j, j') that stop the sector search
(bounds.lebesgue3_shell_bounds, bounds.haar3_shell_bounds; docs/theory/two-polar.md, "Lower
bounds of an n = 3 sector")."""

import numpy as np
import pytest
from scipy import linalg

from affinebody.quantum import covariants3 as cov
from affinebody.quantum import n3
from affinebody.quantum import spectra as sp
from affinebody.quantum.bounds import (
    haar3_centrifugal_matrix_min,
    haar3_centrifugal_min,
    haar3_shell_bounds,
    lebesgue3_shell_bounds,
)
from affinebody.quantum.channels3 import ChamberQuadrature, haar3_grid
from affinebody.quantum.config import ConfigError, compile_potential, parse
from affinebody.quantum.intervals import Haar3Cells, Lebesgue3Cells, lower_bounds
from affinebody.quantum.levels import AffineInertia, Settings
from oracles import r9_radial_levels, r9_radial_states

BUMP = "0.5*trG + 0.8*exp(-trG/2)"  # r^2/2 + 0.8 exp(-r^2/2), r = |phi|
#: af-is: the dilatation sigma = ln det phi and the shear in harmonic wells
SHEAR3 = "0.5*(q1 + q2 + q3)**2 + 0.3*((q1 - q2)**2 + (q1 - q3)**2 + (q2 - q3)**2)"


def bump_radial(r):
    return 0.5 * r**2 + 0.8 * np.exp(-(r**2) / 2)


@pytest.mark.parametrize("sector", [(0, 0), (1, 2), (3, 3)])
def test_sector_harmonics_carry_the_laplacian_of_s8(sector):
    """The candidates orthonormalised on the chamber's sphere in the order of their degree are
    the sector's harmonics: the angular form (1/2 |grad_t Y|^2 plus the centrifugal terms of
    the reduced operator, n3.sector_forms) is L (L + 7) / 2 on degree L, the eigenvalue of
    -Lap_S8 / 2, and zero between different functions. A wrong centrifugal coefficient, a
    wrong covariant or a wrong tangential gradient breaks it."""
    algebra = n3.sector_algebra(*sector, "matrix")
    omega, w = ChamberQuadrature.sphere(30)
    _, L, Y, tY = n3.sphere_harmonics(algebra, omega, w, 8)
    A, S = n3.sector_forms("lebesgue3", algebra, np.zeros(len(omega)), 1.0, 1.0, omega, w, Y, tY)
    assert min(L) == cov.lowest_degree(*sector)
    assert np.allclose(S, np.eye(len(L)), atol=1e-12)
    assert np.allclose(A, np.diag(L * (L + 7) / 2.0), atol=1e-10)


def test_sixty_states_of_the_bump_potential_to_1e9_with_a_certificate():
    """V = r^2/2 + 0.8 exp(-r^2/2): the 60 lowest states (every sector, with multiplicity) at
    harmonic degree 6 x 16 radial functions agree with the sinc-DVR R^9 radial solver to 1e-9,
    the count of states below each energy is the independent count, and the list is certified
    complete (the sectors of lowest degree >= 5 are bounded by sqrt(60) > the 60th level)."""
    K = 60
    s = sp.solve("dalembert", 3, compile_potential(BUMP, 3), 1.0, inertia=1.0, levels=K,
                 settings=Settings(basis_size=6, radial_size=16, scale=1.0, check_shrink=2,
                                   tolerance=1e-9))
    reference = r9_radial_states(bump_radial, 400, max_degree=6, per_degree=3)
    got = np.array(s.energies(K))
    assert s.certified and s.complete(K)
    assert np.max(np.abs(got - reference[:K])) < 1e-9
    for threshold in (5.0, 6.0, 6.6, 7.5):
        assert np.sum(got < threshold) == np.sum(reference < threshold)


def test_a_potential_of_the_qa_separately_converges_in_the_harmonic_basis():
    """V = r^2/2 + 0.8 exp(-r^2/2) + det(phi)^2 exp(-r^2/2) depends on the Q_a separately. The
    harmonic basis (angular degree 12) and the Gaussian x polynomial basis of total degree 10
    (another basis, quadrature and assembly of the same reduced operator) bound the lowest
    levels of the sectors (0, 0), (1, 1) from above; they agree to the polynomial basis's
    accuracy, and the harmonic levels lie below (closer to the limit)."""
    def V(Q):
        r2 = np.sum(Q**2, -1)
        return 0.5 * r2 + 0.8 * np.exp(-r2 / 2) + np.prod(Q, -1) ** 2 * np.exp(-r2 / 2)
    grid = ChamberQuadrature.build(8.0 + 0.75 * np.sqrt(11), n_rho=60, n_angle=26)
    for sector in ((0, 0), (1, 1)):
        H, _ = n3.harmonic_block(V, 1.0, 1.0, *sector, 12, 20, 1.0, 2)
        E = linalg.eigvalsh(H)[:3]
        P, _ = n3.sector_block("lebesgue3", V, 1.0, 1.0, grid, *sector, 10, 1.0)
        Ep = linalg.eigvalsh(P)[:3]
        assert np.all(Ep - E > -1e-10) and np.max(Ep - E) < 5e-4


def test_the_coupling_of_a_qa_potential_matches_the_sphere_average_of_det_squared():
    """An independent check of how the harmonic basis treats a V of the Q_a separately: for
    V = r^2/2 + 0.8 e^(-r^2/2) + lam det(phi)^2 e^(-r^2/2), the derivative dE/dlam at lam = 0
    of the two lowest (0, 0) levels (radial states psi(r)) is <psi| det^2 e^(-r^2/2) |psi> =
    <det^2>_S8 <psi| r^6 e^(-r^2/2) |psi>, and <det^2>_S8 = E[det^2] / E[r^6] = 3! / (9 11 13)
    for a Gaussian 3 x 3 matrix. The radial expectation is the derivative in mu of the levels
    of the sinc-DVR R^9 radial solver with mu r^6 e^(-r^2/2) added (Hellmann-Feynman, central
    differences of step 1e-4 both); they agree to 1e-9 (relative 3e-8)."""
    def V(lam):
        def f(Q):
            r2 = np.sum(Q**2, -1)
            return 0.5 * r2 + 0.8 * np.exp(-r2 / 2) + lam * np.prod(Q, -1) ** 2 * np.exp(-r2 / 2)
        return f

    def radial(mu):
        return lambda r: bump_radial(r) + mu * r**6 * np.exp(-(r**2) / 2)
    h = 1e-4
    E = [linalg.eigvalsh(n3.harmonic_block(V(lam), 1.0, 1.0, 0, 0, 12, 16, 1.0, 2)[0])[:2]
         for lam in (-h, h)]
    R = [np.array(r9_radial_levels(radial(mu), 0, 2, 0.02, 10.0)) for mu in (-h, h)]
    slope = (E[1] - E[0]) / (2 * h)
    assert np.max(np.abs(slope - (R[1] - R[0]) / (2 * h) * 6 / 1287)) < 1e-9
    assert np.min(slope) > 0.02  # the coupling is not negligible


def test_lebesgue3_bounds_lie_below_every_sector_level():
    """The certified bound of each d'Alembert sector (j, j') is below its lowest level
    (computed variationally, an upper bound of the exact one), for a non-radial potential;
    and the bound of a sector grows with its lowest harmonic degree."""
    text = "0.5*trG + 0.1*K2/trG - 0.4*exp(-(det - 1)**2)"
    V = compile_potential(text, 3)
    bounds = lebesgue3_shell_bounds(V, 1.0, 1.0, 4, 1.0)
    for j, jp in ((0, 0), (1, 1), (0, 2), (1, 3), (2, 2)):
        H, _ = n3.harmonic_block(V, 1.0, 1.0, j, jp, 6, 10, 1.0, 2)
        assert bounds.of((j, jp)) <= linalg.eigvalsh(H)[0]
    assert bounds.of((0, 3)) > bounds.of((1, 1)) > bounds.of((0, 0))
    assert bounds.tail >= bounds.shell_min[-1]


#: the scales `affinebody spectrum` chooses for SHEAR3 (af-is): (scale, scale_sigma, centre)
SHEAR3_SCALES = (0.8118, 1.1893, 0.0037)


@pytest.fixture(scope="module")
def shear3_af_is():
    """af-is bounds for SHEAR3 at the command's scales, sectors bounded one by one to shell 12,
    and the quadrature grid of those scales."""
    scale, scale_sigma, centre = SHEAR3_SCALES
    inert = AffineInertia("af-is", 1.0, 0.2, 0.1)
    bounds = haar3_shell_bounds(compile_potential(SHEAR3, 3), 1.0, inert, 6, centre,
                                scale_sigma, scale, enumerate_to=12)
    return inert, bounds, haar3_grid(scale, scale_sigma, centre, 28, 14, 10)


def test_haar3_bounds_lie_below_every_sector_level(shear3_af_is):
    """af-is and is-af: the certified bound (dilatation oscillator + shear ground-state
    representation + centrifugal forms and matrices) is below each sector's lowest level, for a
    shear potential, and it holds most of the zero-point energy: in the scalar sector, where
    the centrifugal terms vanish, it is above 0.7 of the level (the former bound, the plain
    inf V = 0, had none of it)."""
    V = compile_potential(SHEAR3, 3)
    scale, scale_sigma, centre = SHEAR3_SCALES
    is_af = AffineInertia("is-af", 1.0, 0.2, 0.1)
    for inert, bounds, grid in (shear3_af_is, (is_af, haar3_shell_bounds(
            V, 1.0, is_af, 3, centre, scale_sigma, scale), shear3_af_is[2])):
        for j, jp in ((0, 0), (1, 1), (2, 0), (0, 2), (2, 1)):
            H, _ = n3.sector_block("haar3", V, 1.0, inert, grid, j, jp, 4, scale, scale_sigma,
                                   centre)
            E0 = linalg.eigvalsh(H)[0]
            assert bounds.of((j, jp)) <= E0
            if (j, jp) == (0, 0):
                assert bounds.of((j, jp)) > 0.7 * E0
        assert bounds.tail > bounds.of((0, 0))


def test_haar3_bounds_certify_the_readme_af_is_list(shear3_af_is):
    """af-is, V = sigma^2/2 + 0.3 sum (q_a - q_b)^2 (I = 1, A = 0.2, B = 0.1), K = 10, at the
    scales `affinebody spectrum` chooses: the ground level of (0, 0) and the nine states of the
    (1, 1) level (Galerkin, so at or above the exact ones) are ten states at or below 5.503,
    and every sector beyond shell 6 (shells 7 to 12 one by one, then the tail) has a certified
    bound above that, led by the rotor sectors (7, 1) and (8, 0) (docs/theory/two-polar.md,
    "Measured, the example above")."""
    inert, bounds, grid = shear3_af_is
    scale, scale_sigma, centre = SHEAR3_SCALES
    tenth = linalg.eigvalsh(n3.sector_block("haar3", compile_potential(SHEAR3, 3), 1.0, inert,
                                            grid, 1, 1, 4, scale, scale_sigma, centre)[0])[0]
    assert tenth < 5.51 and bounds.beyond(6) > tenth + 0.1
    assert min(bounds.of((7, 1)), bounds.of((8, 0))) < bounds.of((7, 0))


def test_n3_cell_enclosures_hold_on_random_points():
    """Lower bounds of V on n = 3 cells never exceed V at points of the cell: d'Alembert
    (rho, theta, psi) and affine (r, t, sigma) cells, unbounded ones included."""
    rng = np.random.default_rng(3)
    texts = ("0.5*trG - 3*exp(-(Q1 - Q2)**2) + 0.1*det**2/trG**2", "K3/(1 + K1) - q1*q3",
             "0.5*(q1 + q2 + q3)**2 - 4*Q1*Q3/(Q1 + Q3)**2 + sin(q2)")
    r_e = np.array([0.0, 0.5, 1.5, 4.0, np.inf])
    t_e = np.linspace(0.0, np.arctan(np.sqrt(2.0)), 4)
    p_e = np.linspace(-np.pi / 4, np.pi / 4, 4)
    lo = np.meshgrid(r_e[:-1], t_e[:-1], p_e[:-1], indexing="ij")
    hi = np.meshgrid(r_e[1:], t_e[1:], p_e[1:], indexing="ij")
    rho, th, ps = rng.uniform(0, 9, 20000), rng.uniform(0, t_e[-1], 20000), \
        rng.uniform(-np.pi / 4, np.pi / 4, 20000)
    Q = rho[:, None] * np.stack([np.cos(th), np.sin(th) * np.cos(ps), np.sin(th) * np.sin(ps)],
                                -1)
    idx = tuple(np.searchsorted(e, v, side="right") - 1 for e, v in ((r_e, rho), (t_e, th),
                                                                        (p_e, ps)))
    for text in texts[:2]:
        lb = lower_bounds(text, Lebesgue3Cells(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        assert np.all(compile_potential(text, 3)(Q) >= lb[idx]), text
    s_e = np.array([-np.inf, -3.0, 0.0, 1.0, np.inf])
    tt_e = np.linspace(np.pi / 6, np.pi / 2, 4)
    lo = np.meshgrid(r_e[:-1], tt_e[:-1], s_e[:-1], indexing="ij")
    hi = np.meshgrid(r_e[1:], tt_e[1:], s_e[1:], indexing="ij")
    r, t, sig = rng.uniform(0, 9, 20000), rng.uniform(np.pi / 6, np.pi / 2, 20000), \
        rng.uniform(-6, 6, 20000)
    eu, ev = np.array([1.0, -1.0, 0.0]) / np.sqrt(2), np.array([1.0, 1.0, -2.0]) / np.sqrt(6)
    q = sig[:, None] / 3 + r[:, None] * (np.cos(t)[:, None] * eu + np.sin(t)[:, None] * ev)
    idx = tuple(np.searchsorted(e, v, side="right") - 1 for e, v in ((r_e, r), (tt_e, t),
                                                                        (s_e, sig)))
    for text in texts[1:]:
        lb = lower_bounds(text, Haar3Cells(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        assert np.all(compile_potential(text, 3)(np.exp(q)) >= lb[idx]), text


@pytest.mark.parametrize("extra, field", [
    ("kinetic = 'af-is'\nI = 1.0\nA = 0.2\nradial_size = 12\n", "quantum.radial_size"),
    ("inertia = 1.0\nradial_size = 2\n", "quantum.radial_size"),
    ("inertia = 1.0\nsectors = 'scalar'\nradial_size = 12\n", "quantum.radial_size")])
def test_radial_size_is_refused_where_it_does_not_apply(extra, field):
    """radial_size is the d'Alembert n = 3 every-sector basis only: elsewhere, or out of range,
    one line naming the field."""
    with pytest.raises(ConfigError) as err:
        parse("[system]\nn = 3\n[quantum]\npotential = 'trG'\n" + extra)
    assert field in str(err.value) and "\n" not in str(err.value)


#: af-is ring well in the shear plane: sigma^2/2 + 0.3 (r - 3)^2, r^2 = sum (q_a - q_b)^2 / 3
RING = ("0.5*(q1 + q2 + q3)**2 "
        "+ 0.3*(sqrt(((q1 - q2)**2 + (q1 - q3)**2 + (q2 - q3)**2)/3) - 3)**2")


def test_af_is_ring_well_binds_a_higher_shell_below_a_lower_one():
    """af-is, n = 3, a ring well at shear radius 3: there the rotor terms (c - c') |K f|^2 of
    the sectors (j, 0) fade like e^(-2x), while (1, 1) pays its Casimir hbar^2 j'(j'+1)/(2 I~)
    everywhere; so shell 2's (2, 0) lies below shell 1's (1, 1), and below the third (0, 0)
    level. A search stopping after the first shell lying above the K-th candidate (the former
    heuristic) would stop after shell 1 with K = 3 and return three (0, 0) levels; the search
    finds the (2, 0) level (5 states) in second place and, the af-is bound not deciding here
    (the ring's rotor levels really are low), reports the list as conditional."""
    s = sp.solve("af-is", 3, compile_potential(RING, 3), 1.0, I=1.0, A=0.2, B=0.1, levels=3,
                 settings=Settings(basis_size=4, check_shrink=2, scale=1.5, scale_sigma=1.0,
                                   centre=0.0, max_spin=2, tolerance=1e-2))
    lowest: dict = {}
    for key, block in s.blocks.items():
        lowest.setdefault(key[1:3], []).append(float(block.energies[0]))
    scalar = sorted(lowest[(0, 0)])
    assert min(lowest[(1, 1)]) > scalar[2]  # the heuristic would stop after shell 1
    assert min(lowest[(2, 0)]) < scalar[1] < min(lowest[(1, 1)])  # not monotone in the shell
    states = s.states()
    assert [(lv.sectors[0].spin, lv.sectors[0].vorticity) for lv in states[:2]] == [(0, 0),
                                                                                    (2, 0)]
    assert states[1].multiplicity == 5
    assert not s.certified and s.certificate.startswith("conditional")


def test_dalembert_search_stops_on_certified_bounds_not_on_monotonicity():
    """d'Alembert, n = 3, a well at zero shear Q1 = Q2: after shell 2 the lowest level found
    per shell lies above the K-th candidate (the sixth state is in (1, 1)), so a search
    assuming the lowest level per shell to rise (not proven for n = 3) would stop there; the
    certified search goes on to shell 3, whose sectors (1, 3) and (3, 3) have bounds below
    that candidate, and stops only when every sector it did not solve has a certified bound
    above it (recomputed here for every sector up to the n = 3 limit); each bound lies below
    the sector's computed lowest level (docs/theory/two-polar.md, "Lower bounds of an n = 3
    sector")."""
    K = 6
    V = compile_potential("0.5*trG - 2*exp(-(Q1 - Q2)**2/2)", 3)
    s = sp.solve("dalembert", 3, V, 1.0, inertia=1.0, levels=K,
                 settings=Settings(basis_size=6, radial_size=8, scale=1.0, check_shrink=2))
    assert s.certified
    E_K = sorted(lv.energy for lv in s.states() for _ in range(lv.multiplicity))[K - 1]
    low: dict = {}
    for key, block in s.blocks.items():
        for sector in (key[1:3], key[2:0:-1]):  # phi -> phi^T: one block serves (j, j'), (j', j)
            low[sector] = min(low.get(sector, np.inf), float(block.energies[0]))
    first_shell_above = min(L for L in range(4) if min(
        e for k, e in low.items() if max(k) == L) > E_K)
    assert first_shell_above == 2 and s.settings["shells_searched"] == 3
    bounds = lebesgue3_shell_bounds(V, 1.0, 1.0, n3.MAX_SHELL, 1.0)
    assert bounds.of((1, 3)) < E_K and bounds.tail > E_K
    for key, bound in bounds.sector.items():
        assert key in low or bound > E_K, key
        if key in low:
            assert bound <= low[key]


def _spin_matrices(j: int) -> list[np.ndarray]:
    """J_x, J_y, J_z on V_j in the |j, m> basis (Hermitian, complex)."""
    m = np.arange(j, -j - 1, -1.0)
    raising = np.diag(np.sqrt(j * (j + 1) - m[1:] * (m[1:] + 1)), 1)
    return [(raising + raising.T) / 2, (raising - raising.T) / 2j, np.diag(m)]


@pytest.mark.parametrize("sector", [(2, 0), (2, 1), (3, 1), (1, 2)])
def test_haar3_centrifugal_matrix_is_the_rotor_operator_on_the_fixed_subspace(sector):
    """The matrix bound of an affine sector at a point (its coefficients c = c_0/sinh^2(x/2),
    -c' = -c_0/cosh^2(x/2) of each pair) is the lowest eigenvalue of
    sum_g [c (J_g (x) 1 + 1 (x) J_g)^2 - c' (J_g (x) 1 - 1 (x) J_g)^2] + e j'(j'+1) on the
    vectors of V_j (x) V_j' fixed by the rotations by pi about the three axes, built here from
    the complex |j, m> spin matrices and a projector (not from the real covariant bases of the
    bound); and the pairwise closed forms never exceed it."""
    j, jp = sector
    c0, e = 1 / (16 * 1.2), 0.5 / 0.96
    Jl, Jr = _spin_matrices(j), _spin_matrices(jp)
    eye_l, eye_r = np.eye(2 * j + 1), np.eye(2 * jp + 1)
    P = sum(np.kron(linalg.expm(1j * np.pi * Jl[a]), linalg.expm(1j * np.pi * Jr[a]))
            for a in range(3)) + np.eye((2 * j + 1) * (2 * jp + 1))
    w, vecs = linalg.eigh((P + P.conj().T) / 8)
    fixed = vecs[:, w > 0.5]
    assert fixed.shape[1] == cov.fixed_dimension(j, jp)
    rng = np.random.default_rng(5)
    x12, x23 = rng.uniform(0.05, 3.0, (2, 6))
    x13 = x12 + x23
    axis = {0: 2, 1: 1, 2: 0}  # pairs (0,1), (0,2), (1,2): rotations about the axes z, y, x
    c_plus = np.array([c0 / np.sinh(x / 2) ** 2 for x in (x12, x13, x23)])
    c_minus = np.array([-c0 / np.cosh(x / 2) ** 2 for x in (x12, x13, x23)])
    got = haar3_centrifugal_matrix_min(j, jp, c_plus, c_minus, e * jp * (jp + 1))
    closed = haar3_centrifugal_min(j, jp, [x12, x23, x13], c0, e)
    for p in range(6):
        U = e * jp * (jp + 1) * np.eye(len(P), dtype=complex)
        for g in range(3):
            left, right = np.kron(Jl[axis[g]], eye_r), np.kron(eye_l, Jr[axis[g]])
            U += c_plus[g, p] * (left + right) @ (left + right)
            U += c_minus[g, p] * (left - right) @ (left - right)
        exact = linalg.eigvalsh(fixed.conj().T @ U @ fixed)[0]
        assert abs(got[p] - exact) < 1e-9 * (1 + abs(exact))
        assert closed[p] <= exact + 1e-9

