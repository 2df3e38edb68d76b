"""The built-in potentials: generic one-body (57) and pair (59) potentials of any function or
config expression, and the families (80), (81) (dilatation), St Venant-Kirchhoff (32), external
fields (58), Lennard-Jones, Morse, Gaussian in r or D (75), harmonic invariants (60)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from affinebody import _pytree as pytree
from affinebody.expressions import CompiledExpression, compile_expression
from affinebody.potentials.terms import (
    Cutoff,
    OneBodyTerm,
    PairTerm,
    box_field,
    cutoff_field,
    positive_parameter,
    real_parameter,
    real_tuple_parameter,
)
from affinebody.potentials.variables import (
    check_variable_names,
    one_body_variable_names,
    pair_variable_names,
)
from affinebody.space import Space


def _argument(owner: str) -> Any:
    """The field ``argument`` ('r' or 'D') of a pair family named ``owner``."""

    def convert(value):
        if value not in ("r", "D"):
            raise ValueError(f"{owner}.argument must be 'r' or 'D' (got {value!r})")
        return value

    return pytree.field(default="r", converter=convert)


def _number(check, name: str) -> Any:
    """A required field converted by ``check(value, name)`` (e.g. ``positive_parameter``)."""
    return pytree.field(converter=lambda value: check(value, name))


def _optional(check, name: str, default=None) -> Any:
    """An optional field converted by ``check(value, name)`` unless it is None."""
    return pytree.field(
        default=default, converter=lambda v: None if v is None else check(v, name))



# --------------------------------------------------------------------------------------------
# Generic potentials (any JAX function or a config expression)


def _callable(owner: str):
    def convert(function):
        if not callable(function):
            raise ValueError(f"{owner}.function must be callable")
        return function

    return convert


def _names(owner: str, *, pair: bool):
    def convert(names):
        names = (names,) if isinstance(names, str) else names
        return check_variable_names(tuple(names), owner, pair=pair)

    return convert


@pytree.dataclass(static=True)
class OneBodyPotential(OneBodyTerm):
    """``V = sum_K f(**variables_K)``: any one-body potential V(x, phi) (57), e.g. an elastic
    energy in the invariants K_a, I_a or E, a dilatation potential of ``det`` (80), (81), an
    external field in ``x``. ``function`` takes the named variables as keyword arguments
    (arrays with a leading body axis) and must be JAX-traceable."""

    function: Callable[..., jax.Array] = pytree.field(converter=_callable("OneBodyPotential"))
    variables: tuple[str, ...] = pytree.field(
        converter=_names("OneBodyPotential", pair=False))


    def term(self, values):
        return self.function(**{name: values[name] for name in self.variables})

    @classmethod
    def from_expression(cls, text: str, n: int, *, field: str = "expr") -> OneBodyPotential:
        """One-body potential from a config expression in :func:`one_body_variable_names`."""
        expression = compile_expression(text, one_body_variable_names(n), field=field)
        return cls(expression, expression.used)


@pytree.dataclass(static=True)
class PairPotential(PairTerm):
    """``V = sum_{K<L} f(**variables_KL)``: any binary potential (61), (62), (77), (78), e.g.
    ``f(r, D, K1, ..., M1, ..., det)``. ``function`` takes the named variables as keyword
    arguments (arrays with a leading pair axis) and must be JAX-traceable."""

    function: Callable[..., jax.Array] = pytree.field(converter=_callable("PairPotential"))
    variables: tuple[str, ...] = pytree.field(converter=_names("PairPotential", pair=True))
    cutoff: Cutoff | None = cutoff_field("PairPotential")
    box: tuple[float, ...] | Space | None = box_field("PairPotential")


    def term(self, values):
        return self.function(**{name: values[name] for name in self.variables})

    @property
    def expression(self) -> CompiledExpression | None:
        """f as a config expression (:meth:`from_expression`), or None for a Python function:
        the host pair kernel compiles an expression's f and its partials with the geometry
        (``pair_kernels``)."""
        return self.function if isinstance(self.function, CompiledExpression) else None

    @classmethod
    def from_expression(
        cls,
        text: str,
        n: int,
        *,
        cutoff: Cutoff | None = None,
        box: Sequence[float] | Space | None = None,
        field: str = "expr",
    ) -> PairPotential:
        """Pair potential from a config expression in :func:`pair_variable_names`."""
        expression = compile_expression(text, pair_variable_names(n), field=field)
        if not expression.used:
            raise ValueError(
                f"config error: {field}: a pair expression must depend on the pair's "
                f"variables (r, D, det, K1.., M1.., ...; got the constant {text!r}): a "
                f"constant per pair is a step at the cut-off; for no pair interaction leave "
                f"the term out")
        if box is not None and not isinstance(box, Space):
            box = tuple(tuple(row) if isinstance(row, Sequence) else row for row in box)
        return cls(expression, expression.used, cutoff, box)


# --------------------------------------------------------------------------------------------
# Built-in one-body families


@pytree.dataclass(static=True)
class Dilatation(OneBodyTerm):
    """Dilatation-stabilising potential V = sum_K f(det phi_K), eqs. (80), (81).

    ``form="log"``: f = (k/2) ln(|det phi| / v0)^2 (diverges at collapse and at infinite
    expansion); ``form="harmonic"``: f = (k/2) (det phi - v0)^2. Its gradient is
    f'(det) det(phi) phi^-T (docs/theory/exact-flows.md, "Gradients of the invariants").
    """

    stiffness: float = _number(positive_parameter, "dilatation.stiffness")
    volume: float = _optional(positive_parameter, "dilatation.volume", 1.0)
    form: str = "log"
    variables = ("det",)

    def __post_init__(self):
        if self.form not in ("log", "harmonic"):
            raise ValueError(f"dilatation.form must be 'log' or 'harmonic' (got {self.form!r})")

    def term(self, values):
        det = values["det"]
        if self.form == "log":
            return 0.5 * self.stiffness * jnp.log(jnp.abs(det) / self.volume) ** 2
        return 0.5 * self.stiffness * (det - self.volume) ** 2


@pytree.dataclass(static=True)
class StVenantKirchhoff(OneBodyTerm):
    """Elastic energy in the Lagrange strain E = (G - Id)/2 (32):
    V = sum_K [lam/2 (Tr E)^2 + mu Tr(E^2)], positive definite for mu > 0, lam + 2 mu / n > 0."""

    lam: float = _number(real_parameter, "elastic.lam")
    mu: float = _number(positive_parameter, "elastic.mu")
    variables = ("E1", "E2")

    def check_dimension(self, n: int) -> None:
        if n == 1:  # E2 = Tr(E^2) is not a variable of its own there (it is E1^2)
            raise ValueError(
                f"elastic is for n >= 2; in one dimension the same energy is kind = "
                f"\"one-body\" with expr = \"{0.5 * self.lam + self.mu:.17g}*E1**2\" "
                f"((lam/2 + mu) (Tr E)^2)")
        if not self.lam + 2.0 * self.mu / n > 0:  # E = eps Id must cost energy
            raise ValueError(
                f"elastic needs lam + 2 mu / n > 0 in n = {n} (got lam={self.lam}, mu={self.mu})"
            )

    def term(self, values):
        return 0.5 * self.lam * values["E1"] ** 2 + self.mu * values["E2"]


@pytree.dataclass(static=True)
class ExternalHarmonic(OneBodyTerm):
    """External harmonic trap V = sum_K (k/2) |x_K - c|^2 (a translational term of (58))."""

    stiffness: float = _number(positive_parameter, "external-harmonic.stiffness")
    centre: tuple[float, ...] | None = _optional(real_tuple_parameter, "external-harmonic.centre")
    variables = ("x",)

    def check_dimension(self, n: int) -> None:
        if self.centre is not None and len(self.centre) != n:
            raise ValueError(f"external-harmonic.centre must have n = {n} components")

    def term(self, values):
        x = values["x"]
        centre = jnp.zeros(x.shape[-1]) if self.centre is None else jnp.asarray(self.centre)
        return 0.5 * self.stiffness * jnp.sum((x - centre) ** 2, axis=-1)


@pytree.dataclass(static=True)
class ExternalLinear(OneBodyTerm):
    """Uniform external force F on every centre: V = -sum_K F . x_K (e.g. gravity)."""

    force: tuple[float, ...] = _number(real_tuple_parameter, "external-linear.force")
    variables = ("x",)

    def check_dimension(self, n: int) -> None:
        if len(self.force) != n:
            raise ValueError(f"external-linear.force must have n = {n} components")

    def term(self, values):
        x = values["x"]
        return -jnp.sum(x * jnp.asarray(self.force), axis=-1)


# --------------------------------------------------------------------------------------------
# Built-in pair families


def _family_expression(owner: str, text: str, argument: str,
                       **numbers: float) -> CompiledExpression:
    """A family's f as a config expression in its argument (r or D), ``text`` with each
    ``{name}`` replaced by the parenthesised value of ``numbers[name]``: what the host pair
    kernel compiles with the geometry (the fused kernel), as it does for ``kind = "pair"``."""
    values = {name: f"({float(value)!r})" for name, value in numbers.items()}
    return compile_expression(text.format(s=argument, **values), (argument,),
                              field=f"{owner} (as an expression)")


@pytree.dataclass(static=True)
class LennardJones(PairTerm):
    """V_KL = 4 eps ((sigma/s)^12 - (sigma/s)^6), s = r or the affine distance D (75);
    minimum -eps at s = 2^(1/6) sigma."""

    epsilon: float = _number(positive_parameter, "lennard-jones.epsilon")
    sigma: float = _number(positive_parameter, "lennard-jones.sigma")
    argument: str = _argument("lennard-jones")
    cutoff: Cutoff | None = cutoff_field("LennardJones")
    box: tuple[float, ...] | Space | None = box_field("LennardJones")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        q6 = (self.sigma / values[self.argument]) ** 6
        return 4.0 * self.epsilon * (q6 * q6 - q6)

    @property
    def expression(self) -> CompiledExpression:
        """:meth:`term` as a config expression (:func:`_family_expression`)."""
        return _family_expression("lennard-jones", "4*{eps}*(({sigma}/{s})**12 - ({sigma}/{s})**6)",
                                  self.argument, eps=self.epsilon, sigma=self.sigma)


@pytree.dataclass(static=True)
class Morse(PairTerm):
    """V_KL = depth ((1 - exp(-alpha (s - r0)))^2 - 1), s = r or D; minimum -depth at s = r0."""

    depth: float = _number(positive_parameter, "morse.depth")
    alpha: float = _number(positive_parameter, "morse.alpha")
    r0: float = _number(positive_parameter, "morse.r0")
    argument: str = _argument("morse")
    cutoff: Cutoff | None = cutoff_field("Morse")
    box: tuple[float, ...] | Space | None = box_field("Morse")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        decay = jnp.exp(-self.alpha * (values[self.argument] - self.r0))
        return self.depth * ((1.0 - decay) ** 2 - 1.0)

    @property
    def expression(self) -> CompiledExpression:
        """:meth:`term` as a config expression (:func:`_family_expression`)."""
        return _family_expression("morse", "{depth}*((1 - exp(-{alpha}*({s} - {r0})))**2 - 1)",
                                  self.argument, depth=self.depth, alpha=self.alpha, r0=self.r0)


@pytree.dataclass(static=True)
class Gaussian(PairTerm):
    """V_KL = amplitude exp(-s^2 / (2 width^2)), s = r or D (amplitude < 0: attraction)."""

    amplitude: float = _number(real_parameter, "gaussian.amplitude")
    width: float = _number(positive_parameter, "gaussian.width")
    argument: str = _argument("gaussian")
    cutoff: Cutoff | None = cutoff_field("Gaussian")
    box: tuple[float, ...] | Space | None = box_field("Gaussian")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        s = values[self.argument]
        return self.amplitude * jnp.exp(-(s**2) / (2.0 * self.width**2))

    @property
    def expression(self) -> CompiledExpression:
        """:meth:`term` as a config expression (:func:`_family_expression`)."""
        return _family_expression("gaussian", "{amplitude}*exp(-{s}**2/(2*{width}**2))",
                                  self.argument, amplitude=self.amplitude, width=self.width)


def _invariants(value: str) -> str:
    if value not in ("M", "K"):
        raise ValueError(f"harmonic-invariants.invariants must be 'M' or 'K' (got {value!r})")
    return value


@pytree.dataclass(static=True)
class HarmonicInvariants(PairTerm):
    """Internal binary term (60): V_KL = (k/2) sum_a (X_a - X0_a)^2 with X = M[phi_K, phi_L]
    (30) (affine, ``invariants="M"``) or X = K[phi_K, phi_L] (28) (Euclidean, ``"K"``);
    ``reference`` X0 defaults to n for every a (the value at phi_K = phi_L = Id). Distance
    enters only through an optional cut-off."""

    stiffness: float = _number(positive_parameter, "harmonic-invariants.stiffness")
    invariants: str = pytree.field(default="M", converter=_invariants)
    reference: tuple[float, ...] | None = _optional(
        real_tuple_parameter, "harmonic-invariants.reference")
    cutoff: Cutoff | None = cutoff_field("HarmonicInvariants")
    box: tuple[float, ...] | Space | None = box_field("HarmonicInvariants")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.invariants,)

    def check_dimension(self, n: int) -> None:
        super().check_dimension(n)
        if self.reference is not None and len(self.reference) != n:
            raise ValueError(f"harmonic-invariants.reference must have n = {n} entries")

    def term(self, values):
        x = values[self.invariants]
        n = x.shape[-1]
        ref = jnp.full(n, float(n)) if self.reference is None else jnp.asarray(self.reference)
        return 0.5 * self.stiffness * jnp.sum((x - ref) ** 2, axis=-1)


__all__ = [
    "Dilatation", "ExternalHarmonic", "ExternalLinear", "Gaussian", "HarmonicInvariants",
    "LennardJones", "Morse", "OneBodyPotential", "PairPotential", "StVenantKirchhoff",
]
