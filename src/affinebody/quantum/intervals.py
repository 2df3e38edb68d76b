"""Interval arithmetic on potential expressions: certified lower bounds of V on cells of the
reduced domain (docs/theory/two-polar.md, "Lower bounds of a sector").

A potential given as text (the grammar of :mod:`affinebody.expressions`, variables
q1..qn, Q1..Qn, trG, K1..Kn, det) is evaluated on a whole array of cells at once; every value
is an enclosure, so the lower end of the result is a lower bound of V on the cell.

Plain interval arithmetic overestimates when a variable occurs several times (the dependency
problem); on the unbounded cells of the reduced domain that loses everything (Q1 Q2 / (Q1 + Q2)^2
on Q1, Q2 in [a, inf] gives [0, inf]). Two exact representations keep the dependencies the
reduced coordinates make explicit:

* monomials ``lam^d tau^e [lo, hi]``: n = 2 affine models, Q_1 = lam tau, Q_2 = lam / tau with
  lam = e^(sigma/2), tau = e^(x/2); d'Alembert, Q_a = rho c_a(theta) (lam = rho, no tau).
  Products, quotients and powers act on the exponents exactly, so scale-invariant parts
  (degree 0 in lam) are bounded independently of sigma (resp. rho), also on unbounded cells;
* linear forms ``a sigma + b x + [lo, hi]`` (affine models: q_1 = (sigma + x)/2,
  q_2 = (sigma - x)/2), exact under sums and constant multiples, so (q1 + q2)^2 = sigma^2.

Everything else is flattened to an interval over the cell. Each arithmetic result is widened
outward by one ulp (nextafter) and each elementary function by two ulps: the enclosures assume
numpy's libm is within one ulp (true of exp, log, sin, ... on the platforms supported) and
IEEE-754 arithmetic (a product with an exact zero factor is kept exactly 0; underflow below
5e-324 is ignored). 0 * inf is taken as 0 (the convention of extended interval arithmetic),
an undefined result (inf - inf, a division by an interval containing 0, sqrt/log of a negative
interval) encloses everything: [-inf, inf], so it never yields a false bound.
"""

from __future__ import annotations

import abc
import ast
import math
from dataclasses import dataclass

import numpy as np

from affinebody.expressions import CONSTANTS, compile_expression


# ------------------------------------------------------------------------------ intervals
def _down(v: np.ndarray, ulps: int = 1) -> np.ndarray:
    for _ in range(ulps):
        v = np.nextafter(v, -np.inf)
    return v


def _up(v: np.ndarray, ulps: int = 1) -> np.ndarray:
    for _ in range(ulps):
        v = np.nextafter(v, np.inf)
    return v


@dataclass(frozen=True)
class Interval:
    """Arrays of lower and upper ends (NaN never survives: it is widened to -inf / inf)."""

    lo: np.ndarray
    hi: np.ndarray

    @staticmethod
    def make(lo, hi, ulps: int = 1) -> Interval:
        lo = np.asarray(lo, float)
        hi = np.asarray(hi, float)
        bad = np.isnan(lo) | np.isnan(hi)
        lo = np.where(bad, -np.inf, _down(lo, ulps))
        hi = np.where(bad, np.inf, _up(hi, ulps))
        return Interval(lo, hi)

    def is_scalar_point(self) -> bool:
        return np.ndim(self.lo) == 0 and np.ndim(self.hi) == 0 and float(self.lo) == float(
            self.hi)

    @staticmethod
    def point(value: float) -> Interval:
        return Interval(np.asarray(value, float), np.asarray(value, float))

    def __add__(self, other: Interval) -> Interval:
        if self.is_scalar_point() and other.is_scalar_point():
            a, b = float(self.lo), float(other.lo)
            s = a + b
            if math.isfinite(s) and (s - a) == b and (s - b) == a:  # the float sum is exact
                return Interval.point(s)
        with np.errstate(invalid="ignore"):
            lo, hi = self.lo + other.lo, self.hi + other.hi
        out = Interval.make(lo, hi)
        # a float sum that is 0 is exact (x + y rounds to 0 only if x = -y): keep 0 unwidened
        return Interval(np.where(lo == 0, 0.0, out.lo), np.where(hi == 0, 0.0, out.hi))

    def __neg__(self) -> Interval:
        return Interval(-self.hi, -self.lo)

    def __sub__(self, other: Interval) -> Interval:
        return self + (-other)

    def __mul__(self, other: Interval) -> Interval:
        with np.errstate(invalid="ignore", over="ignore"):
            prods = [self.lo * other.lo, self.lo * other.hi, self.hi * other.lo,
                     self.hi * other.hi]
        prods = [np.where(np.isnan(p), 0.0, p) for p in prods]  # 0 * inf = 0
        lo, hi = np.minimum.reduce(prods), np.maximum.reduce(prods)
        out = Interval.make(lo, hi)
        # a product with an exact 0 factor is exactly 0: keep 0 unwidened there
        zero = ((self.lo == 0) | (self.hi == 0) | (other.lo == 0) | (other.hi == 0))
        return Interval(np.where(zero & (lo == 0), 0.0, out.lo),
                        np.where(zero & (hi == 0), 0.0, out.hi))

    def reciprocal(self) -> Interval:
        with np.errstate(divide="ignore"):
            lo = np.where(self.hi == 0, -np.inf, 1 / self.hi)
            hi = np.where(self.lo == 0, np.inf, 1 / self.lo)
        straddles = (self.lo < 0) & (self.hi > 0)
        return Interval.make(np.where(straddles, -np.inf, lo), np.where(straddles, np.inf, hi))

    def __truediv__(self, other: Interval) -> Interval:
        return self * other.reciprocal()

    def integer_power(self, m: int) -> Interval:
        if m == 0:
            return Interval.point(1.0) + Interval(0 * self.lo, 0 * self.hi)
        if m < 0:
            return self.integer_power(-m).reciprocal()
        with np.errstate(over="ignore", invalid="ignore"):
            a, b = self.lo**m, self.hi**m
        if m % 2:
            return Interval.make(a, b)
        straddles = (self.lo < 0) & (self.hi > 0)
        lo = np.where(self.lo >= 0, a, np.where(self.hi <= 0, b, 0.0))
        out = Interval.make(lo, np.maximum(a, b))
        return Interval(np.where(straddles, 0.0, out.lo), out.hi)  # exactly 0 there

    def real_power(self, m: float) -> Interval:
        """x^m for a non-integer m: defined for x >= 0 only."""
        negative = self.lo < 0
        lo = np.maximum(self.lo, 0.0)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            a, b = lo**m, self.hi**m
        small, large = (a, b) if m > 0 else (b, a)
        return Interval.make(np.where(negative, -np.inf, small), np.where(negative, np.inf, large),
                             ulps=2)

    def increasing(self, fn, lo_domain: float = -np.inf, hi_domain: float = np.inf) -> Interval:
        """fn monotone increasing on [lo_domain, hi_domain]; outside it: everything."""
        bad = (self.lo < lo_domain) | (self.hi > hi_domain)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            a = fn(np.clip(self.lo, lo_domain, hi_domain))
            b = fn(np.clip(self.hi, lo_domain, hi_domain))
        return Interval.make(np.where(bad, -np.inf, a), np.where(bad, np.inf, b), ulps=2)

    def decreasing(self, fn, lo_domain: float = -np.inf, hi_domain: float = np.inf) -> Interval:
        return (-self).increasing(lambda v: -fn(-v), -hi_domain, -lo_domain)

    def even(self, fn) -> Interval:
        """fn even and increasing on [0, inf) (cosh, abs, square)."""
        straddles = (self.lo < 0) & (self.hi > 0)
        mag = Interval(np.where(self.lo >= 0, self.lo, np.where(self.hi <= 0, -self.hi, 0.0)),
                       np.maximum(np.abs(self.lo), np.abs(self.hi)))
        out = mag.increasing(fn)
        at_zero = float(fn(np.float64(0.0)))  # fn(0) exactly: abs, square -> 0, cosh -> 1
        return Interval(np.where(straddles, np.minimum(out.hi, at_zero) if at_zero == 0.0
                                 else out.lo, out.lo), out.hi)

    def periodic(self, fn, phase: float) -> Interval:
        """fn(t) = sin(t + phase) (sin: phase 0, cos: phase pi/2): the values at the ends, and
        +1 / -1 where a crest t + phase = pi/2 + 2 pi j / a trough 3 pi/2 + 2 pi j lies inside."""
        with np.errstate(invalid="ignore", over="ignore"):
            a, b = fn(self.lo), fn(self.hi)
            u_lo, u_hi = self.lo + phase, self.hi + phase

            def contains(centre):
                return (np.floor((u_hi - centre) / (2 * np.pi))
                        >= np.ceil((u_lo - centre) / (2 * np.pi)))
            has_max, has_min = contains(np.pi / 2), contains(3 * np.pi / 2)
        wide = ~np.isfinite(self.lo) | ~np.isfinite(self.hi) | (self.hi - self.lo >= 2 * np.pi)
        lo = np.where(wide | has_min, -1.0, np.minimum(a, b))
        hi = np.where(wide | has_max, 1.0, np.maximum(a, b))
        return Interval.make(lo, hi, ulps=2)

    def minimum(self, other: Interval) -> Interval:
        return Interval(np.minimum(self.lo, other.lo), np.minimum(self.hi, other.hi))

    def maximum(self, other: Interval) -> Interval:
        return Interval(np.maximum(self.lo, other.lo), np.maximum(self.hi, other.hi))


def quadratic_range(s: Interval, qq: float, a: float) -> Interval:
    """Enclosure of qq t^2 + a t for t in s (cells possibly unbounded): ends and vertex."""
    with np.errstate(invalid="ignore", over="ignore"):
        def f(t):
            out = qq * t * t + a * t if qq else a * t
            return np.where(np.isnan(out), np.inf if qq > 0 else -np.inf, out)
        ends = [f(s.lo), f(s.hi)]
        lo, hi = np.minimum(*ends), np.maximum(*ends)
        if qq:
            vertex = -a / (2 * qq)
            inside = (s.lo <= vertex) & (vertex <= s.hi)
            fv = qq * vertex * vertex + a * vertex
            lo = np.where(inside & (qq > 0), np.minimum(lo, fv), lo)
            hi = np.where(inside & (qq < 0), np.maximum(hi, fv), hi)
    return Interval.make(lo, hi, ulps=4)


def _uniform_point(iv: Interval) -> bool:
    lo, hi = np.ravel(iv.lo), np.ravel(iv.hi)
    return bool(np.all(lo == hi) and np.all(lo == lo[0]))


# ------------------------------------------------------------------ values with structure
@dataclass(frozen=True)
class Value:
    """lam^d tau^e iv when (d, e) != (0, 0); else qq sigma^2 + a sigma + b x + iv. ``const``:
    the exact number when the value is a literal constant."""

    iv: Interval
    d: float = 0.0
    e: float = 0.0
    a: float = 0.0
    b: float = 0.0
    const: float | None = None
    qq: float = 0.0

    @property
    def structured(self) -> bool:
        """Carries a linear / quadratic form (qq, a, b not all 0)."""
        return bool(self.a or self.b or self.qq)

    def negated(self) -> Value:
        return Value(-self.iv, self.d, self.e, -self.a, -self.b,
                     None if self.const is None else -self.const, -self.qq)

    def scaled(self, c: float) -> Value:
        """c * self for a value without monomial part (d = e = 0); c rounded into a, b, qq."""
        return Value(self.iv * Interval.point(c), a=c * self.a, b=c * self.b,
                     const=None if self.const is None else c * self.const, qq=c * self.qq)


class Cells(abc.ABC):
    """The cells of a reduced domain: enclosures of lam^d, tau^e, a sigma + b x and the
    variables of the potential (``HaarCells``, ``LebesgueCells``)."""

    @abc.abstractmethod
    def lam_power(self, d: float) -> Interval:
        """Enclosure of lam^d on each cell."""

    @abc.abstractmethod
    def tau_power(self, e: float) -> Interval:
        """Enclosure of tau^e on each cell."""

    @abc.abstractmethod
    def linear(self, a: float, b: float, qq: float = 0.0) -> Interval:
        """Enclosure of qq sigma^2 + a sigma + b x on each cell."""

    @abc.abstractmethod
    def variables(self) -> dict[str, Value]:
        """The potential's variables on the cells."""

    def flatten(self, v: Value) -> Interval:
        """The plain interval enclosing v on each cell."""
        if v.d or v.e:
            out = v.iv
            if v.d:
                out = out * self.lam_power(v.d)
            if v.e:
                out = out * self.tau_power(v.e)
            return out
        if v.structured:
            return v.iv + self.linear(v.a, v.b, v.qq)
        return v.iv


class HaarCells(Cells):
    """n = 2 affine models: cells [x_lo, x_hi] x [sigma_lo, sigma_hi], x = q1 - q2 >= 0,
    sigma = q1 + q2; lam = e^(sigma/2), tau = e^(x/2)."""

    def __init__(self, x_lo, x_hi, s_lo, s_hi):
        self.x = Interval(np.asarray(x_lo, float), np.asarray(x_hi, float))
        self.s = Interval(np.asarray(s_lo, float), np.asarray(s_hi, float))

    @staticmethod
    def _exp_power(iv: Interval, c: float) -> Interval:
        """exp(c t / 2) for t in iv."""
        with np.errstate(over="ignore", invalid="ignore"):
            a = np.exp(0.5 * c * iv.lo)
            b = np.exp(0.5 * c * iv.hi)
        return Interval.make(np.minimum(a, b), np.maximum(a, b), ulps=2)

    def lam_power(self, d):
        return self._exp_power(self.s, d)

    def tau_power(self, e):
        return self._exp_power(self.x, e)

    def linear(self, a, b, qq=0.0):
        return quadratic_range(self.s, qq, a) + (self.x * Interval.point(b))

    def variables(self):
        half = 0.5
        one = Interval.point(1.0)
        two_cosh = lambda k: self.x.even(lambda t: 2 * np.cosh(k * t))  # noqa: E731
        out = {
            "q1": Value(Interval.point(0.0), a=half, b=half),
            "q2": Value(Interval.point(0.0), a=half, b=-half),
            "Q1": Value(one, d=1, e=1),
            "Q2": Value(one, d=1, e=-1),
            "trG": Value(two_cosh(1.0), d=2),
            "det": Value(one, d=2),
        }
        for k in (1, 2):
            out[f"K{k}"] = Value(two_cosh(float(k)), d=2 * k)
        return out


class LebesgueCells(Cells):
    """n = 2 d'Alembert: r1 = |z| = rho cos(theta), r2 = |w| = rho sin(theta), cells
    [rho_lo, rho_hi] x [theta_lo, theta_hi] in [0, inf] x [0, pi/2]; Q_1 = rho (cos + sin),
    Q_2 = rho (cos - sin) (lam = rho)."""

    def __init__(self, r_lo, r_hi, t_lo, t_hi):
        self.r = Interval(np.asarray(r_lo, float), np.asarray(r_hi, float))
        self.t = Interval(np.asarray(t_lo, float), np.asarray(t_hi, float))

    def lam_power(self, d):
        if float(d).is_integer():
            return self.r.integer_power(int(d))
        return self.r.real_power(d)

    def tau_power(self, e):
        raise AssertionError("no tau in the d'Alembert cells")

    def linear(self, a, b, qq=0.0):
        raise AssertionError("no linear forms in the d'Alembert cells")

    def variables(self):
        shift = Interval.point(math.pi / 4)
        root2 = Interval.point(math.sqrt(2.0))
        c1 = root2 * (self.t + shift).periodic(np.sin, 0.0)  # cos + sin = sqrt2 sin(t + pi/4)
        c2 = root2 * (self.t + shift).periodic(np.cos, math.pi / 2)
        log_r = self.r.increasing(np.log, 0.0)
        out = {
            "Q1": Value(c1, d=1),
            "Q2": Value(c2, d=1),
            "q1": Value(log_r + c1.even(np.abs).increasing(np.log, 0.0)),
            "q2": Value(log_r + c2.even(np.abs).increasing(np.log, 0.0)),
            "trG": Value(Interval.point(2.0), d=2),
            "det": Value((self.t * Interval.point(2.0)).periodic(np.cos, math.pi / 2), d=2),
        }
        for k in (1, 2):
            out[f"K{k}"] = Value(c1.integer_power(2 * k) + c2.integer_power(2 * k), d=2 * k)
        return out


class Lebesgue3Cells(Cells):
    """n = 3 d'Alembert: Q = rho (cos theta, sin theta cos psi, sin theta sin psi), cells
    [rho_lo, rho_hi] x [theta_lo, theta_hi] x [psi_lo, psi_hi] covering the chamber Q_1 >= Q_2
    >= |Q_3| (theta in [0, arctan sqrt 2], psi in [-pi/4, pi/4]; a cover of it is enough for
    lower bounds); lam = rho."""

    def __init__(self, r_lo, r_hi, t_lo, t_hi, p_lo, p_hi):
        self.r = Interval(np.asarray(r_lo, float), np.asarray(r_hi, float))
        self.t = Interval(np.asarray(t_lo, float), np.asarray(t_hi, float))
        self.p = Interval(np.asarray(p_lo, float), np.asarray(p_hi, float))

    def lam_power(self, d):
        """rho^d, rho >= 0 (d < 0: [rho_hi^d, rho_lo^d], infinite at rho_lo = 0)."""
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            a, b = self.r.lo ** float(d), self.r.hi ** float(d)
        a, b = np.where(np.isnan(a), 1.0, a), np.where(np.isnan(b), 1.0, b)  # 0^0, inf^0
        return Interval.make(np.minimum(a, b), np.maximum(a, b), ulps=2)

    def tau_power(self, e):
        raise AssertionError("no tau in the d'Alembert cells")

    def linear(self, a, b, qq=0.0):
        raise AssertionError("no linear forms in the d'Alembert cells")

    def variables(self):
        sin_t = self.t.periodic(np.sin, 0.0)
        omega = [self.t.periodic(np.cos, math.pi / 2), sin_t * self.p.periodic(np.cos, math.pi / 2),
                 sin_t * self.p.periodic(np.sin, 0.0)]
        log_r = self.r.increasing(np.log, 0.0)
        out = {"trG": Value(Interval.point(1.0), d=2),
               "det": Value(omega[0] * omega[1] * omega[2], d=3)}
        for a in range(3):
            out[f"Q{a + 1}"] = Value(omega[a], d=1)
            out[f"q{a + 1}"] = Value(log_r + omega[a].even(np.abs).increasing(np.log, 0.0))
        for k in (1, 2, 3):
            total = omega[0].integer_power(2 * k)
            for a in (1, 2):
                total = total + omega[a].integer_power(2 * k)
            out[f"K{k}"] = Value(total, d=2 * k)
        return out


class Haar3Cells(Cells):
    """n = 3 affine models: q = (sigma/3)(1, 1, 1) + r (cos t e_u + sin t e_v), e_u = (1, -1,
    0)/sqrt2, e_v = (1, 1, -2)/sqrt6 (the chamber q_1 > q_2 > q_3 is t in [pi/6, pi/2]), cells
    [r_lo, r_hi] x [t_lo, t_hi] x [sigma_lo, sigma_hi]; q_a - sigma/3 = r sqrt(2/3) sin(t +
    phase_a), phases pi/3, -pi/3, pi; lam = e^(sigma/3), so Q_a = lam e^(q_a - sigma/3) and
    det = lam^3 exactly. The linear forms are a sigma + b (r cos t, r sin t) + [interval] with
    a complex ``b`` (real part: the coefficient of r cos t, imaginary: of r sin t), so q_a =
    sigma/3 + r (e_u[a] + i e_v[a]) exactly and q_1 + q_2 + q_3 = sigma (the coefficients
    cancel exactly in float64: e_v[2] = -2 e_v[0])."""

    PHASES = (math.pi / 3, -math.pi / 3, math.pi)

    def __init__(self, r_lo, r_hi, t_lo, t_hi, s_lo, s_hi):
        self.r = Interval(np.asarray(r_lo, float), np.asarray(r_hi, float))
        self.t = Interval(np.asarray(t_lo, float), np.asarray(t_hi, float))
        self.s = Interval(np.asarray(s_lo, float), np.asarray(s_hi, float))

    def lam_power(self, d):
        with np.errstate(over="ignore", invalid="ignore"):
            a = np.exp(d * self.s.lo / 3)
            b = np.exp(d * self.s.hi / 3)
        return Interval.make(np.minimum(a, b), np.maximum(a, b), ulps=2)

    def tau_power(self, e):
        raise AssertionError("no tau in the n = 3 affine cells")

    def linear(self, a, b, qq=0.0):
        out = quadratic_range(self.s, qq, a)
        if b:  # r |b| sin(t + arg), arg = atan2(Re b, Im b)
            wave = (self.t + Interval.point(math.atan2(b.real, b.imag))).periodic(np.sin, 0.0)
            out = out + Interval.point(abs(b)) * self.r * wave
        return out

    def shear(self, a: int) -> Interval:
        """q_a - sigma/3 on each cell."""
        wave = (self.t + Interval.point(self.PHASES[a])).periodic(np.sin, 0.0)
        return Interval.point(math.sqrt(2.0 / 3.0)) * self.r * wave

    def variables(self):
        y = [self.shear(a) for a in range(3)]
        out = {"det": Value(Interval.point(1.0), d=3)}
        cu, cv = 1 / math.sqrt(2.0), 1 / math.sqrt(6.0)
        for a, b in enumerate((complex(cu, cv), complex(-cu, cv), complex(0.0, -2 * cv))):
            out[f"q{a + 1}"] = Value(Interval.point(0.0), a=1.0 / 3.0, b=b)
            out[f"Q{a + 1}"] = Value(y[a].increasing(np.exp), d=1)
        for k in (1, 2, 3):
            total = (y[0] * Interval.point(2.0 * k)).increasing(np.exp)
            for a in (1, 2):
                total = total + (y[a] * Interval.point(2.0 * k)).increasing(np.exp)
            out[f"K{k}"] = Value(total, d=2 * k)
        out["trG"] = out["K1"]
        return out


# ------------------------------------------------------------------------------ evaluator
class Unsupported(ValueError):
    """The expression uses something the enclosure does not cover."""


_INCREASING = {
    "exp": (np.exp, -np.inf, np.inf), "log": (np.log, 0.0, np.inf),
    "log1p": (np.log1p, -1.0, np.inf), "expm1": (np.expm1, -np.inf, np.inf),
    "sqrt": (np.sqrt, 0.0, np.inf), "cbrt": (np.cbrt, -np.inf, np.inf),
    "arcsin": (np.arcsin, -1.0, 1.0), "asin": (np.arcsin, -1.0, 1.0),
    "arctan": (np.arctan, -np.inf, np.inf), "atan": (np.arctan, -np.inf, np.inf),
    "sinh": (np.sinh, -np.inf, np.inf), "tanh": (np.tanh, -np.inf, np.inf),
    "arcsinh": (np.arcsinh, -np.inf, np.inf), "asinh": (np.arcsinh, -np.inf, np.inf),
    "arccosh": (np.arccosh, 1.0, np.inf), "acosh": (np.arccosh, 1.0, np.inf),
    "arctanh": (np.arctanh, -1.0, 1.0), "atanh": (np.arctanh, -1.0, 1.0),
}
_DECREASING = {"arccos": (np.arccos, -1.0, 1.0), "acos": (np.arccos, -1.0, 1.0)}


class Enclosure:
    """Evaluates the syntax tree of a potential on :class:`Cells` (module docstring)."""

    def __init__(self, cells: Cells):
        self.cells = cells
        self.vars = cells.variables()

    def plain(self, v: Value) -> Interval:
        return self.cells.flatten(v)

    def eval(self, node: ast.AST) -> Value:
        if isinstance(node, ast.Expression):
            return self.eval(node.body)
        if isinstance(node, ast.Constant):
            c = float(node.value)
            return Value(Interval.point(c), const=c)
        if isinstance(node, ast.Name):
            if node.id in self.vars:
                return self.vars[node.id]
            if node.id in CONSTANTS:
                c = float(CONSTANTS[node.id])
                return Value(Interval.point(c), const=c)
            raise Unsupported(f"variable {node.id!r}")
        if isinstance(node, ast.UnaryOp):
            v = self.eval(node.operand)
            if isinstance(node.op, ast.UAdd):
                return v
            return v.negated()
        if isinstance(node, ast.BinOp):
            return self.binary(node)
        if isinstance(node, ast.Call):
            return self.call(node)
        raise Unsupported(type(node).__name__)

    def binary(self, node: ast.BinOp) -> Value:
        x, y = self.eval(node.left), self.eval(node.right)
        op = node.op
        if isinstance(op, (ast.Add, ast.Sub)):
            if isinstance(op, ast.Sub):
                y = y.negated()
            if (x.d, x.e) == (y.d, y.e):  # same monomial, or two linear forms: exact
                return Value(x.iv + y.iv, x.d, x.e, x.a + y.a, x.b + y.b, qq=x.qq + y.qq)
            if x.d == y.d and x.d:  # lam^d (tau^e1 I1 + tau^e2 I2)
                fx = x.iv * self.cells.tau_power(x.e) if x.e else x.iv
                fy = y.iv * self.cells.tau_power(y.e) if y.e else y.iv
                return Value(fx + fy, x.d)
            return Value(self.plain(x) + self.plain(y))
        if isinstance(op, ast.Mult):
            if x.const is not None or y.const is not None:
                c, v = (x.const, y) if x.const is not None else (y.const, x)
                if (v.d, v.e) == (0, 0):
                    return v.scaled(c)
            if x.structured or y.structured:
                return Value(self.plain(x) * self.plain(y))
            return Value(x.iv * y.iv, x.d + y.d, x.e + y.e)
        if isinstance(op, ast.Div):
            if y.const is not None and y.const != 0 and (x.d, x.e) == (0, 0):
                c = 1.0 / y.const  # rounded: the form coefficients carry 1e-16 relative error
                return Value(x.iv / y.iv, a=c * x.a, b=c * x.b,
                             const=None if x.const is None else x.const / y.const, qq=c * x.qq)
            if x.structured or y.structured:
                return Value(self.plain(x) / self.plain(y))
            return Value(x.iv / y.iv, x.d - y.d, x.e - y.e)
        if isinstance(op, ast.Pow):
            if y.const is None:  # x^y = exp(y log x), x > 0
                base = self.plain(x)
                return Value((self.plain(y) * base.increasing(np.log, 0.0)).increasing(np.exp))
            m = y.const
            if m == 2 and x.structured and not (x.b or x.qq) and _uniform_point(x.iv):
                c0 = float(np.ravel(x.iv.lo)[0])  # (a sigma + c0)^2, exactly as a form
                return Value(Interval.point(c0 * c0), a=2 * x.a * c0, qq=x.a * x.a)
            if x.structured:
                x = Value(self.plain(x))
            if float(m).is_integer() and abs(m) <= 256:
                return Value(x.iv.integer_power(int(m)), x.d * m, x.e * m)
            return Value(x.iv.real_power(m), x.d * m, x.e * m)  # lam, tau > 0
        raise Unsupported(type(op).__name__)

    def call(self, node: ast.Call) -> Value:
        name = node.func.id
        args = [self.eval(a) for a in node.args]
        if name == "abs" and len(args) == 1:
            v = args[0]
            if v.structured:
                return Value(self.plain(v).even(np.abs))
            return Value(v.iv.even(np.abs), v.d, v.e)  # lam, tau > 0
        if name == "square":
            v = args[0]
            if v.structured:
                v = Value(self.plain(v))
            return Value(v.iv.integer_power(2), 2 * v.d, 2 * v.e)
        if name == "sqrt" and not args[0].structured:
            v = args[0]
            return Value(v.iv.increasing(np.sqrt, 0.0), v.d / 2, v.e / 2)
        ivs = [self.plain(v) for v in args]
        if name in _INCREASING:
            fn, lo, hi = _INCREASING[name]
            out = ivs[0].increasing(fn, lo, hi)
            if name in ("exp", "sqrt"):  # >= 0: the outward widening must not cross 0, where
                # a factor lam^d = inf on an unbounded cell would turn it into -inf
                out = Interval(np.maximum(out.lo, 0.0), out.hi)
            return Value(out)
        if name in _DECREASING:
            fn, lo, hi = _DECREASING[name]
            return Value(ivs[0].decreasing(fn, lo, hi))
        if name == "cosh":
            return Value(ivs[0].even(np.cosh))
        if name == "sin":
            return Value(ivs[0].periodic(np.sin, 0.0))
        if name == "cos":
            return Value(ivs[0].periodic(np.cos, math.pi / 2))
        if name in ("min", "minimum"):
            return Value(ivs[0].minimum(ivs[1]))
        if name in ("max", "maximum"):
            return Value(ivs[0].maximum(ivs[1]))
        raise Unsupported(f"function {name}()")


def summands(node: ast.AST, sign: int = 1) -> list[tuple[int, ast.AST]]:
    """The top-level terms of a sum, with their signs (a - (b + c) -> +a, -b, -c)."""
    if isinstance(node, ast.Expression):
        return summands(node.body, sign)
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub)):
        right = -sign if isinstance(node.op, ast.Sub) else sign
        return summands(node.left, sign) + summands(node.right, right)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        return summands(node.operand, -sign if isinstance(node.op, ast.USub) else sign)
    return [(sign, node)]


def lower_bounds(text: str, cells: Cells, extra: Value | None = None) -> np.ndarray:
    """Certified lower bounds of the potential ``text`` (plus ``extra``, a value of degree 0,
    e.g. -kappa (sigma - c)^2) on each cell (-inf where none).

    The top-level terms are grouped by their monomial lam^d tau^e and summed exactly within a
    group (degree 0 keeps its sigma form); the groups are combined per cell by the larger of
    the plain sum of their enclosures and, on cells with lam >= lam_lo > 0, the dominant-degree
    bound: sum_d c_d lam^d >= lam^D [c_D + sum_(d<D) min(0, c_d) lam_lo^(d-D)] (D the highest
    degree; a negative bracket gives bracket * lam_hi^D). So a double well
    Q^4 - Q^2 stays bounded on the unbounded cells. Where the coefficients of the degrees above
    some D are all >= 0 on a cell, those terms are >= 0 and D may serve as the dominant degree
    (e.g. (Q1 - Q2)^4 vanishing on the cell's edge Q1 = Q2 while the degree-2 terms confine):
    the best such D per cell.

    Raises :class:`Unsupported` when the expression uses a function the enclosure does not
    cover (tan, arctan2, ...)."""
    enc = Enclosure(cells)
    groups: dict[tuple[float, float], Value] = {}
    terms = [(1, extra)] if extra is not None else []
    tree = ast.parse(text.strip(), mode="eval")
    terms += [(sign, enc.eval(node)) for sign, node in summands(tree)]
    for sign, v in terms:
        v = v if sign > 0 else v.negated()
        key = (v.d, v.e)
        if key in groups:
            g = groups[key]
            v = Value(g.iv + v.iv, g.d, g.e, g.a + v.a, g.b + v.b, qq=g.qq + v.qq)
        groups[key] = v
    by_degree: dict[float, Interval] = {}
    for (d, e), v in groups.items():
        part = cells.flatten(v) if d == 0 else (v.iv * cells.tau_power(e) if e else v.iv)
        by_degree[d] = by_degree[d] + part if d in by_degree else part
    total = None
    for d, c in by_degree.items():
        term = c if d == 0 else c * cells.lam_power(d)
        total = term if total is None else total + term
    lower = np.asarray(total.lo, float)
    degrees = sorted(by_degree)
    if degrees[-1] > 0 and len(degrees) > 1:
        lam = cells.lam_power(1.0)
        lam_lo, lam_hi = np.asarray(lam.lo, float), np.asarray(lam.hi, float)
        safe = np.where(lam_lo > 0, lam_lo, 1.0)
        dropped = np.ones(lam_lo.shape, bool)  # every degree above ``top`` has c_d >= 0 there
        for i in range(len(degrees) - 1, -1, -1):
            top = degrees[i]
            if top <= 0:
                break
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                bracket = np.asarray(by_degree[top].lo, float)
                for d in degrees[:i]:
                    bracket = bracket + np.minimum(0.0, by_degree[d].lo) * safe ** (d - top)
                bracket = _down(bracket, 4)
                bound = np.where(bracket >= 0, bracket * _down(safe**top, 2),
                                 bracket * _up(lam_hi**top, 2))
            bound = np.where(np.isnan(bound) | (lam_lo <= 0) | ~dropped, -np.inf, bound)
            lower = np.maximum(lower, bound)
            dropped &= np.asarray(by_degree[top].lo, float) >= 0
    return np.where(np.isnan(lower), -np.inf, lower)


def evaluate(text: str, cells: Cells) -> Value:
    """The structured enclosure of the potential ``text`` on ``cells`` (:class:`Value`)."""
    return Enclosure(cells).eval(ast.parse(text.strip(), mode="eval"))


@dataclass(frozen=True)
class ExpressionPotential:
    """A potential given as an expression in the invariants (names of
    :func:`invariant_names`), callable on Q [..., n] like any :data:`Potential`; its ``text``
    lets :mod:`affinebody.quantum.bounds` certify lower bounds of V."""

    text: str
    n: int
    field: str = "quantum.potential"

    def __post_init__(self):
        expr = compile_expression(self.text, invariant_names(self.n), field=self.field)
        object.__setattr__(self, "_expr", expr)

    def __call__(self, Q: np.ndarray) -> np.ndarray:
        Q = np.asarray(Q, float)
        values = invariant_values(Q)
        expr = self._expr
        out = np.asarray(expr(**{k: values[k] for k in expr.used}), float)
        return np.broadcast_to(out, Q.shape[:-1])


def invariant_values(Q: np.ndarray) -> dict[str, np.ndarray]:
    """The values of :func:`invariant_names` at signed singular values Q [..., n]: q_a =
    ln |Q_a|, Q_a, K_a = Tr G^a = sum Q^(2a), trG, det = prod Q."""
    Q = np.asarray(Q, float)
    G2 = Q * Q
    values = {}
    with np.errstate(divide="ignore"):
        for a in range(Q.shape[-1]):
            values[f"q{a + 1}"] = np.log(np.abs(Q[..., a]))
            values[f"Q{a + 1}"] = Q[..., a]
            values[f"K{a + 1}"] = np.sum(G2 ** (a + 1), axis=-1)
    values["trG"] = np.sum(G2, axis=-1)
    values["det"] = np.prod(Q, axis=-1)
    return values


def invariant_names(n: int) -> tuple[str, ...]:
    """Variables of a potential expression: q1..qn, Q1..Qn, trG, K1..Kn, det."""
    return (tuple(f"q{a}" for a in range(1, n + 1)) + tuple(f"Q{a}" for a in range(1, n + 1))
            + ("trG",) + tuple(f"K{a}" for a in range(1, n + 1)) + ("det",))


__all__ = ["Interval", "Value", "Cells", "HaarCells", "LebesgueCells", "Lebesgue3Cells",
           "Haar3Cells", "Enclosure",
           "Unsupported", "lower_bounds", "evaluate", "summands", "quadratic_range",
           "ExpressionPotential", "invariant_values", "invariant_names"]
