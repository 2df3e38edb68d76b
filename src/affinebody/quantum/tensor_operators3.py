"""n = 3 configuration operators as sums of SO(3) x SO(3) tensor operators: the expansion of an
expression in the invariants and the components of phi, G, C in Wigner D functions of the two
rotations of phi = L diag(Q) R^T (docs/quantum-transitions.md, "n = 3: any polynomial
expression"), and the numerical projection of any other expression on the ranks a pair of
multiplets can couple (:func:`project`; "Operators that are not polynomials").

Structure. An operator O is read as a polynomial in the components x (phi^i_a, G_ab, C_ij) with
coefficients that are any expression in the invariants v (q, Q, trG, K, det),

    O = sum_m s_m(v) x^m,   total degree <= MAX_DEGREE,

found numerically: the degree along random rays x -> t x, then the monomials by least squares
at random points, checked at fresh points (an expression that is not of that form, e.g.
exp(G12) or |G11|, whose SO(3) ranks do not terminate, is refused here and projected
numerically instead, :func:`project`). At phi = L diag(Q) R^T

    phi^i_a = sum_k L_ik Q_k R_ak,  G_ab = sum_k R_ak R_bk Q_k^2,  C_ij = sum_k L_ik L_jk Q_k^2,

so a monomial is sum_K Q^e(K) A_K(L) B_K(R) over the inner indices K, with A_K, B_K products of
entries of L and R of degrees g_L = d_phi + 2 d_C, g_R = d_phi + 2 d_G (its ranks on each side
are at most those). Peter-Weyl (Haar measure of mass 1, the real orthogonal representations
D^l of covariants3's harmonic bases, :func:`wigner`) gives

    O(L diag Q R^T) = sum_{l, l'} sum_{pqrs} c^{l l'}_{pq, rs}(Q) D^l_pq(L) D^l'_rs(R),
    c = (2l + 1)(2l' + 1) sum_{m, e} s_m Q^e sum_{K: e(K) = e} a^l_K (x) b^l'_K,
    a^l_K[p, q] = int A_K(L) D^l_pq(L) dL,

the integrals done exactly by the Euler-angle rule of :func:`euler_quadrature`. The
coefficient functions are collected in a few radial functions r_t(Q) (a basis of the s_m
times the powers Q^e) with constant angular tensors T_t^{l l'}[p, q, r, s]. The angular
integrals of a product of three D functions are then exact,

    int D^j_ab(L) D^j'_cd(L) D^l_pq(L) dL = w[a, c, p] w[b, d, q],

w the unit SO(3)-invariant vector of V_j (x) V_j' (x) V_l (:func:`coupling_tensor`; unique
up to sign when the triangle rule holds, none otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property
from itertools import combinations_with_replacement, product

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.intervals import invariant_values

#: largest total degree in the components of phi, G, C (ranks up to 8 on a side: G^4)
MAX_DEGREE = 4
#: largest number of monomials of that degree in the components used (the least-squares fit)
MAX_MONOMIALS = 1200
#: relative residual below which a polynomial fit is exact
FIT_TOLERANCE = 1e-9
#: the second, far ray of the degree test: component values up to this
RAY_REACH = 40.0


def component_names() -> tuple[str, ...]:
    """phi11..phi33, G11..G33, C11..C33 (G = phi^T phi, C = phi phi^T)."""
    return tuple(f"{m}{a}{b}" for m in ("phi", "G", "C") for a in range(1, 4)
                 for b in range(1, 4))


# ----------------------------------------------------------------- Wigner D functions
def wigner(j: int, rotations: np.ndarray) -> np.ndarray:
    """D^j(L) [..., 2j + 1, 2j + 1] in the real harmonic basis of covariants3 ((D^j(L) p)(u) =
    p(L^T u)) for rotation matrices L [..., 3, 3]: D^j(exp(sum_g a_g K_g)) = exp(sum_g a_g
    K^j_g) with K_g the generators of covariants3.rotation_generators (the defining ones for
    j = 1, where D^1(L) = L) and a_g read off the axis-angle form of L."""
    rotations = np.asarray(rotations, float)
    flat = rotations.reshape(-1, 3, 3)
    # the axis-angle vector from the antisymmetric part (and, near omega = pi, from L + L^T)
    vee = np.stack([flat[:, 2, 1] - flat[:, 1, 2], flat[:, 0, 2] - flat[:, 2, 0],
                    flat[:, 1, 0] - flat[:, 0, 1]], -1)
    c = (np.trace(flat, axis1=1, axis2=2) - 1) / 2
    s = np.linalg.norm(vee, axis=-1) / 2
    angle = np.arctan2(s, c)
    small = s < 1e-6
    axis = vee / np.where(small, 1.0, 2 * s)[:, None]
    if np.any(small & (c < 0)):  # omega near pi: n n^T = ((L + L^T)/2 - c)/(1 - c) exactly
        for i in np.flatnonzero(small & (c < 0)):
            sym = ((flat[i] + flat[i].T) / 2 - c[i] * np.eye(3)) / (1 - c[i])
            k = int(np.argmax(np.diag(sym)))
            n = sym[:, k] / np.sqrt(sym[k, k])
            axis[i] = n if n @ vee[i] >= 0 else -n
    rotvec = np.where((small & (c > 0))[:, None], vee / 2, axis * angle[:, None])
    # K_01 = [e_3]_x, K_02 = -[e_2]_x, K_12 = [e_1]_x (covariants3 pairs (0,1), (0,2), (1,2))
    a = np.stack([rotvec[:, 2], -rotvec[:, 1], rotvec[:, 0]], -1)
    out = cov.expm_antisymmetric(np.einsum("pg,gab->pab", a, cov.rotation_generators(j)))
    return out.reshape(*rotations.shape[:-2], 2 * j + 1, 2 * j + 1)


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    a, b = [(1, 2), (0, 2), (0, 1)][axis]
    out = np.zeros(np.shape(angle) + (3, 3))
    out[..., axis, axis] = 1.0
    out[..., a, a], out[..., b, b] = c, c
    sign = -1.0 if axis == 1 else 1.0  # R_2(t) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    out[..., a, b], out[..., b, a] = -sign * s, sign * s
    return out


@cache
def euler_quadrature(rank: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations L = R_3(alpha) R_2(beta) R_3(gamma) [N, 3, 3] and weights [N] (sum 1) that
    integrate exactly, under the Haar measure, every function of rank <= ``rank`` (a
    combination of D^l, l <= rank): the trapezoid rule of rank + 1 points in alpha and in
    gamma (exact for e^{i m alpha}, |m| <= rank) and Gauss-Legendre in cos beta with
    rank // 2 + 1 nodes (what survives the averages is P_l(cos beta), l <= rank)."""
    n = rank + 1
    t = 2 * np.pi * np.arange(n) / n
    x, wx = np.polynomial.legendre.leggauss(rank // 2 + 1)
    A, X, C = np.meshgrid(t, x, t, indexing="ij")
    rot = (_axis_rotation(2, A.ravel()) @ _axis_rotation(1, np.arccos(X.ravel()))
           @ _axis_rotation(2, C.ravel()))
    weights = np.broadcast_to(wx[None, :, None] / (2 * n * n), A.shape).ravel()
    return rot, weights


@cache
def coupling_tensor(j1: int, j2: int, l: int) -> np.ndarray:
    """The unit SO(3)-invariant vector w [2 j1 + 1, 2 j2 + 1, 2l + 1] of V_j1 (x) V_j2 (x) V_l
    (real, in the harmonic bases), so that int D^j1_ab D^j2_cd D^l_pq = w[a, c, p] w[b, d, q];
    shape [0, ...] when the triangle rule forbids. Found as the null vector of the Casimir
    sum_g X_g^T X_g of the product restricted to the weight-zero subspace of the rotations
    about the third axis (its dimension is at most (2 j1 + 1)(2 j2 + 1))."""
    dims = (2 * j1 + 1, 2 * j2 + 1, 2 * l + 1)
    if not abs(j1 - j2) <= l <= j1 + j2:
        return np.zeros((0, *dims))
    U = [_magnetic(j) for j in (j1, j2, l)]
    m = [np.arange(j, -j - 1, -1) for j in (j1, j2, l)]
    zero = [(a, b, c) for a in range(dims[0]) for b in range(dims[1]) for c in range(dims[2])
            if m[0][a] + m[1][b] + m[2][c] == 0]
    B = np.stack([np.einsum("i,j,k->ijk", U[0][:, a], U[1][:, b], U[2][:, c])
                  for a, b, c in zero], -1)  # [d1, d2, d3, D0]
    gens = [cov.rotation_generators(j) for j in (j1, j2, l)]
    casimir = 0.0
    for g in range(3):
        X = (np.einsum("ia,ajkt->ijkt", gens[0][g], B) + np.einsum("ja,iakt->ijkt", gens[1][g], B)
             + np.einsum("ka,ijat->ijkt", gens[2][g], B)).reshape(-1, len(zero))
        casimir = casimir + X.conj().T @ X
    w, v = np.linalg.eigh(casimir)
    if not (w[0] < 1e-8 and (len(w) == 1 or w[1] > 0.5)):
        raise RuntimeError(f"the invariant of V_{j1} (x) V_{j2} (x) V_{l} is not unique")
    vec = (B.reshape(-1, len(zero)) @ v[:, 0])
    vec = vec * np.exp(-1j * np.angle(vec[np.argmax(np.abs(vec))]))
    real = vec.real / np.linalg.norm(vec.real)
    return real.reshape(1, *dims)


@cache
def _magnetic(j: int) -> np.ndarray:
    """Columns: eigenvectors of i K_01 on V_j with eigenvalues j, ..., -j."""
    w, v = np.linalg.eigh(1j * cov.rotation_generators(j)[0])
    return v[:, np.argsort(-w)]


# ------------------------------------------------------------------- the expansion
@dataclass(frozen=True)
class Expansion:
    """O(L diag Q R^T) = sum_t r_t(Q) sum_{l l'} T_t^{l l'}[p, q, r, s] D^l_pq(L) D^l'_rs(R).

    ``monomials``: exponents [M, C] over ``components`` (the components used);
    ``structure`` [k, M]: the monomials' coefficients in the k coefficient functions (the
    identity when they depend on the invariants: each monomial its own; else one row of
    constants); ``terms``: per radial function (coefficient function b, exponent e of Q) the
    tensors {(l, l'): T}."""

    components: tuple[str, ...]
    invariants: tuple[str, ...]
    monomials: np.ndarray
    probes: np.ndarray  # [K, C] interpolation points of the coefficient functions
    solve: np.ndarray  # [M, K]: s(v) = solve @ O(v, probes)
    structure: np.ndarray  # [k, M]
    terms: tuple  # ((b, e, {(l, lp): T}), ...)

    @property
    def ranks(self) -> tuple[tuple[int, int], ...]:
        return tuple(sorted({key for _, _, tensors in self.terms for key in tensors}))

    @cached_property
    def stacked(self) -> dict:
        """{(l, l'): T [terms, 2l + 1, 2l + 1, 2l' + 1, 2l' + 1]} (zero where a term lacks the
        rank): the tensors of :func:`contract`."""
        out = {}
        for key in self.ranks:
            shape = (2 * key[0] + 1,) * 2 + (2 * key[1] + 1,) * 2
            out[key] = np.stack([tensors.get(key, np.zeros(shape))
                                 for _, _, tensors in self.terms])
        return out

    def radial(self, expr, Q: np.ndarray) -> np.ndarray:
        """r_t(Q) [P, terms] at signed singular values Q [P, 3]: the coefficient function of
        the term's monomial (read off O at the interpolation points ``probes``; 1 for constant
        coefficients) times Q^e. ValueError where a coefficient is not finite or the
        polynomial form found at the probe points does not hold."""
        P = len(Q)
        if self.invariants:
            values = invariant_values(Q)
            args = {name: np.asarray(values[name])[:, None] for name in self.invariants}
            for c, name in enumerate(self.components):
                args[name] = self.probes[None, :, c]
            with np.errstate(all="ignore"):
                O = np.broadcast_to(np.asarray(expr(**args), float), (P, len(self.probes)))
            basis = O @ self.solve.T  # [P, M]
            if not np.all(np.isfinite(basis)):
                raise ValueError("is not finite where the states live (e.g. log of 0)")
            fit = basis @ _vandermonde(self.probes, self.monomials).T
            if np.max(np.abs(fit - O)) > 1e3 * FIT_TOLERANCE * (1 + np.max(np.abs(O))):
                raise ValueError("is not a polynomial in the components where the states live")
        else:
            basis = np.ones((P, 1))
        return np.stack([basis[:, b] * np.prod(Q ** np.asarray(e), -1)
                         for b, e, _ in self.terms], -1)


def _vandermonde(x: np.ndarray, exps: np.ndarray) -> np.ndarray:
    return np.prod(x[:, None, :] ** exps[None, :, :], -1)


def _exponents(count: int, degree: int) -> np.ndarray:
    out = [np.zeros(count, int)]
    for d in range(1, degree + 1):
        for combo in combinations_with_replacement(range(count), d):
            e = np.zeros(count, int)
            np.add.at(e, list(combo), 1)
            out.append(e)
    return np.array(out)


def expand(expr, used: tuple[str, ...], text: str, field: str = "--operator") -> Expansion:
    """The :class:`Expansion` of a compiled expression (module docstring); ValueError, one
    line, for an expression that is not a polynomial of degree <= MAX_DEGREE in the
    components or has too many monomials."""
    comps = tuple(v for v in used if v in component_names())
    invs = tuple(v for v in used if v not in comps)
    rng = np.random.default_rng(16)
    Qs = np.sort(rng.uniform(0.4, 1.8, (3, 3)), -1)[:, ::-1]
    refuse = (f"{field}: for n = 3 an operator is a polynomial of degree <= {MAX_DEGREE} in the "
              f"components of phi, G, C with coefficients that are any expression in the "
              f"invariants (e.g. 'phi11*phi22', 'G12**2 - trG*G33', 'exp(-trG)*C13'); {text!r} "
              f"is not (its SO(3) ranks do not terminate)")

    def evaluate(Q, x):
        values = invariant_values(Q)
        args = {name: np.asarray(values[name]) for name in invs}
        args.update({name: x[..., c] for c, name in enumerate(comps)})
        with np.errstate(all="ignore"):
            return np.broadcast_to(np.asarray(expr(**args), float), x.shape[:-1])

    # degree along rays, out to component values of 1.5 and of RAY_REACH (an expression that is
    # a polynomial only to the fit's tolerance near 0, e.g. exp(-0.02 G11), is not one there)
    u = np.cos(np.pi * (np.arange(MAX_DEGREE + 4) + 0.5) / (MAX_DEGREE + 4))
    degree = 0
    for Q in Qs:
        for reach in (1.5, RAY_REACH):
            x0 = rng.uniform(-1, 1, len(comps))
            g = evaluate(Q, reach * u[:, None] * x0[None])
            if not np.all(np.isfinite(g)):
                raise ValueError(refuse)
            for d in range(MAX_DEGREE + 1):
                c = np.polynomial.chebyshev.chebfit(u, g, d)
                if np.max(np.abs(np.polynomial.chebyshev.chebval(u, c) - g)) <= \
                        FIT_TOLERANCE * (np.max(np.abs(g)) + 1e-300):
                    break
            else:
                raise ValueError(refuse)
            degree = max(degree, d)
    exps = _exponents(len(comps), degree)
    if len(exps) > MAX_MONOMIALS:
        raise ValueError(f"{field}: {text!r} has {len(exps)} possible monomials of degree "
                         f"{degree} in its {len(comps)} components, more than the "
                         f"{MAX_MONOMIALS} this command is built for (use fewer components)")
    x = rng.uniform(-1, 1, (2 * len(exps) + 8, len(comps)))
    V = _vandermonde(x, exps)
    coefs = []
    for Q in Qs:
        y = evaluate(Q, x)
        c = np.linalg.lstsq(V, y, rcond=None)[0]
        fresh = rng.uniform(-1, 1, (8, len(comps)))
        check = evaluate(Q, fresh)
        if np.max(np.abs(_vandermonde(fresh, exps) @ c - check)) > \
                1e2 * FIT_TOLERANCE * (1 + np.max(np.abs(check))):
            raise ValueError(refuse)
        coefs.append(c)
    coefs = np.array(coefs)
    keep = np.max(np.abs(coefs), 0) > 1e-10 * max(np.max(np.abs(coefs)), 1e-300)
    exps, coefs = exps[keep], coefs[:, keep]
    if len(exps) == 0:
        exps, coefs = np.zeros((1, len(comps)), int), np.zeros((len(Qs), 1))
    probes = rng.uniform(-1, 1, (len(exps) + 4, len(comps)))
    solve = np.linalg.pinv(_vandermonde(probes, exps))
    # the coefficient functions: each monomial's own (any expression in the invariants), or
    # the constants found at the probes
    structure = np.eye(len(exps)) if invs else coefs[:1]
    terms = _angular_terms(comps, exps, structure)
    return Expansion(comps, invs, exps, probes, solve, structure, terms)


def _factors(comps, exponent) -> list[tuple[str, int, int]]:
    out = []
    for name, power in zip(comps, exponent, strict=True):
        kind = name[:-2]
        out += [(kind, int(name[-2]) - 1, int(name[-1]) - 1)] * int(power)
    return out


def _angular_terms(comps, exps, structure) -> tuple:
    """The tensors T of every (basis function, exponent of Q) (module docstring)."""
    pieces: dict[tuple[int, tuple], dict] = {}
    degrees = []
    for mono in exps:
        f = _factors(comps, mono)
        gL = sum({"phi": 1, "C": 2, "G": 0}[k] for k, _, _ in f)
        gR = sum({"phi": 1, "G": 2, "C": 0}[k] for k, _, _ in f)
        degrees.append((gL, gR))
    top = max(max(d) for d in degrees)
    rot, wq = euler_quadrature(2 * top)
    D = {l: wigner(l, rot) * wq[:, None, None] for l in range(top + 1)}
    for m, mono in enumerate(exps):
        f = _factors(comps, mono)
        gL, gR = degrees[m]
        by_e: dict[tuple, dict] = {}
        for K in product(range(3), repeat=len(f)):
            A = np.ones(len(rot))
            B = np.ones(len(rot))
            e = [0, 0, 0]
            for (kind, a, b), k in zip(f, K, strict=True):
                if kind == "phi":
                    A, B = A * rot[:, a, k], B * rot[:, b, k]
                    e[k] += 1
                elif kind == "G":
                    B = B * rot[:, a, k] * rot[:, b, k]
                    e[k] += 2
                else:
                    A = A * rot[:, a, k] * rot[:, b, k]
                    e[k] += 2
            a_l = {l: (2 * l + 1) * np.einsum("n,npq->pq", A, D[l]) for l in range(gL + 1)}
            b_l = {l: (2 * l + 1) * np.einsum("n,nrs->rs", B, D[l]) for l in range(gR + 1)}
            acc = by_e.setdefault(tuple(e), {})
            for l, a in a_l.items():
                if np.max(np.abs(a)) < 1e-13:
                    continue
                for lp, b in b_l.items():
                    if np.max(np.abs(b)) < 1e-13:
                        continue
                    acc[(l, lp)] = acc.get((l, lp), 0.0) + np.einsum("pq,rs->pqrs", a, b)
        for e, tensors in by_e.items():
            for bi in range(len(structure)):
                c = structure[bi, m]
                if c == 0.0:
                    continue
                target = pieces.setdefault((bi, e), {})
                for key, T in tensors.items():
                    target[key] = target.get(key, 0.0) + c * T
    terms = []
    for (b, e), tensors in sorted(pieces.items()):
        kept = {key: T for key, T in tensors.items() if np.max(np.abs(T)) > 1e-12}
        if kept:
            terms.append((b, e, kept))
    return tuple(terms)


def reduced_matrix(expansion: Expansion, moments: np.ndarray, jf: tuple[int, int],
                   ji: tuple[int, int]) -> np.ndarray | None:
    """M [(2 j_f + 1)(2 j'_f + 1), (2 j_i + 1)(2 j'_i + 1)] of two multiplets (spin, vorticity)
    ``jf``, ``ji`` from the radial moments [terms, b, d, b', d'] = int mu r_t F_f[b, d]
    F_i[b', d'] (module docstring): :func:`contract` of the expansion's tensors stacked over
    its terms; None when no rank of the operator satisfies both triangle rules (the selection
    rule)."""
    return contract(expansion.stacked, moments, jf, ji)


def contract(tensors: dict, moments: np.ndarray, jf: tuple[int, int], ji: tuple[int, int]
             ) -> np.ndarray | None:
    """The contraction shared by the exact expansion and the numerical projection: with
    ``tensors`` {(l, l'): T [t, 2l + 1, 2l + 1, 2l' + 1, 2l' + 1]} and ``moments``
    [t, b, d, b', d'] over the same terms t (the radial functions of an :class:`Expansion`, or
    the nodes of a chamber rule for :func:`project`),

        M[(a, c), (a', c')] = sum_t sum_{l l'} sum_pqrs T_t[p, q, r, s] w_l[a, a', p]
                              w_l[b, b', q] w_l'[c, c', r] w_l'[d, d', s] moments_t[b, d, b', d'],

    w the invariant vectors of :func:`coupling_tensor`; None when no rank satisfies both
    triangle rules."""
    out, reached = 0.0, False
    for key, T in tensors.items():
        wL = coupling_tensor(jf[0], ji[0], key[0])
        wR = coupling_tensor(jf[1], ji[1], key[1])
        if not (len(wL) and len(wR)):
            continue
        wL, wR = wL[0], wR[0]
        Y = np.einsum("bBq,dDs,tbdBD->tqs", wL, wR, moments, optimize=True)
        X = np.einsum("tpqrs,tqs->pr", T, Y, optimize=True)
        M = np.einsum("aAp,cCr,pr->acAC", wL, wR, X, optimize=True)
        out = out + M.reshape(wL.shape[0] * wR.shape[0], wL.shape[1] * wR.shape[1])
        reached = True
    return out if reached else None


# ------------------------------------------------- the numerical projection (any expression)
#: samples per one-parameter subgroup of the bandwidth probe (harmonics |m| < 62 resolved)
PROBE_SAMPLES = 128
#: a Fourier coefficient of the probe below this fraction of the largest counts as absent
BAND_TOLERANCE = 1e-13


def operator_grid(expr, used: tuple[str, ...], Q: np.ndarray, left: np.ndarray,
                  right: np.ndarray) -> np.ndarray:
    """O(L diag(Q) R^T) [P, NL, NR] at nodes Q [P, 3] and rotations L [NL, 3, 3], R [NR, 3, 3]:
    phi^i_a = sum_k L_ik Q_k R_ak, G_ab = sum_k R_ak R_bk Q_k^2, C_ij = sum_k L_ik L_jk Q_k^2,
    the invariants of Q; only the components ``used`` are formed (the expression compiled once
    per shape). ValueError where O is not finite."""
    comps = set(component_names())
    values = invariant_values(Q)
    args = {}
    for name in used:
        if name not in comps:
            args[name] = np.asarray(values[name], float).reshape(-1, 1, 1)
            continue
        a, b = int(name[-2]) - 1, int(name[-1]) - 1
        if name.startswith("phi"):
            args[name] = (Q[:, None, :] * left[None, :, a, :]) @ right[:, b, :].T
        elif name.startswith("G"):
            args[name] = ((Q * Q) @ (right[:, a, :] * right[:, b, :]).T)[:, None, :]
        else:
            args[name] = ((Q * Q) @ (left[:, a, :] * left[:, b, :]).T)[:, :, None]
    out = np.asarray(_compiled(expr)(args), float)
    out = np.broadcast_to(out, (len(Q), len(left), len(right)))
    if not np.all(np.isfinite(out)):
        raise ValueError("is not finite where the states live (e.g. log of 0)")
    return out


@cache
def _compiled(expr):
    """The expression as one compiled JAX program (per shape of its arguments)."""
    import jax

    return jax.jit(lambda args: expr(**args))


def fourier_reach(f: np.ndarray, tolerance=BAND_TOLERANCE, floor=0.0) -> int | None:
    """The largest |m| whose discrete Fourier coefficient of the periodic samples f [P, S]
    (each row one period) exceeds ``tolerance`` times the row's largest and the absolute
    ``floor`` (each a number, or one per row); None when that is within 2 of the Nyquist
    frequency S/2 (not resolved)."""
    samples = f.shape[1]
    F = np.abs(np.fft.fft(f, axis=1)) / samples
    m = np.abs(np.fft.fftfreq(samples, 1 / samples))
    top = np.max(F, axis=1, keepdims=True)
    tolerance = np.reshape(np.broadcast_to(tolerance, (len(f),)), (-1, 1))
    floor = np.reshape(np.broadcast_to(floor, (len(f),)), (-1, 1))
    above = F > np.maximum(tolerance * np.maximum(top, 1e-300), floor)
    reach = int(np.max(np.where(above, m[None], 0)))
    return None if reach >= samples // 2 - 2 else reach


def _padded(Q: np.ndarray, rows: int) -> np.ndarray:
    """Q with its last row repeated up to ``rows`` rows: every chunk of one grid has one shape,
    so the expression (JAX, compiled per shape) compiles once."""
    return np.concatenate([Q, np.repeat(Q[-1:], rows - len(Q), 0)]) if len(Q) < rows else Q


def _random_rotations(rng, count: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    return q * np.linalg.det(q)[:, None, None]


def bandwidth(expr, used: tuple[str, ...], Q: np.ndarray, samples: int = PROBE_SAMPLES,
              tolerance=BAND_TOLERANCE, floor=0.0) -> tuple[int | None, int | None]:
    """Estimated ranks (B_L, B_R) of L -> O(L diag Q R^T) and R -> O(...) at nodes Q [P, 3]:
    the largest |m| whose Fourier coefficient along t -> exp(t K) L (resp. R), K a random
    generator, exceeds ``tolerance`` times the largest, over three random subgroups and
    starting points (a function of rank l has |m| <= l along every such circle, and its rank
    shows along a generic one); ``tolerance`` (relative) and ``floor`` (absolute) as in
    :func:`fourier_reach`, a number or one per node; None when the coefficients have not
    decayed by |m| = samples/2 - 2 (not resolved: a kink, or too wide)."""
    rng = np.random.default_rng(16)
    t = 2 * np.pi * np.arange(samples) / samples
    count = len(Q)
    Q = _padded(Q, 32 * -(-count // 32))  # one shape for most probes (compiled once)
    tolerance = _padded(np.broadcast_to(np.asarray(tolerance, float), (count,))[:, None],
                        len(Q))[:, 0]
    floor = _padded(np.broadcast_to(np.asarray(floor, float), (count,))[:, None], len(Q))[:, 0]
    out = []
    for side in (0, 1):
        band = 0
        for _ in range(3):
            n = rng.normal(size=3)
            n /= np.linalg.norm(n)
            K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
            path = (np.eye(3) + np.sin(t)[:, None, None] * K
                    + (1 - np.cos(t))[:, None, None] * (K @ K))
            start, other = _random_rotations(rng, 2)
            moving = path @ start
            f = (operator_grid(expr, used, Q, moving, other[None]) if side == 0
                 else operator_grid(expr, used, Q, other[None], moving)).reshape(len(Q), -1)
            reach = fourier_reach(f, tolerance, floor)
            if reach is None:
                band = None
                break
            band = max(band, reach)
        out.append(band)
    return out[0], out[1]


def side_rows(used: tuple[str, ...]) -> tuple[set[int], set[int]]:
    """The rows of L and of R that an expression's components involve (0-based): phi_ia row i
    of L and row a of R, G_ab rows a, b of R, C_ij rows i, j of L (phi^i_a = sum_k L_ik Q_k R_ak,
    G_ab = sum_k R_ak R_bk Q_k^2, C_ij = sum_k L_ik L_jk Q_k^2)."""
    left, right = set(), set()
    for name in used:
        if name not in set(component_names()):
            continue
        a, b = int(name[-2]) - 1, int(name[-1]) - 1
        if name.startswith("phi"):
            left.add(a)
            right.add(b)
        elif name.startswith("G"):
            right |= {a, b}
        else:
            left |= {a, b}
    return left, right


def side_points(rank: int, rows: set[int]) -> int:
    """The rotations of :func:`side_rule` of ``rank`` for an operator using ``rows``."""
    return (rank + 1) * (rank // 2 + 1) * (1 if len(rows) == 1 else rank + 1)


@cache
def side_rule(rank: int, row: int | None) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Rotations [N, 3, 3], weights [N] (sum 1) and, per l, the matrix A^l with
    int f(L) D^l(L) dL = sum_k w_k f(L_k) A^l D^l(M_k) for every f of rank <= ``rank`` ... on
    one side of phi = L diag Q R^T. ``row`` None: :func:`euler_quadrature` (M_k = L_k, A^l = 1).
    ``row`` i: f depends on L only through its row i (f(S L) = f(L) for S fixing e_i), so with
    L = Pi R_3(alpha) M, Pi e_3 = e_i, the average over alpha is that of D^l(R_3(alpha)), the
    projector P^l on its m = 0 vector: L_k = Pi M_k, M_k = R_2(beta) R_3(gamma) on the rule's
    (beta, gamma) points and A^l = D^l(Pi) P^l, rank + 1 times fewer points."""
    if row is None:
        rot, w = euler_quadrature(rank)
        return rot, w, ()
    n = rank + 1
    t = 2 * np.pi * np.arange(n) / n
    x, wx = np.polynomial.legendre.leggauss(rank // 2 + 1)
    X, C = np.meshgrid(x, t, indexing="ij")
    M = _axis_rotation(1, np.arccos(X.ravel())) @ _axis_rotation(2, C.ravel())
    weights = np.broadcast_to(wx[:, None] / (2 * n), X.shape).ravel()
    Pi = {0: _axis_rotation(1, np.pi / 2), 1: _axis_rotation(0, -np.pi / 2),
          2: np.eye(3)}[row]
    return Pi @ M, weights, (Pi, M)


def _side_basis(rank: int, rows: set[int], lmax: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations [N, 3, 3] of :func:`side_rule` and the weighted Wigner matrices [N, K]
    (2l + 1) w_k (A^l D^l(M_k))_pq, l <= lmax, flattened over (l, p, q)."""
    row = next(iter(rows)) if len(rows) == 1 else None
    rot, w, zonal = side_rule(rank, row)
    blocks = []
    for l in range(lmax + 1):
        if zonal:
            Pi, M = zonal
            alpha = 2 * np.pi * np.arange(2 * l + 1) / (2 * l + 1)
            P = np.mean(wigner(l, _axis_rotation(2, alpha)), axis=0)
            D = (wigner(l, Pi) @ P)[None] @ wigner(l, M)
        else:
            D = wigner(l, rot)
        blocks.append((2 * l + 1) * (w[:, None, None] * D).reshape(len(rot), -1))
    return rot, np.concatenate(blocks, axis=1)


def project(expr, used: tuple[str, ...], Q: np.ndarray, lmax: tuple[int, int],
            ranks: tuple[int, int], chunk: int = 2_000_000) -> dict:
    """The angular components of O at every node Q [P, 3] up to the ranks ``lmax`` = (l_max,
    l'_max), by the Euler-angle rules of ``ranks`` on each side:

        c^{l l'}(Q)[p, q, r, s] = (2l + 1)(2l' + 1) int int O(L diag Q R^T) D^l_pq(L)
                                  D^l'_rs(R) dL dR,

    exact when O's ranks are at most ``ranks`` - ``lmax`` on each side, else with the aliasing
    of its higher ranks (docs/quantum-transitions.md, "Operators that are not polynomials");
    a side whose components involve one row of its rotation only takes the reduced rule of
    :func:`side_rule`. Returns {(l, l'): c [P, 2l + 1, 2l + 1, 2l' + 1, 2l' + 1]}: the tensors
    of :func:`contract` with the nodes as terms."""
    rows = side_rows(used)
    (rotL, DL), (rotR, DR) = (_side_basis(ranks[side], rows[side], lmax[side])
                              for side in (0, 1))
    rots = (rotL, rotR)
    step = min(len(Q), max(1, chunk // (len(rots[0]) * len(rots[1]))))
    c = np.empty((len(Q), DL.shape[1], DR.shape[1]))
    for s in range(0, len(Q), step):
        V = operator_grid(expr, used, _padded(Q[s:s + step], step), rots[0], rots[1])
        V = V[:len(Q) - s]  # [p, NL, NR]
        c[s:s + step] = np.einsum("lk,plm->pkm", DL, V @ DR, optimize=True)
    out, i0 = {}, 0
    for l in range(lmax[0] + 1):
        j0 = 0
        for lp in range(lmax[1] + 1):
            a, b = (2 * l + 1) ** 2, (2 * lp + 1) ** 2
            out[(l, lp)] = c[:, i0:i0 + a, j0:j0 + b].reshape(
                len(Q), 2 * l + 1, 2 * l + 1, 2 * lp + 1, 2 * lp + 1)
            j0 += b
        i0 += a
    return out


__all__ = ["MAX_DEGREE", "MAX_MONOMIALS", "PROBE_SAMPLES", "BAND_TOLERANCE", "component_names",
           "wigner", "euler_quadrature", "side_rows", "side_points", "side_rule", "coupling_tensor",
           "Expansion", "expand",
           "reduced_matrix", "contract", "operator_grid", "fourier_reach", "bandwidth", "project"]
