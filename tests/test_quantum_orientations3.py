"""Orientation densities of single n = 3 states (quantum/orientations3.py) against the closed
form of the R^9 oscillator's first excited multiplet (spin = vorticity = 1, psi ~ phi^i_a x
Gaussian), the Haar density of a multiplet summed over its states, and the command line."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import special

from affinebody.quantum import green3
from affinebody.quantum import spectra as sp
from affinebody.quantum.cli import density
from affinebody.quantum.intervals import ExpressionPotential
from affinebody.quantum.orientations3 import (
    mixture_orientations,
    multiplet_orientations,
    multiplet_state,
    orientation_densities3,
    side_terms,
    state_mixture,
    terms_density,
)
from affinebody.quantum.tensor_operators3 import euler_quadrature, reduced_matrix, wigner
from affinebody.quantum.transitions import Operator, level_states

HBAR, INERTIA, K = 0.7, 1.3, 0.8


@pytest.fixture(scope="module")
def oscillator3():
    """R^9 oscillator, every sector up to max(j, j') = 2: levels N = 0, 1, 2 with 1, 9 and 45
    states (N = 1: (1, 1); N = 2: (0, 0) + (1, 1) + (2, 0) + (0, 2) + (2, 2))."""
    s = sp.solve("dalembert", 3, ExpressionPotential(f"0.5*{K}*trG", 3), HBAR, inertia=INERTIA,
                 levels=55, settings=sp.Settings(basis_size=4, check_shrink=2, max_spin=2))
    assert [lv.multiplicity for lv in s.levels] == [1, 9, 45]
    return s


def chamber_moments(f) -> np.ndarray:
    """int f(Q) rho(Q) dQ / int rho, rho = prod_{a<b} (Q_a^2 - Q_b^2) e^{-|Q|^2/2} on Q1 > Q2
    > |Q3| (the singular values of a 3 x 3 matrix of independent standard normals), by a
    Gauss-Legendre product rule in Cartesian coordinates (exact in Q2, Q3; Q1 cut at 12)."""
    x, w = np.polynomial.legendre.leggauss(80)
    u, wu = np.polynomial.legendre.leggauss(12)
    q1, w1 = 6 * (x + 1), 6 * w
    q2 = q1[:, None] * (u[None] + 1) / 2
    w2 = w1[:, None] * wu[None] * q1[:, None] / 2
    q3 = q2[..., None] * u
    w3 = w2[..., None] * wu * q2[..., None]
    Q = np.stack(np.broadcast_arrays(q1[:, None, None], q2[..., None], q3), -1)
    rho = w3 * np.exp(-np.sum(Q * Q, -1) / 2) * np.prod(
        [Q[..., a] ** 2 - Q[..., b] ** 2 for a, b in ((0, 1), (0, 2), (1, 2))], 0)
    values = f(Q)
    return np.tensordot(values, rho, axes=rho.ndim) / np.sum(rho)


def chamber_weights() -> np.ndarray:
    """w_k = <Q_k^2> / <|Q|^2> under the ground state's singular-value density."""
    moments = chamber_moments(lambda Q: np.moveaxis(Q * Q, -1, 0))
    return moments / moments.sum()


def test_first_excited_multiplet_closed_form(oscillator3):
    """psi ~ <c, phi> e^{-|phi|^2/4s^2} with c = |1 m> (x) |1 m'>: phi = L diag(Q) R^T gives
    p_L(L) = 3 sum_k w_k |<1 m| L e_k>|^2 (the |D^1|^2 pattern, w_k = <Q_k^2>/<|Q|^2>), so the
    axis k of L (and of R, with m') has the cosine density (3/2)[w_k g + (1 - w_k)(1 - g)/2]
    with g = t^2 (m = 0), (1 - t^2)/2 (m = +-1); the rotation angle of L has (1 - cos w)/pi x
    3 [w_3 a + (w_1 + w_2) b] (m = 0) and 3 [w_3 b + (w_1 + w_2)(a + b)/2] (m = +-1), with
    a = c^2 + 2c(1 - c)/3 + (1 - c)^2/5, b = (1 - c)^2/15 + (1 - c^2)/3 the axis averages of
    L_33^2 and L_31^2 (Rodrigues). Every density integrates to 1; the sum over the 9 states
    is Haar (angle (1 - cos w)/pi, axes uniform 1/2)."""
    wk = chamber_weights()
    assert np.all(np.diff(wk) < -0.05)  # far from uniform: the axes are ordered by Q_k
    total = {}
    multiplet = multiplet_orientations(oscillator3, 4, points=41)
    assert [d["state"] for d in multiplet] == list(range(1, 10))
    for d in multiplet:
        state = d["state"]
        o = d["orientation"]
        assert d["sector"]["spin"] == 1 and d["sector"]["vorticity"] == 1
        np.testing.assert_allclose(d["weights_L"], wk, atol=1e-9)
        np.testing.assert_allclose(d["weights_R"], wk, atol=1e-9)
        t, c = o["t"], np.cos(o["angle"])
        a = c * c + 2 * c * (1 - c) / 3 + (1 - c) ** 2 / 5
        b = (1 - c) ** 2 / 15 + (1 - c * c) / 3
        for side, m in (("L", d["m"]), ("R", d["m_prime"])):
            g = t * t if m == 0 else (1 - t * t) / 2
            for k in range(3):
                exact = 1.5 * (wk[k] * g + (1 - wk[k]) * (1 - g) / 2)
                assert np.abs(o[f"{side}_axis{k + 1}"] - exact).max() < 1e-8, (state, side, k)
            mix = wk[2] * a + (wk[0] + wk[1]) * b if m == 0 else \
                wk[2] * b + (wk[0] + wk[1]) * (a + b) / 2
            exact = (1 - c) / np.pi * 3 * mix
            assert np.abs(o[f"{side}_angle"] - exact).max() < 1e-8, (state, side)
        for name, value in d["integrals"].items():
            assert abs(value - 1) < 1e-12, name
        for name, value in o.items():
            total[name] = total.get(name, 0) + value / 9
    for side in ("L", "R"):
        haar = (1 - np.cos(total["angle"])) / np.pi
        assert np.abs(total[f"{side}_angle"] - haar).max() < 1e-12
        for k in (1, 2, 3):
            assert np.abs(total[f"{side}_axis{k}"] - 0.5).max() < 1e-12


def test_wigner_is_a_representation():
    """D^j(L1 L2) = D^j(L1) D^j(L2) for j = 2, 3 (and D^1 = L), rotations by nearly pi
    included (where the axis is read off L + L^T)."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(8, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    a, b, c, d = q.T
    L = np.stack([[a*a + b*b - c*c - d*d, 2*(b*c - a*d), 2*(b*d + a*c)],
                  [2*(b*c + a*d), a*a - b*b + c*c - d*d, 2*(c*d - a*b)],
                  [2*(b*d - a*c), 2*(c*d + a*b), a*a - b*b - c*c + d*d]]).transpose(2, 0, 1)
    flip = np.diag([-1.0, -1.0, 1.0])  # a rotation by pi, then by pi - 1e-9
    eps = 1e-9
    near = flip @ np.array([[1, 0, 0], [0, np.cos(eps), -np.sin(eps)],
                            [0, np.sin(eps), np.cos(eps)]])
    L = np.concatenate([L, flip[None], near[None]])
    assert np.abs(wigner(1, L) - L).max() < 1e-14
    for j in (2, 3):
        assert np.abs(wigner(j, L[:5] @ L[5:]) - wigner(j, L[:5]) @ wigner(j, L[5:])).max() \
            < 1e-13


CONFIG3 = f"""
[system]
n = 3
[quantum]
hbar = {HBAR}
kinetic = "dalembert"
inertia = {INERTIA}
potential = "0.5*{K}*trG"
sectors = "scalar+spin1"
basis_size = 4
density_points = 11
"""


def test_density_command_n3_state(tmp_path):
    """affinebody density --state k --orientation for n = 3: state 3 is |1 1> (x) |1 -1> of
    N = 1; orientation.json carries its labels, the densities with integral 1 and Phi's
    weights (the ordered singular values' share of |Q|^2); exit 0."""
    path = tmp_path / "osc3.toml"
    path.write_text(CONFIG3)
    out = tmp_path / "o"
    result = CliRunner().invoke(density, [str(path), "--state", "3", "--orientation", "-o",
                                          str(out), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "orientation.json").read_text())
    assert (doc["kind"], doc["m"], doc["m_prime"]) == ("state", 1, -1)
    assert doc["sector"]["spin"] == doc["sector"]["vorticity"] == 1
    np.testing.assert_allclose(doc["weights_L"], chamber_weights(), atol=1e-9)
    assert set(doc["densities"]) == {f"{s}_{k}" for s in "LR"
                                     for k in ("angle", "axis1", "axis2", "axis3")}
    assert all(abs(v - 1) < 1e-12 for v in doc["integrals"].values())
    assert (out / "orientation.png").exists() and (out / "orientation.npz").exists()


def frames(k: int, t: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Rotations [t, twist, 3, 3] whose column k is n = (sqrt(1 - t^2), 0, t) and whose other
    columns are u = cos(twist) e1 + sin(twist) e2 (e1, e2 completing n) and n x u, cyclically."""
    st = np.sqrt(1 - t * t)
    n = np.stack([st, 0 * t, t], -1)[:, None]
    e1 = np.stack([t, 0 * t, -st], -1)[:, None]
    e2 = np.broadcast_to([0.0, 1.0, 0.0], e1.shape)
    u = np.cos(twist)[None, :, None] * e1 + np.sin(twist)[None, :, None] * e2
    L = np.zeros(u.shape[:2] + (3, 3))
    L[..., k], L[..., (k + 1) % 3], L[..., (k + 2) % 3] = n, u, np.cross(n, u)
    return L


def test_quadrupole_multiplets_against_their_wave_functions(oscillator3):
    """N = 2, sector (2, 0): psi ~ <T_m, phi phi^T> e^{-|phi|^2/4s^2} with T_m the traceless
    tensor of the harmonic Y_2m (T_0 = diag(-1, -1, 2), T_{+-1} ~ e_3 (e_1 +- i e_2)^T +
    transpose, T_{+-2} ~ (e_1 +- i e_2)(e_1 +- i e_2)^T); with phi phi^T = L diag(Q^2) L^T,
    p(L) ~ sum_kl <Q_k^2 Q_l^2> X_k conj(X_l), X_k = (L^T conj(T_m) L)_kk, evaluated here on
    explicit rotations (no Wigner matrices), normalised by its Haar mean and integrated over
    the twist about each axis and over the rotation axes. (0, 2): the same with R (psi ~
    <T_m, phi^T phi>), and the other side is Haar."""
    M = chamber_moments(lambda Q: np.einsum("...k,...l->kl...", Q * Q, Q * Q))
    e = np.eye(3)
    plus = e[0] + 1j * e[1]
    tensors = {0: np.diag([-1.0, -1.0, 2.0]), 1: np.outer(e[2], plus) + np.outer(plus, e[2]),
               2: np.outer(plus, plus)}

    def density(m, L):  # unnormalised p at rotations [..., 3, 3]
        T = tensors[abs(m)] if m >= 0 else tensors[-m].conj()
        X = np.einsum("...ik,ij,...jk->...k", L, T.conj(), L)
        return np.einsum("kl,...k,...l->...", M, X, X.conj()).real

    # Haar mean by Euler angles z-y-z: Gauss-Legendre in cos(beta), trapezoid in the others
    c, wc = np.polynomial.legendre.leggauss(8)
    ang = 2 * np.pi * np.arange(12) / 12
    haar = frames(2, c, ang)  # column 3 at cos(beta) = c, the first Euler angle is 0 ...
    rz = np.stack([[np.cos(ang), -np.sin(ang), 0 * ang], [np.sin(ang), np.cos(ang), 0 * ang],
                   [0 * ang, 0 * ang, 1 + 0 * ang]]).transpose(2, 0, 1)
    haar = np.einsum("aij,tbjk->tabik", rz, haar)  # ... and here the azimuth
    twist = 2 * np.pi * np.arange(12) / 12
    level = oscillator3.levels[2]
    first = 10 + sum(s.dimension for s in level.sectors[:[(s.spin, s.vorticity) for s in
                                                          level.sectors].index((2, 0))])
    for sector, side in (((2, 0), "L"), ((0, 2), "R")):
        start = first if sector == (2, 0) else None
        if start is None:
            names = [(s.spin, s.vorticity) for s in level.sectors]
            start = 10 + sum(s.dimension for s in level.sectors[:names.index((0, 2))])
        multiplet = multiplet_orientations(oscillator3, start, points=21)
        assert len(multiplet) == 5
        for d in multiplet:
            m = d["m"] if side == "L" else d["m_prime"]
            o = d["orientation"]
            assert (d["sector"]["spin"], d["sector"]["vorticity"]) == sector
            norm = np.einsum("t,tab->", wc, density(m, haar)) / (2 * 12 * 12)
            for k in range(3):
                exact = 0.5 * density(m, frames(k, o["t"], twist)).mean(1) / norm
                assert np.abs(o[f"{side}_axis{k + 1}"] - exact).max() < 1e-7, (m, k)
            # rotation angle: mean over the axes n (cos theta Gauss, azimuth trapezoid)
            st = np.sqrt(1 - c * c)
            n = np.stack([st[:, None] * np.cos(ang), st[:, None] * np.sin(ang),
                          c[:, None] + 0 * ang], -1)
            cw, sw = np.cos(o["angle"]), np.sin(o["angle"])
            nx = np.swapaxes(np.cross(n[..., None, :], np.eye(3)), -1, -2)
            rot = (cw[:, None, None, None, None] * np.eye(3)
                   + sw[:, None, None, None, None] * nx
                   + (1 - cw)[:, None, None, None, None] * np.einsum("...i,...j->...ij", n, n))
            mean = np.einsum("t,wta->w", wc, density(m, rot)) / (2 * 12)
            exact = (1 - cw) / np.pi * mean / norm
            assert np.abs(o[f"{side}_angle"] - exact).max() < 1e-7, m
            other = "R" if side == "L" else "L"
            haar_angle = (1 - cw) / np.pi
            assert np.abs(o[f"{other}_angle"] - haar_angle).max() < 1e-12
            assert abs(d["integrals"][f"{side}_angle"] - 1) < 1e-12


def test_superposition_against_direct_quadrature_of_the_wave_function(oscillator3):
    """A superposition of states of (1, 1) (N = 1 and N = 2), (2, 0) and (0, 2) with complex
    amplitudes: p_L from the Schur-reduced cross terms (side_terms) equals the direct
    quadrature of |Psi|^2 = |sum_k c_k sqrt(d_k) u_k^H D(L) F_k(Q) D(R)^T conj(v_k)|^2 over R
    (an Euler-angle rule exact for its rank) and Q (both on the same 3000 random nodes of the
    chamber rule: the identity is in the angles), at random L; every marginal integrates to 1;
    a single state through the same route reproduces the exact |D^j|^2 formulas of
    multiplet_orientations."""
    level = oscillator3.levels[2]
    names = [(s.spin, s.vorticity) for s in level.sectors]
    start = {key: 10 + sum(s.dimension for s in level.sectors[:names.index(key)])
             for key in ((2, 0), (0, 2), (1, 1))}
    sup = {1: 1.0, 4: 0.5j, start[(1, 1)] + 3: 0.4 - 0.2j, start[(2, 0)] + 1: 0.3,
           start[(0, 2)] + 2: 0.3j}
    data = mixture_orientations(oscillator3, superposition=sup, points=11)
    assert all(abs(v - 1) < 1e-10 for v in data["integrals"].values())
    picked = [multiplet_state(oscillator3, k) for k in sup]
    rng = np.random.default_rng(3)
    nodes = rng.choice(len(picked[0][1]), 3000, replace=False)
    states = [replace(p, F=p.F[nodes]) for p, _ in picked]
    w = picked[0][1][nodes]
    c = np.array(list(sup.values()), complex)
    c /= np.linalg.norm(c)
    L = np.linalg.qr(rng.normal(size=(4, 3, 3)))[0]
    L *= np.linalg.det(L)[:, None, None]
    R, wR = euler_quadrature(4)
    formula = terms_density(side_terms(c, states, w, "L"), L)
    direct = []
    for one in L:
        psi = 0.0
        for ck, st in zip(c, states, strict=True):
            X = np.einsum("a,ab,pbd->pd", st.u.conj(), wigner(st.sector.spin, one), st.F)
            # (D(R)^T conj(v))_d = sum_e D_ed conj(v_e)
            Y = np.einsum("ned,e->nd", wigner(st.sector.vorticity, R), st.v.conj())
            psi = psi + ck * math.sqrt(st.sector.dimension) * (X @ Y.T)
        direct.append(float(w @ (np.abs(psi) ** 2 @ wR)))
    np.testing.assert_allclose(formula, direct, rtol=1e-10)
    assert np.ptp(direct) > 0.1 * np.mean(direct)  # L far from Haar
    single = mixture_orientations(oscillator3, superposition={start[(2, 0)] + 1: 1.0},
                                  points=11)
    (exact,) = multiplet_orientations(oscillator3, start[(2, 0)] + 1, points=11, every=False)
    for key, values in exact["orientation"].items():
        np.testing.assert_allclose(single["orientation"][key], values, atol=1e-12)


def test_thermal_mixture_is_haar_at_every_temperature(oscillator3):
    """The thermal mixture, a function of H (which commutes with SO(3) x SO(3)), summed over
    the 55 states computed state by state (whose own densities are far from Haar): the rotation
    angle has (1 - cos omega)/pi and each axis cosine 1/2 at T = 0.05 (the ground state's
    density, a singlet) and at T = 3 (where the mixture is truncated, with a warning)."""
    for T in (0.05, 3.0):
        data = mixture_orientations(oscillator3, temperature=T, points=11)
        o = data["orientation"]
        for side in "LR":
            np.testing.assert_allclose(o[f"{side}_angle"], (1 - np.cos(o["angle"])) / np.pi,
                                       atol=1e-12)
            for k in (1, 2, 3):
                np.testing.assert_allclose(o[f"{side}_axis{k}"], 0.5, atol=1e-12)
        assert bool(data["warnings"]) == (T > 1)
    ground = orientation_densities3(oscillator3, 0, points=11)["orientation"]
    np.testing.assert_allclose(ground["L_angle"], o["L_angle"], atol=1e-12)
    one = orientation_densities3(oscillator3, 1, points=11)["orientation"]
    assert np.max(np.abs(one["L_axis3"] - 0.5)) > 0.1


def test_density_command_n3_superposition_and_temperature(tmp_path):
    """affinebody density --superpose / --temperature for n = 3: orientation.json with the kind,
    integrals 1, a thermal mixture with Haar axes; exit 0; a bad temperature: one line, exit 1."""
    path = tmp_path / "osc3.toml"
    path.write_text(CONFIG3)
    for args, kind in ((["--superpose", "1:1,4:0.5j"], "superposition"),
                       (["--temperature", "0.03"], "thermal")):
        out = tmp_path / kind
        result = CliRunner().invoke(density, [str(path), *args, "-o", str(out)])
        assert result.exit_code == 0, result.output
        doc = json.loads((out / "orientation.json").read_text())
        assert doc["kind"] == kind
        assert all(abs(v - 1) < 1e-10 for v in doc["integrals"].values())
    np.testing.assert_allclose(doc["densities"]["R_axis1"]["density"], 0.5, atol=1e-12)
    bad = CliRunner().invoke(density, [str(path), "--temperature", "-1", "-o", str(out)])
    assert bad.exit_code == 1 and len(bad.output.strip().splitlines()) == 1
    assert "--temperature must be a finite kT > 0" in bad.output


def test_green_diagonal_densities_against_closed_form_and_transition_elements(oscillator3):
    """Densities of G_aa (quantum.green3): the ground state's G11 = sum_i phi_i1^2 is U times a
    chi-square with 3 degrees of freedom; for a state |2 1> of the multiplet (0, 2) of N = 2
    (anisotropic in the body) the first two moments of the density of G33 equal <G33> and
    <G33^2> (to 1e-4, the rule in y) computed as matrix elements by the transitions' expansion
    in Wigner D functions (an independent route)."""
    U = HBAR / (2 * INERTIA * math.sqrt(K / INERTIA))
    ground, _ = multiplet_state(oscillator3, 0)
    pair_list = green3.pairs([(1.0, np.ones(1), [ground])])
    bounds = green3.support("lebesgue3", pair_list)
    y = np.array([0.2, 0.5, 1.0, 2.0])
    exact = np.sqrt(y) * np.exp(-y / (2 * U)) / (math.gamma(1.5) * (2 * U) ** 1.5)
    p = green3.diagonal_density(pair_list, "lebesgue3", 0, y, green3.RULES[1], bounds)
    np.testing.assert_allclose(p, exact, rtol=1e-3)  # 5e-4 at y = 0.2, 2e-8 at y = 2
    level = oscillator3.levels[2]
    names = [(s.spin, s.vorticity) for s in level.sectors]
    index = 10 + sum(s.dimension for s in level.sectors[:names.index((0, 2))]) + 1
    state, w = multiplet_state(oscillator3, index)
    pair_list = green3.pairs([(1.0, np.ones(1), [state])])
    bounds = green3.support("lebesgue3", pair_list)
    u, wu = np.polynomial.legendre.leggauss(12)
    u, wu = (u + 1) / 2, wu / 2
    y, wy = bounds[3] * u * u, bounds[3] * 2 * u * wu  # y = top u^2: the sqrt(y) edge is smooth
    Q = level_states(oscillator3).Q
    c = np.kron(state.u, state.v)
    p = green3.diagonal_density(pair_list, "lebesgue3", 2, y, (8, 32, 16), bounds)
    for power in (1, 2):
        op = Operator(f"G33**{power}", 3)
        moments = np.einsum("p,pt,pbd,pBD->tbdBD", w, op.radial(Q), state.F, state.F)
        M = reduced_matrix(op.expansion, moments, (0, 2), (0, 2))
        element = (state.sector.dimension * c @ M @ c.conj()).real
        assert abs(np.sum(wy * y**power * p) - element) < 5e-4 * element


def test_green_offdiagonal_densities_against_closed_form_and_transition_elements(
        oscillator3):
    """Densities of G_ab, a != b (quantum.green3): the ground state's G12 = sum_i phi_i1 phi_i2
    is a sum of three products of independent normals of variance U, whose density is
    |y| K_1(|y|/U) / (pi U^2) (the sum of n products of standard normal pairs has
    |x|^{(n-1)/2} K_{(n-1)/2}(|x|) / (sqrt(pi) Gamma(n/2) 2^{(n-1)/2}), characteristic
    function (1 + k^2)^{-n/2}; 1/(pi U) at y = 0), to 2e-4 relative over y in [-1, 2] with y = 0
    included, and G13 and G23 have the same law; for a superposition with complex amplitudes of
    the three states of the multiplet (1, 1) of N = 1 that share their magnetic number in L
    (anisotropic, <G12> = 0.137: a single state |j' m'> has <G12> = 0) the first two moments
    of the G12 density equal <G12> and <G12^2> computed as matrix elements by the transitions'
    expansion in Wigner D functions (an independent route)."""
    U = HBAR / (2 * INERTIA * math.sqrt(K / INERTIA))
    ground, _ = multiplet_state(oscillator3, 0)
    pair_list = green3.pairs([(1.0, np.ones(1), [ground])])
    bounds = green3.support("lebesgue3", pair_list)
    y = np.array([-1.0, 0.0, 0.2, 0.5, 2.0])
    with np.errstate(invalid="ignore"):
        exact = np.where(y == 0, 1 / (math.pi * U), np.abs(y) * special.k1(np.abs(y) / U)
                         / (math.pi * U**2))
    p = green3.offdiagonal_density(pair_list, "lebesgue3", (0, 1), y, green3.OFF_RULES[1],
                                   bounds)
    np.testing.assert_allclose(p, exact, rtol=2e-4)  # 3e-5 measured
    for axes in ((0, 2), (1, 2)):
        p = green3.offdiagonal_density(pair_list, "lebesgue3", axes, y[[0, 3]],
                                       green3.OFF_RULES[0], bounds)
        np.testing.assert_allclose(p, exact[[0, 3]], rtol=1e-3)
    picked = [multiplet_state(oscillator3, k) for k in (1, 2, 3)]  # (1, 1), one m, three m'
    states, w = [state for state, _ in picked], picked[0][1]
    amplitudes = np.array([1.0, 0.5 + 0.4j, -0.3j]) / math.sqrt(1.5)
    pair_list = green3.pairs([(1.0, amplitudes, states)])
    bounds = green3.support("lebesgue3", pair_list)
    u, wu = np.polynomial.legendre.leggauss(8)
    u, wu = (u + 1) / 2, wu / 2
    y = np.concatenate([-6 * u[::-1] ** 2, 6 * u**2])
    wy = np.concatenate([12 * (u * wu)[::-1], 12 * u * wu])
    p = green3.offdiagonal_density(pair_list, "lebesgue3", (0, 1), y, (6, 4, 32, 10), bounds)
    # psi = sum_k a_k sqrt(d) u_k^H D(L) F D(R)^T conj(v_k): coefficients conj(u_k (x) v_k)
    c = sum(a * np.kron(s.u, s.v).conj() for a, s in zip(amplitudes, states, strict=True))
    Q = level_states(oscillator3).Q
    assert abs(np.sum(wy * p) - 1) < 2e-3  # the tails beyond |y| = 6 left out: 1.2e-3 measured
    for power, tolerance in ((1, 2e-3), (2, 3e-3)):  # 9e-4, 1e-3 measured
        op = Operator(f"G12**{power}", 3)
        moments = np.einsum("p,pt,pbd,pBD->tbdBD", w, op.radial(Q), states[0].F, states[0].F)
        M = reduced_matrix(op.expansion, moments, (1, 1), (1, 1))
        element = (states[0].sector.dimension * c.conj() @ M @ c).real
        assert abs(element) > 0.1
        assert abs(np.sum(wy * y**power * p) - element) < tolerance * abs(element)


def test_green_integrals_carry_an_error_that_bounds_them(oscillator3, monkeypatch):
    """The integral of each n = 3 G density (green3.g_densities3) comes with integral_error,
    which bounds |integral - 1| for the ground state (on 11 and 21 points) and a state of the
    multiplet (1, 1) (on 11) and shrinks with the points for an off-diagonal component (the
    trapezoid in xi over its points; a diagonal one has its own INTEGRAL_NODES). Smaller rules
    than the defaults, for speed: their larger difference enters the error (the old trapezoid
    over the points had no error, and for a diagonal component it left out [0, y1]: 0.32 for
    the ground state's G11 on 11 points)."""
    monkeypatch.setattr(green3, "RULES", ((6, 24, 12), (8, 32, 16)))
    monkeypatch.setattr(green3, "OFF_RULES", ((6, 4, 32, 10), (8, 6, 48, 12)))
    errors = []
    for state, points, components in ((0, 11, ("G22", "G13")), (0, 21, ("G13",)),
                                      (3, 11, ("G22", "G13"))):
        mixture, *_ = state_mixture(oscillator3, state)
        out = green3.g_densities3(oscillator3, mixture, points, components=components)
        for m in out.values():
            assert abs(m.integral - 1) <= m.integral_error, (state, points, m.integral)
            assert m.as_dict()["integral_error"] == m.integral_error
        errors.append(out["G13"].integral_error)
    assert errors[1] < min(errors[0] / 2, 0.05), errors
    assert out["G22"].integral_error < 1e-2


def test_density_command_n3_green_components(tmp_path):
    """--g-components for n = 3: orientation.json holds the densities of G33 and G12 of the
    thermal mixture at low T (the ground state's: U x chi-square(3) and the variance-gamma law
    |y| K_1(|y|/U)/(pi U^2), the latter symmetric under y -> -y as the mixture is isotropic);
    an unknown component or too many points: one line, exit 1."""
    path = tmp_path / "osc3.toml"
    path.write_text(CONFIG3)
    out = tmp_path / "g"
    result = CliRunner().invoke(density, [str(path), "--temperature", "0.03", "--g-components",
                                          "G33,G12", "-o", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "orientation.json").read_text())
    g = doc["densities"]["G33"]
    U = HBAR / (2 * INERTIA * math.sqrt(K / INERTIA))
    y = np.array(g["x"])
    exact = np.sqrt(y) * np.exp(-y / (2 * U)) / (math.gamma(1.5) * (2 * U) ** 1.5)
    np.testing.assert_allclose(g["density"], exact, atol=1e-4 * exact.max())
    # its integral by its own nodes (the 11 points start past the peak: 0.32 over them)
    assert abs(g["integral"] - 1) <= g["integral_error"] < 1e-2
    g = doc["densities"]["G12"]
    y, p = np.array(g["x"]), np.array(g["density"])
    assert y[5] == 0 and g["converged"] and not doc["warnings"]
    assert abs(g["integral"] - 1) < 0.05  # 11 points across the cusp-like peak: 1.03
    assert abs(g["integral"] - 1) <= g["integral_error"] < 0.3
    np.testing.assert_allclose(p, p[::-1], rtol=1e-12)
    with np.errstate(invalid="ignore"):
        exact = np.where(y == 0, 1 / (math.pi * U), np.abs(y) * special.k1(np.abs(y) / U)
                         / (math.pi * U**2))
    np.testing.assert_allclose(p, exact, atol=1e-4 * exact.max())
    for args, needle in ((["--g-components", "G21"], "not computed"),
                         (["--g-components", "G11,G22,G33", "--superpose", "1:1"], None)):
        if needle is None:
            path.write_text(CONFIG3.replace("density_points = 11", "density_points = 60"))
            needle = "is more than"
        extra = [] if "--superpose" in args else ["--temperature", "0.03"]
        bad = CliRunner().invoke(density, [str(path), *args, *extra, "-o", str(out)])
        assert bad.exit_code == 1 and needle in bad.output, bad.output
        assert len(bad.output.strip().splitlines()) == 1
