"""The engine of the potentials: the term interface, cut-off, sums and forces.

``AbstractPotentialTerm`` and its two kinds, ``OneBodyTerm`` (57) and ``PairTerm`` (59), turn a
function of named variables (:mod:`affinebody.potentials.variables`) into an energy of N bodies;
``PairTerm`` also holds the contract with :mod:`affinebody.pair_kernels` (scalar requirements,
asymmetry, energies from the pair scalars). :class:`Cutoff` and :func:`switching` give the C^2
cut-off, :class:`TotalPotential` the sum (56), :func:`generalized_forces` the forces.
The package docstring (``affinebody.potentials``) describes the variables and symmetries.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _pytree as pytree
from affinebody._checks import as_matrix, as_vector
from affinebody.mutual import affine_invariants
from affinebody.potentials.variables import (
    ALL_SYMMETRIES,
    check_variable_indices,
    one_body_symmetry,
    one_body_variables,
    pair_symmetry,
    pair_variables,
    uses_indexed,
)
from affinebody.space import Space, as_space


def _masked_pair_value(name: str, value: jax.Array, n: int, r_cut: float) -> jax.Array:
    """Harmless stand-in for a masked pair: identity configurations at the cut-off distance."""
    if name in ("r", "D"):
        return jnp.full_like(value, r_cut)
    if name == "det":
        return jnp.ones_like(value)
    return jnp.full_like(value, float(n))  # K_a, M_a of two identities


# --------------------------------------------------------------------------------------------
# Cut-off


def switching(s: jax.Array, r_on: float, r_cut: float) -> jax.Array:
    """C^2 quintic switch: 1 for s <= r_on, 1 - t^3 (10 - 15 t + 6 t^2) with
    t = (s - r_on)/(r_cut - r_on) in between, 0 for s >= r_cut (first and second derivatives
    vanish at both ends)."""
    t = jnp.clip((s - r_on) / (r_cut - r_on), 0.0, 1.0)
    return 1.0 - t**3 * (10.0 - 15.0 * t + 6.0 * t**2)


@pytree.dataclass(static=True)
class Cutoff:
    """Smooth cut-off of a pair potential in ``variable`` (``"r"`` or ``"D"``).

    The pair energy is multiplied by :func:`switching` (``r_on``, ``r_cut``); ``r_on`` defaults
    to ``0.9 * r_cut``. Energy and forces are exactly zero for ``variable >= r_cut``.
    """

    r_cut: float = pytree.field(converter=lambda v: positive_parameter(v, "cutoff.r_cut"))
    r_on: float | None = pytree.field(
        default=None, converter=lambda v: None if v is None else real_parameter(v, "cutoff.r_on"))
    variable: str = "r"

    def __post_init__(self):
        if self.r_on is None:
            pytree.initialize(self, r_on=0.9 * self.r_cut)
        if not 0 <= self.r_on < self.r_cut:
            raise ValueError(f"cutoff.r_on must satisfy 0 <= r_on < r_cut "
                             f"(got {self.r_on}, {self.r_cut})")
        if self.variable not in ("r", "D"):
            raise ValueError(f"cutoff.variable must be 'r' or 'D' (got {self.variable!r})")


def real_parameter(value: Any, name: str) -> float:
    """float(value); ValueError naming ``name`` unless a finite real number (a traced JAX value
    too: a potential is static data, docs/tutorials/autodiff.md)."""
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"{name} must be a number, not a traced JAX value: the parameters of "
                         f"the built-in potentials are static; to differentiate with respect "
                         f"to one, write the term as a Python function that closes over it "
                         f"(OneBodyPotential, PairPotential; docs/tutorials/autodiff.md)")
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ValueError(f"{name} must be a real number (got {value!r})")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite (got {value})")
    return value


def positive_parameter(value: Any, name: str) -> float:
    """float(value); ValueError naming ``name`` unless finite and > 0."""
    value = real_parameter(value, name)
    if not value > 0:
        raise ValueError(f"{name} must be > 0 (got {value})")
    return value


def real_tuple_parameter(value: Any, name: str) -> tuple[float, ...]:
    """A tuple of finite reals; ValueError naming ``name`` (and the entry) otherwise."""
    if isinstance(value, str) or not isinstance(value, Sequence | np.ndarray):
        raise ValueError(f"{name} must be a list of numbers (got {value!r})")
    return tuple(real_parameter(v, f"{name}[{i}]") for i, v in enumerate(value))


# --------------------------------------------------------------------------------------------
# Engines shared by all potentials


def _coordinates(x, phi) -> tuple[jax.Array, jax.Array]:
    phi = as_matrix(phi, "phi")
    x = as_vector(x, "x", phi.shape[-1])
    if phi.ndim < 3 or x.shape[:-1] != phi.shape[:-2]:
        raise ValueError(
            f"x [..., N, n] and phi [..., N, n, n] must agree (got {x.shape} and {phi.shape})"
        )
    return x, phi


class AbstractPotentialTerm(abc.ABC):
    """One term of the potential V (56): a function of named variables (``affinebody.potentials``).

    A term is a static ``_pytree.dataclass`` (hashable: it enters compiled functions as data
    of the treedef) that declares ``variables``, the names its function ``term`` takes; its
    ``symmetry`` follows from them (:func:`one_body_symmetry`, :func:`pair_symmetry`), so a
    declaration cannot be wrong. ``energy(x [..., N, n], phi [..., N, n, n]) -> [...]`` is the
    total over bodies (one-body terms) or unordered pairs (pair terms).
    """

    variables: tuple[str, ...]

    @abc.abstractmethod
    def term(self, values: Mapping[str, jax.Array]) -> jax.Array:
        """f of each body (or pair) from its named variables (arrays [..., N] or [..., P])."""

    @abc.abstractmethod
    def energy(self, x, phi) -> jax.Array:
        """Total energy of the term, shape [...]."""

    @property
    @abc.abstractmethod
    def symmetry(self) -> frozenset[str]:
        """The symmetries (``SYMMETRIES`` labels) the term has, inferred from its variables."""

    def check_dimension(self, n: int) -> None:
        """ValueError if the parameters do not fit dimension n (overridden where needed)."""
        return None  # a hook: most families fit every n


class OneBodyTerm(AbstractPotentialTerm):
    """``energy = sum_K f(variables of body K)``, eq. (57). Subclasses define
    ``variables`` (names) and ``term(values) -> [..., N]``."""

    def body_energies(self, x, phi) -> jax.Array:
        """Energy of each body, shape [..., N]."""
        x, phi = _coordinates(x, phi)
        check_variable_indices(self.variables, phi.shape[-1], type(self).__name__)
        self.check_dimension(phi.shape[-1])
        values = one_body_variables(self.variables, x, phi)
        return jnp.broadcast_to(self.term(values), phi.shape[:-2])

    def energy(self, x, phi) -> jax.Array:
        """Total one-body energy, shape [...]."""
        return jnp.sum(self.body_energies(x, phi), axis=-1)

    @property
    def symmetry(self) -> frozenset[str]:
        return one_body_symmetry(self.variables)


class PairTerm(AbstractPotentialTerm):
    """``energy = sum_{K<L} V_KL``, eq. (59), with optional cut-off and periodic box.
    Subclasses define ``variables``, ``cutoff``, ``box`` and ``term(values) -> [..., P]``.

    The contract with :mod:`affinebody.pair_kernels`: :meth:`scalar_requirements` (which
    scalar pair variables f needs), :attr:`asymmetric` (whether f is averaged over both
    orders of a pair), :meth:`energy_from_scalars` (the pair energies from those scalars,
    elementwise, so that its gradient gives the per-pair partial derivatives) and
    :attr:`expression` (f as a config expression, which the host kernel compiles with the
    geometry, or None)."""

    cutoff: Cutoff | None
    box: tuple[float, ...] | Space | None

    def check_dimension(self, n: int) -> None:
        """ValueError if the parameters do not fit dimension n (overridden where needed)."""
        if self.box is not None and self.space.dimension != n:
            raise ValueError(
                f"box has {self.space.dimension} edges but the dimension is n = {n}"
            )

    @property
    def space(self) -> Space:
        """The space of the centres: free, or the periodic box ``box`` (package docstring)."""
        return as_space(self.box)

    def __post_init__(self):
        """A periodic box needs a cut-off on r within half its perpendicular width."""
        owner = type(self).__name__
        if self.box is None:
            return
        if self.cutoff is None or self.cutoff.variable != "r":
            raise ValueError(
                f"{owner}: a periodic box needs a cut-off on r (set r_cut <= half the box)"
            )
        limit = self.space.max_cutoff
        if self.cutoff.r_cut > limit * (1 + 1e-12):
            raise ValueError(
                f"{owner}: r_cut = {self.cutoff.r_cut} exceeds half the shortest box edge "
                f"(perpendicular width) {limit}: the minimum image would miss images in range"
            )

    @property
    def expression(self):
        """f as a config expression (``affinebody.expressions.CompiledExpression``) in
        :attr:`variables`, or None (here): where it is one, the host pair kernel compiles f
        and its partials with the geometry and the chain rule in one loop (the fused kernel
        of :mod:`affinebody.pair_kernels`); otherwise XLA evaluates f between two host calls."""
        return None

    @property
    def _needed(self) -> frozenset[str]:
        extra = {self.cutoff.variable} if self.cutoff is not None else set()
        return frozenset(self.variables) | extra

    @property
    def asymmetric(self) -> bool:
        """True when f uses det Gamma (79) or M_a (30), which change under K <-> L
        (Gamma[phi_L, phi_K] = Gamma[phi_K, phi_L]^-1): f is then averaged over both orders."""
        return "det" in self.variables or uses_indexed(self.variables, "M")

    def scalar_requirements(self, n: int) -> tuple[frozenset[str], int, int]:
        """What :meth:`energy_from_scalars` needs in dimension n: the plain scalars among
        r, D, det, and the highest powers k, m of K_a (28) and M_a (30) used (0: none)."""
        names = self._needed
        plain = frozenset(names & {"r", "D", "det"})
        powers = []
        for letter in "KM":
            used = [int(name[1:]) for name in names
                    if uses_indexed([name], letter) and name != letter]
            powers.append(n if letter in names else max(used, default=0))
        return plain, powers[0], powers[1]

    def energy_from_scalars(self, base: Mapping[str, jax.Array], n: int) -> jax.Array:
        """Pair energies [..., P] from the scalar pair variables: ``base`` holds r, D, det
        [..., P] and K, M, Ms [..., P, k or m] (K_a[phi_K, phi_L], M_a[phi_K, phi_L] and
        M_a[phi_L, phi_K], a = 1..k or m) as :meth:`scalar_requirements` asks.

        Applies the average over both orders of an asymmetric pair (eq. (59) with one f; the
        swapped det Gamma is 1/det), the cut-off mask and the switch. Elementwise over pairs,
        so its gradient with respect to ``base`` is the per-pair partial derivatives
        (``pair_kernels`` uses exactly this)."""
        values = {name: base[name] for name in ("r", "D", "det") if name in base}
        for letter in "KM":
            if letter in base:
                array = base[letter]
                values[letter] = array
                for a in range(array.shape[-1]):
                    values[f"{letter}{a + 1}"] = array[..., a]
        swapped = None
        if "Ms" in base:
            swapped = {"M": base["Ms"]}
            for a in range(base["Ms"].shape[-1]):
                swapped[f"M{a + 1}"] = base["Ms"][..., a]
        return self.energy_from_values(values, swapped, n)

    @property
    def columnwise(self) -> bool:
        """Whether f reads only scalars of each pair (r, D, det, K1.., M1..), not a whole array
        K or M: then :meth:`energy_from_values` runs on one vector per scalar, as the GPU pair
        kernel that evaluates f does (``affinebody._pair_triton``)."""
        return not {"K", "M"} & set(self.variables)

    def energy_from_values(self, values: Mapping[str, jax.Array],
                           swapped_m: Mapping[str, jax.Array] | None, n: int) -> jax.Array:
        """:meth:`energy_from_scalars` from the variables by name: ``values`` maps r, D, det,
        K1.., M1.. (and K, M where f reads the whole array) to arrays [..., P] (K, M
        [..., P, k or m]); ``swapped_m``: the M entries of the swapped order M_a[phi_L,
        phi_K] by the same names, where :attr:`asymmetric` f uses M, else None."""
        orders = [values]
        if self.asymmetric:  # average f over (K, L) and (L, K): eq. (59) with a single f
            swapped = dict(values)
            if "det" in values:
                swapped["det"] = 1.0 / values["det"]
            if swapped_m is not None:
                swapped.update(swapped_m)
            orders.append(swapped)
        if self.cutoff is None:
            energies = [self.term(v) for v in orders]
            return sum(energies) / len(energies)
        s = values[self.cutoff.variable]
        inside = s < self.cutoff.r_cut
        switch = switching(s, self.cutoff.r_on, self.cutoff.r_cut)
        total = 0.0
        for v in orders:
            safe = {}
            for name, value in v.items():
                mask = inside.reshape(inside.shape + (1,) * (value.ndim - inside.ndim))
                safe[name] = jnp.where(
                    mask, value, _masked_pair_value(name, value, n, self.cutoff.r_cut)
                )
            # beyond the cut-off 0 x s: 0 with gradient 0, but NaN for a NaN s (which fails
            # s < r_cut and read as a pair beyond the cut-off)
            total = total + jnp.where(inside, self.term(safe) * switch, 0.0 * s)
        return total / len(orders)

    def pair_energies(self, x, phi, cell=None) -> jax.Array:
        """Energies of the unordered pairs K < L (order of ``numpy.triu_indices``), [..., P].

        cell: None, or the current cell matrix [n, n] of a box that a barostat deforms (may be
        traced; :meth:`affinebody.space.Space.displacement`)."""
        x, phi = _coordinates(x, phi)
        n, bodies = phi.shape[-1], phi.shape[-3]
        check_variable_indices(self.variables, n, type(self).__name__)
        self.check_dimension(n)
        k, l = np.triu_indices(bodies, 1)
        u = self.space.displacement(x[..., k, :], x[..., l, :], cell)
        return self.bond_energies(u, phi[..., k, :, :], phi[..., l, :, :])

    def bond_energies(self, u, phi_k, phi_l) -> jax.Array:
        """Energies V_KL [..., P] of pairs given by their displacements u = x_K - x_L
        [..., P, n] (already the image in range) and shapes phi_K, phi_L [..., P, n, n]:
        computes only the scalars :meth:`scalar_requirements` asks for, then
        :meth:`energy_from_scalars` (cut-off and switch included)."""
        n = phi_k.shape[-1]
        plain, k_powers, m_powers = self.scalar_requirements(n)
        names = plain | ({"K"} if k_powers else set()) | ({"M"} if m_powers else set())
        values = pair_variables(names, u, phi_k, phi_l)
        base = {name: values[name] for name in plain}
        if k_powers:
            base["K"] = values["K"][..., :k_powers]
        if m_powers:
            base["M"] = values["M"][..., :m_powers]
            if self.asymmetric:
                base["Ms"] = affine_invariants(phi_l, phi_k)[..., :m_powers]
        return self.energy_from_scalars(base, n)

    def energy(self, x, phi, neighbors=None, cell=None) -> jax.Array:
        """Total pair energy sum_{K<L} V_KL, shape [...] (0 for a single body).

        With a ``neighbors`` list (:mod:`affinebody.neighbors`) the sum runs over its pairs
        only, through the closed-form kernel of :mod:`affinebody.pair_kernels` (its gradient
        is that kernel's, not autodiff through the geometry); the list must cover every pair
        within the cut-off (``neighbors.check``). ``cell``: as in :meth:`pair_energies` (with a
        list: one built in that cell, ``neighbors.build(spec, x, phi, cell)``)."""
        if neighbors is not None:
            from affinebody.pair_kernels import neighbor_energy

            x, phi = _coordinates(x, phi)
            return neighbor_energy(self, x, phi, neighbors, cell)
        return jnp.sum(self.pair_energies(x, phi, cell), axis=-1)

    @property
    def symmetry(self) -> frozenset[str]:
        return pair_symmetry(self._needed, periodic=self.box is not None)


def cutoff_field(owner: str) -> Any:
    """The field ``cutoff`` of a pair term named ``owner``: None or a :class:`Cutoff`."""

    def convert(value):
        if value is not None and not isinstance(value, Cutoff):
            raise ValueError(f"{owner}.cutoff must be a Cutoff (got {value!r})")
        return value

    return pytree.field(default=None, converter=convert)


def box_field(owner: str) -> Any:
    """The field ``box`` of a pair term named ``owner``: None, n positive edges
    (orthorhombic), an n x n cell matrix (triclinic) or an ``affinebody.space.Space``."""

    def convert(box):
        if box is None:
            return None
        if isinstance(box, Sequence) and all(not isinstance(b, Sequence) for b in box):
            return tuple(positive_parameter(b, f"{owner}.box[{i}]") for i, b in enumerate(box))
        return as_space(box)  # a Space or an n x n cell matrix (triclinic)

    return pytree.field(default=None, converter=convert)


# --------------------------------------------------------------------------------------------
# Sums and forces


@pytree.dataclass(static=True)
class TotalPotential:
    """Sum of potentials, eq. (56); its symmetry is the intersection of the terms'."""

    terms: tuple[Any, ...]

    def energy(self, x, phi, neighbors=None, cell=None) -> jax.Array:
        """Sum of the terms' energies; ``neighbors`` and ``cell`` go to the pair terms (see
        :meth:`PairTerm.energy`)."""
        x, phi = _coordinates(x, phi)
        total = jnp.zeros(phi.shape[:-3])
        for term in self.terms:
            if (neighbors is not None or cell is not None) and isinstance(term, PairTerm):
                total = total + term.energy(x, phi, neighbors, cell)
            else:
                total = total + term.energy(x, phi)
        return total

    @property
    def symmetry(self) -> frozenset[str]:
        sym = ALL_SYMMETRIES
        for term in self.terms:
            sym = sym & term.symmetry
        return frozenset(sym)


def terms_of(potential) -> tuple[Any, ...]:
    """The terms of ``potential``: those of a :class:`TotalPotential`, the potential itself
    otherwise, none for None."""
    if potential is None:
        return ()
    return potential.terms if isinstance(potential, TotalPotential) else (potential,)


def total_potential(potentials: Iterable[Any]) -> TotalPotential:
    """The sum V = V^(1) + V^(2) (56) of the given potentials (nested sums are flattened)."""
    terms: list[Any] = []
    for pot in potentials:
        if isinstance(pot, TotalPotential):
            terms.extend(pot.terms)
        elif callable(getattr(pot, "energy", None)) and hasattr(pot, "symmetry"):
            terms.append(pot)
        else:
            raise ValueError(f"{pot!r} is not a potential (needs .energy and .symmetry)")
    return TotalPotential(tuple(terms))


class NoNeighborRange(ValueError):
    """The pair terms cannot share one neighbour list; ``index`` is the offending term's
    position in the sequence given to :func:`neighbor_range` (None: no pair term at all)."""

    def __init__(self, message: str, index: int | None):
        super().__init__(message)
        self.index = index


def neighbor_range(terms) -> tuple[Any, float, str]:
    """(space, cutoff, variable) that one neighbour list must cover for the pair terms among
    ``terms`` (a potential, or a sequence of terms): all pair terms need a cut-off on the same
    variable ("r", or "D" of eq. (75)) in the same space (free or one periodic box), and the
    list covers the largest cut-off. The one rule for "can this system use a list?" (the
    system's ``neighbor_range`` and the config's checks apply it); :class:`NoNeighborRange`
    says why not."""
    if isinstance(terms, TotalPotential):
        terms = terms.terms
    elif not isinstance(terms, list | tuple):
        terms = (terms,)
    pairs = [(k, t) for k, t in enumerate(terms) if isinstance(t, PairTerm)]
    if not pairs:
        raise NoNeighborRange("a neighbour list needs pair potentials of affinebody.potentials "
                              "(PairTerm, alone or in a TotalPotential); this system has none: "
                              "run without neighbors", None)
    for k, t in pairs:
        if t.cutoff is None:
            raise NoNeighborRange(
                f"a neighbour list needs a cut-off on every pair term ({type(t).__name__} has "
                f"none): give it cutoff=potentials.Cutoff(r_cut) or run without neighbors", k)
    variables = {t.cutoff.variable for _, t in pairs}
    spaces = {t.space for _, t in pairs}
    if len(variables) > 1 or len(spaces) > 1:
        raise NoNeighborRange("one neighbour list serves pair terms with cut-offs on the same "
                              "variable (r or D) in the same space; these differ: run without "
                              "neighbors", pairs[-1][0])
    return spaces.pop(), max(float(t.cutoff.r_cut) for _, t in pairs), variables.pop()


def generalized_forces(potential, x, phi) -> tuple[jax.Array, jax.Array]:
    """(-dV/dx, -dV/dphi), shaped like x and phi (summed energy over leading batch axes,
    which are independent systems). The momentum equations are dp/dt = -dV/dx and
    dpi/dt = -(dV/dphi)^T in the paper's placement of pi (docs/theory/conventions.md)."""
    x, phi = _coordinates(x, phi)
    return _negative_gradient(potential, x, phi)


@pytree.compiled_for_models
def _negative_gradient(potential, x, phi):
    gx, gphi = jax.grad(lambda a, b: jnp.sum(potential.energy(a, b)), argnums=(0, 1))(x, phi)
    return -gx, -gphi


__all__ = [
    "AbstractPotentialTerm", "Cutoff", "NoNeighborRange", "OneBodyTerm", "PairTerm",
    "TotalPotential", "box_field", "cutoff_field", "generalized_forces", "neighbor_range",
    "positive_parameter", "real_parameter", "real_tuple_parameter", "switching", "terms_of",
    "total_potential",
]
