"""One-dimensional bases of the reduced problems and the shared dense solver
(docs/theory/two-polar.md).

Gauss quadratures by Golub-Welsch, 2D-radial (generalised Laguerre) and Hermite functions, the
basis descriptor :class:`Basis` used to evaluate eigenfunctions, the smooth functions of the Haar
conjugation g(x) = sqrt(x / sinh x), and :func:`solve_block` (main, nested and widened bases:
the spread is the error estimate).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import linalg, optimize, special

from affinebody.quantum.levels import Settings, level_starts


# ------------------------------------------------------------------ one-dimensional bases
def gauss_basis(jacobi_diag: np.ndarray, jacobi_off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss nodes and the matrix B[g, j] = sqrt(w_g) p_j(t_g) of orthonormal polynomials.

    Golub-Welsch: the eigenvectors of the Jacobi matrix (the matrix of t in the orthonormal
    basis) are exactly sqrt(w_g) p_j(t_g), with the sign fixed by p_0 > 0. No overflow for large
    degrees or parameters, unlike explicit weights and polynomial values.
    """
    nodes, vecs = linalg.eigh_tridiagonal(jacobi_diag, jacobi_off)
    vecs = vecs * np.sign(vecs[0])[None, :]
    return nodes, vecs.T


def laguerre_jacobi(m: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi matrix of t for Laguerre polynomials orthonormal under t^m e^-t dt on (0, inf)."""
    j = np.arange(size, dtype=float)
    return 2 * j + m + 1, -np.sqrt((j[1:]) * (j[1:] + m))


def hermite_jacobi(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi matrix of x for Hermite polynomials orthonormal under e^{-x^2} dx."""
    j = np.arange(1, size, dtype=float)
    return np.zeros(size), np.sqrt(j / 2)


#: the recurrences of :func:`_scaled_recurrence` divide p_j by 2^_RESCALE wherever it exceeds
#: that (exactly: a power of two) ...
_RESCALE = 512
#: ... and take an argument beyond _DEAD (t = r^2/b^2, or |y|) as where every basis function
#: is 0 in float64 (e^{-t/2} t^j, e^{-y^2/2} y^j underflow for any degree in use); below it
#: a step grows |p| by at most ~2^401, so p stays below 2^913 before it is rescaled
_DEAD = 2.0**400


def _scaled_recurrence(p0: np.ndarray, step, size: int, weight: np.ndarray,
                       log_front: np.ndarray, log_constant: float) -> np.ndarray:
    """Values [P, size] of weight x p_j of a three-term recurrence p_{j+1} = step(j, p_j,
    p_{j-1}) (p_{-1} = 0) of orthonormal polynomials, ``weight`` = exp(log_front) x
    exp(log_constant) the Gaussian front factor (0 where the argument is dead).

    Far outside the support of the functions p_j grows like t^j and overflows to inf long
    before the front factor (0 there) is applied: inf x 0 = nan. Wherever |p_j| passes
    2^512, p_j and p_{j-1} are divided by 2^512 (exact) and the weight of that point becomes
    exp(log_front + shifts x 512 ln 2 + log_constant) (tiny or 0 where the function is). Points
    never rescaled (all points at ordinary arguments) keep ``weight`` itself: their values are
    those of the plain recurrence bit for bit."""
    out = np.empty((size,) + p0.shape)  # row j contiguous: returned transposed, [P, size]
    p_prev, p = np.zeros_like(p0), p0
    shifts = None
    for j in range(size):
        np.multiply(p, weight, out=out[j])
        if j + 1 == size:
            break
        p_prev, p = p, step(j, p, p_prev)
        big = np.flatnonzero(np.abs(p) > 2.0**_RESCALE)
        if big.size:
            if shifts is None:
                shifts = np.zeros(p.shape, dtype=np.int64)
            p[big] *= 2.0**-_RESCALE  # both arrays are this function's own (p0 the caller's
            p_prev[big] *= 2.0**-_RESCALE  # fresh array): scaled in place
            shifts[big] += 1
            weight[big] = np.exp(log_front[big] + shifts[big] * (_RESCALE * math.log(2.0))
                                 + log_constant)
    return out.T


@dataclass(frozen=True)
class Radial2D:
    """2D-radial oscillator functions u_j(r) = sqrt(2) b^-1 (r/b)^m e^{-t/2} l_j(t), t = r^2/b^2.

    Orthonormal under r dr; ``laplacian`` is the exact Galerkin matrix of
    -(1/r)(r u')' + m^2 u / r^2, namely (2 diag(2j+m+1) - T)/b^2 with T the Jacobi matrix.
    """

    m: int
    size: int
    scale: float
    quad: int

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        t, B = gauss_basis(*laguerre_jacobi(self.m, self.quad))
        return self.scale * np.sqrt(t), B[:, : self.size]

    def laplacian(self) -> np.ndarray:
        d, o = laguerre_jacobi(self.m, self.size)
        T = np.diag(d) + np.diag(o, 1) + np.diag(o, -1)
        return (2 * np.diag(d) - T) / self.scale**2

    def evaluate(self, r: np.ndarray, size: int | None = None) -> np.ndarray:
        """u_j(r) at arbitrary r >= 0, shape [..., size] (the first ``size`` functions, all by
        default), by the scaled recurrence of
        :func:`_scaled_recurrence` (finite and exact to round-off at any r: far out, where
        l_j(t) ~ t^j overflows long before e^{-t/2} is folded in, the values are the tiny or
        zero numbers they are, not inf x 0 = nan)."""
        with np.errstate(over="ignore"):  # r beyond ~1e154: t = inf, dead below
            t = (np.asarray(r, float) / self.scale) ** 2
        shape = t.shape
        t = t.ravel()
        dead = t > _DEAD  # e^{-t/2} t^j underflows for every j: all functions are 0 there
        t = np.where(dead, 0.0, t)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_power = np.where(t > 0, 0.5 * self.m * np.log(np.where(t > 0, t, 1.0)),
                                 0.0 if self.m == 0 else -np.inf)
        log_front = log_power - 0.5 * t - 0.5 * special.gammaln(self.m + 1)
        weight = np.where(dead, 0.0, np.exp(log_front) * math.sqrt(2) / self.scale)
        j = np.arange(self.size, dtype=float)
        a = 2 * j + self.m + 1
        b_next = np.sqrt((j + 1) * (j + 1 + self.m))
        b_here = np.sqrt(j * (j + self.m))

        def step(k, p, p_prev):
            return ((a[k] - t) * p - b_here[k] * p_prev) / b_next[k]

        size = self.size if size is None else size
        out = _scaled_recurrence(np.ones_like(t), step, size, weight, log_front,
                                 math.log(math.sqrt(2) / self.scale))
        return out.reshape(shape + (size,))


@dataclass(frozen=True)
class Hermite1D:
    """Hermite functions h_j(x) = b^-1/2 psi_j((x - c)/b), orthonormal under dx.

    ``laplacian`` is the exact Galerkin matrix of -d^2/dx^2, (2 diag(j + 1/2) - X^2)/b^2.
    """

    size: int
    scale: float
    centre: float
    quad: int

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        y, B = gauss_basis(*hermite_jacobi(self.quad))
        return self.centre + self.scale * y, B[:, : self.size]

    def laplacian(self) -> np.ndarray:
        d, o = hermite_jacobi(self.size + 1)
        X = np.diag(o, 1) + np.diag(o, -1)
        X2 = (X @ X)[: self.size, : self.size]
        return (2 * np.diag(np.arange(self.size) + 0.5) - X2) / self.scale**2

    def evaluate(self, x: np.ndarray, size: int | None = None) -> np.ndarray:
        """h_j(x) at arbitrary x, shape [..., size] (the first ``size``, all by default; the
        scaled recurrence of
        :func:`_scaled_recurrence`: finite at any x)."""
        with np.errstate(over="ignore"):  # |y| = inf: dead below
            y = (np.asarray(x, float) - self.centre) / self.scale
        shape = y.shape
        y = y.ravel()
        dead = np.abs(y) > _DEAD
        y = np.where(dead, 0.0, y)
        log_front = -0.5 * y * y
        weight = np.where(dead, 0.0, np.exp(log_front) / math.sqrt(self.scale))

        def step(j, p, p_prev):
            return math.sqrt(2.0 / (j + 1)) * y * p - math.sqrt(j / (j + 1)) * p_prev

        size = self.size if size is None else size
        out = _scaled_recurrence(np.full_like(y, math.pi**-0.25), step, size, weight,
                                 log_front, -0.5 * math.log(self.scale))
        return out.reshape(shape + (size,))


# --------------------------------------------------------------------- reduced problems
@dataclass(frozen=True)
class Basis:
    """What is needed to evaluate a block's eigenfunctions: kind plus its 1D factors."""

    kind: str  # "lebesgue2", "haar2", "scalar3"
    factors: tuple

    def reduced_values(self, coords: tuple[np.ndarray, ...]) -> np.ndarray:
        """Basis functions at reduced coordinates (r1, r2) / (x, sigma) / Q [P, 3]."""
        if self.kind == "lebesgue2":
            u1 = self.factors[0].evaluate(coords[0])
            u2 = self.factors[1].evaluate(coords[1])
            return (u1[..., :, None] * u2[..., None, :]).reshape(u1.shape[:-1] + (-1,))
        if self.kind == "haar2":
            x, sigma = coords
            g = sqrt_x_over_sinh(x)
            u = self.factors[0].evaluate(x) * g[..., None]
            h = self.factors[1].evaluate(sigma)
            return (u[..., :, None] * h[..., None, :]).reshape(u.shape[:-1] + (-1,))
        return self.factors[0].evaluate(coords[0])


def sqrt_x_over_sinh(x: np.ndarray) -> np.ndarray:
    """g(x) = sqrt(x / sinh x), smooth (-> 1 - x^2/12 at 0): the conjugation of the Haar radial
    part (module docstring)."""
    x = np.asarray(x, float)
    small = np.abs(x) < 1e-4
    safe = np.where(small, 1.0, x)
    return np.where(small, 1 - x * x / 12, np.sqrt(safe / np.sinh(safe)))


def inv_x2_minus_inv_sinh2(x: np.ndarray) -> np.ndarray:
    """1/x^2 - 1/sinh^2 x, smooth (-> 1/3 at 0)."""
    x = np.asarray(x, float)
    small = np.abs(x) < 2e-2
    safe = np.where(small, 1.0, x)
    series = 1 / 3 - x**2 / 15 + 2 * x**4 / 189
    return np.where(small, series, 1 / safe**2 - 1 / np.sinh(safe) ** 2)


def sqrt_x_over_sinh_derivative_ratio(x: np.ndarray) -> np.ndarray:
    """d/dx log sqrt(x / sinh x) = (1/x - coth x)/2, smooth (-> -x/6 at 0)."""
    small = np.abs(x) < 1e-3
    safe = np.where(small, 1.0, x)
    return np.where(small, -x / 6, 0.5 * (1 / safe - 1 / np.tanh(safe)))


def product_potential_matrix(B1: np.ndarray, B2: np.ndarray, V: np.ndarray) -> np.ndarray:
    """The Galerkin matrix of a potential in a product basis by Gauss quadrature,
    H[(a, b), (c, d)] = sum_gh B1[g, a] B2[h, b] V[g, h] B1[g, c] B2[h, d] (``B1`` [q1, s1] and
    ``B2`` [q2, s2] as :func:`gauss_basis` gives them, ``V`` [q1, q2] at the product nodes),
    summed one factor at a time: q1 q2 s2^2 + q1 s1^2 s2^2 operations where the dense
    product (B1 x B2)^T V (B1 x B2) takes 2 q1 q2 s1^2 s2^2 (two orders of magnitude at the
    largest n = 2 bases), with memory O(s1^2 s2^2) instead of O(q1 q2 s1 s2)."""
    q1, s1 = B1.shape
    q2, s2 = B2.shape
    pairs1 = (B1[:, :, None] * B1[:, None, :]).reshape(q1, s1 * s1)  # [g, (a, c)]
    pairs2 = (B2[:, :, None] * B2[:, None, :]).reshape(q2, s2 * s2)  # [h, (b, d)]
    inner = np.asarray(V, float) @ pairs2  # [g, (b, d)]
    H = (pairs1.T @ inner).reshape(s1, s1, s2, s2)  # [a, c, b, d]
    return H.transpose(0, 2, 1, 3).reshape(s1 * s2, s1 * s2)


def dense_lowest(H: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest eigenpairs of the symmetric ``H`` (all where it has fewer)."""
    count = min(count, H.shape[0])
    w, v = linalg.eigh(H, subset_by_index=[0, count - 1], driver="evr")
    return w, v


def lowest_eigenvalues(H: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` lowest eigenvalues of the symmetric ``H`` (all where it has fewer; none for
    an empty ``H``), found alone: LAPACK's subset by index, not the whole spectrum cut short."""
    count = min(count, H.shape[0])
    if count == 0:
        return np.zeros(0)
    return linalg.eigvalsh(H, subset_by_index=[0, count - 1])


def solve_block(build: Callable[[int, float], tuple[np.ndarray, Basis]], size: int, scale: float,
                count: int, settings: Settings
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Basis]:
    """The ``count`` lowest eigenpairs of ``build(size, scale)`` and their error estimates: the
    larger change under the nested basis ``size - check_shrink`` and the widened basis
    ``scale * check_widen`` (skipped when check_widen == 1); inf where a check basis has fewer
    levels. Returns (energies, eigenvectors, errors, basis)."""
    H, basis = build(size, scale)
    if H.size == 0:  # no basis function (an n = 3 sector starting above this degree)
        return np.zeros(0), np.zeros((0, 0)), np.zeros(0), basis
    E, vec = dense_lowest(H, count)
    Hs, _ = build(size - settings.check_shrink, scale)
    Es = lowest_eigenvalues(Hs, len(E))
    if settings.check_widen == 1.0:
        Ew = E
    else:
        Hw, _ = build(size, scale * settings.check_widen)
        Ew = lowest_eigenvalues(Hw, len(E))
    err = np.full(len(E), np.inf)
    k = min(len(Es), len(Ew))
    err[:k] = np.maximum(np.abs(E[:k] - Es[:k]), np.abs(E[:k] - Ew[:k]))
    return E, vec, level_errors(E, err, settings), basis


def level_errors(E: np.ndarray, err: np.ndarray, settings: Settings) -> np.ndarray:
    """``err`` with each state's estimate replaced by the largest over its degenerate level
    (ascending energies E joined into levels by :func:`affinebody.quantum.levels.level_starts`).

    The estimates pair the states with the check bases' levels by index, which a degenerate
    level's eigenvectors (any orthonormal basis of its eigenspace, as LAPACK happens to return
    it) do not determine; a sum weighted by |c_n|^2 over such states (the packet's
    ``energy_error`` of the evolve command) would depend on that choice, one estimate per level
    does not."""
    if len(E) == 0:
        return err
    starts = level_starts(E, settings.merge)
    return np.repeat(np.maximum.reduceat(err, starts), np.diff(np.r_[starts, len(E)]))

def lowest_sum(H: np.ndarray, count: int) -> float:
    """The sum of the ``count`` lowest eigenvalues of ``H``: the objective of the automatic
    basis scales. +inf where ``H`` is not finite (the potential overflows float64 at a
    quadrature point of a trial scale, e.g. ``trG`` = e^(2 q) far out): the search then
    avoids that scale instead of stopping on LAPACK's refusal."""
    if not np.all(np.isfinite(H)):
        return np.inf
    return float(np.sum(lowest_eigenvalues(H, count)))


def variational_parameters(energy: Callable[[np.ndarray], float], start: np.ndarray
                           ) -> np.ndarray:
    """The basis parameters (log-scales, centre) minimising ``energy`` (Nelder-Mead from
    ``start``; coarse: only the basis quality depends on them)."""
    res = optimize.minimize(energy, start, method="Nelder-Mead",
                            options={"xatol": 1e-3, "fatol": 1e-10, "maxiter": 200})
    return res.x


def variational_scales(energy: Callable[[float, float, float], float], start: tuple,
                       given: tuple, clip: tuple[float, float]) -> tuple[float, float, float]:
    """(scale, scale_sigma, centre) of an affine model's basis minimising
    ``energy(scale, scale_sigma, centre)`` (:func:`variational_parameters` from ``start`` =
    (log scale, log scale_sigma, centre), the log scales clipped to ``clip``); those that
    ``given`` sets are held, and the others minimise again from the full minimiser (the
    objective can be flat to round-off in a scale: a search of the free ones alone from
    ``start`` stopped where the basis did not converge)."""
    free = [i for i, value in enumerate(given) if value is None]

    def scales(x, which=(0, 1, 2), held=(None,) * 3):
        p = list(held)
        for i, value in zip(which, x, strict=True):
            p[i] = float(np.exp(np.clip(value, *clip))) if i < 2 else float(value)
        return tuple(p)
    full = variational_parameters(lambda x: energy(*scales(x)), np.asarray(start, float))
    if len(free) == 3:
        return scales(full)
    found = variational_parameters(lambda x: energy(*scales(x, free, given)), full[free])
    return scales(found, free, given)


def centre_runs_away(energy: Callable[[float, float, float], float], scale: float,
                     scale_sigma: float, centre: float) -> bool:
    """True where the automatic centre of an affine basis is no minimum of ``energy(scale,
    scale_sigma, centre)`` (the objective of :func:`variational_scales`): a shift by one basis
    width ``scale_sigma`` either way does not raise it (to 1e-9 relative). A potential that
    does not confine the dilatation sigma = ln det phi (V tends to a constant as det -> 0, e.g.
    0.5 trG: the spectrum is continuous there) gives an objective with no minimum in the
    centre, and the search drifts until round-off stops it where V underflows and the objective
    is flat (a centre of -8450 for 0.5 trG with n = 2 af-is, -124 for README's n = 3 potential
    with af-is); at a minimum the shift raises the sum by a finite amount."""
    here = energy(scale, scale_sigma, centre)
    shifted = min(energy(scale, scale_sigma, centre - scale_sigma),
                  energy(scale, scale_sigma, centre + scale_sigma))
    return not shifted > here + 1e-9 * abs(here)


def runaway_message(model: str, scale: float, scale_sigma: float, centre: float,
                    n: int = 2) -> str:
    """The one line for automatic affine scales that ran away (:func:`centre_runs_away`, or a
    basis not finite at the scales found). Where V does not confine the body (``trG`` with an
    affine model tends to 0 as det -> 0) the sum :func:`variational_scales` minimises has no
    minimum, and the search drifts until round-off decides where it stops: where V overflows
    float64 (eigenvalues ~ -1e251 of a positive operator; trG) or where it underflows to 0 and
    the sum is flat (0.5 trG). Where V is nowhere below its limit at det -> 0 (README's n = 3
    potential with af-is: 0.5 x + 0.8 e^{-x/2} >= 0.8 for x = trG >= 0) the spectrum is
    continuous from its bottom and no basis size converges a level."""
    return (f"the automatic basis of the n = {n} {model} model ran away (scale {scale:.3g}, "
            f"scale_sigma {scale_sigma:.3g}, centre {centre:.3g}, where the search found no "
            f"minimum): a potential that does not confine the body (e.g. tends to a "
            f"constant as det -> 0) has no best basis; add a confining term to "
            f"quantum.potential, or set quantum.scale, quantum.scale_sigma and quantum.centre")


__all__ = [
    "gauss_basis", "laguerre_jacobi", "hermite_jacobi", "Radial2D", "Hermite1D", "Basis",
    "sqrt_x_over_sinh", "inv_x2_minus_inv_sinh2", "sqrt_x_over_sinh_derivative_ratio",
    "dense_lowest", "lowest_eigenvalues", "product_potential_matrix", "solve_block", "level_errors",
    "lowest_sum", "variational_parameters", "variational_scales", "centre_runs_away",
    "runaway_message"
]
