"""Potential energies of N affine bodies: one-body (57), (58), (80), (81) and binary (59)-(62),
(77), (78) terms, with forces and torques by automatic differentiation.

Every potential is a small frozen (hashable) dataclass with

- ``pot.energy(x [..., N, n], phi [..., N, n, n]) -> [...]`` the total energy, summed over
  bodies and over unordered pairs;
- ``pot.symmetry``: a frozenset of the symmetries it has (see below), inferred from the
  variables it depends on, so a declaration cannot be wrong;

and :func:`total_potential` adds several. Generalised forces are ``-jax.grad`` of the energy
(:func:`generalized_forces`); note ``dV/dphi`` has the shape of ``phi``
(docs/theory/conventions.md: Hamilton's equation is ``dpi/dt = -(dV/dphi)^T``).

One-body potentials (57) are sums over bodies of ``f(variables)`` where the variables are
(``n`` the dimension, ``a = 1..n``):

==========  ================================================================================
``x1..xn``  components of the centre x (an external field breaks translations)
``det``     det phi (volume ratio; the dilatation potentials (80), (81))
``trG``     Tr G[phi] = K1
``K1..Kn``  K_a[phi] = Tr(G^a), G = phi^T phi, eq. (17)
``I1..In``  characteristic invariants of G, eq. (19)
``E1..En``  Tr(E^a) of the Lagrange strain E = (G - Id)/2, eq. (32)
==========  ================================================================================

and, for Python callables only, the arrays ``x`` [n], ``phi`` [n, n], ``K``, ``I`` [n] and
``E`` [n, n]. The separable form (58) is the sum of a term in ``x`` and a term in ``phi``.

Pair potentials are ``V = sum_{K<L} V_KL``, which is the paper's ``1/2 sum_{K != L}`` (59) when
``V_KL`` is symmetric in (K, L); variables that are not symmetric (``M_a`` and ``det``, since
``Gamma[phi_L, phi_K] = Gamma[phi_K, phi_L]^-1``) are handled by averaging ``f`` over both orders,
which is exactly (59) with one function ``f`` for all pairs. The variables of (61), (62), (77),
(78) are

==========  ================================================================================
``r``       |x_K - x_L| (minimum image in a periodic box)
``D``       the affine distance of (75), sqrt(u^T (C[phi_K] + C[phi_L])/2 u), u = x_K - x_L
``det``     relative volume det Gamma[phi_K, phi_L] = det phi_L / det phi_K, eq. (79)
``K1..Kn``  K_a[phi_K, phi_L] = Tr((phi_K^T phi_L)^a), eq. (28)
``M1..Mn``  M_a[phi_K, phi_L] = Tr((phi_K^-1 phi_L)^a), eq. (30)
==========  ================================================================================

(callables may also take the arrays ``K`` and ``M`` [n]). The separable form (60) is the sum of a
pair potential in ``r`` and one in ``K``/``M``/``det``.

Symmetries (the strings shared with :mod:`affinebody.kinetic`). Each names a group acting on all
bodies at once; Euclidean means proper rotations R in SO(n) (a potential of ``det`` is not
invariant under reflections):

=======================  =====================================================================
``translation``          x_K -> x_K + b
``spatial-euclidean``    (x_K, phi_K) -> (R x_K, R phi_K)
``spatial-affine``       (x_K, phi_K) -> (A x_K, A phi_K), A in GL(n)  (76)
``material-euclidean``   phi_K -> phi_K R
``material-affine``      phi_K -> phi_K B, B in GL(n)  (27), (31)
=======================  =====================================================================

``r`` and ``K_a`` break spatial affine symmetry, ``D`` and ``K_a`` break material affine
symmetry, ``M_a`` and ``det Gamma`` keep all of them (31), (79): functions of ``D`` and ``M_a``
only are the purely affine binary models (78). By Noether's theorem a spatially affine potential
has ``sum_K [x_K (dV/dx_K)^T + phi_K (dV/dphi_K)^T] = 0``, a materially affine one
``sum_K phi_K^T dV/dphi_K = 0``, a translation-invariant one ``sum_K dV/dx_K = 0``.

Cut-off: a pair potential may carry a :class:`Cutoff` on ``r`` or ``D``: the pair energy is
multiplied by the C^2 quintic switch ``S`` (1 below ``r_on``, 0 from ``r_cut`` on) and is exactly
zero, with exactly zero gradient, at and beyond ``r_cut``. A periodic ``box`` (n edges of an
orthorhombic box, an n x n cell matrix of a triclinic one, or an :class:`affinebody.space.Space`)
uses the minimum image and requires a cut-off on ``r`` of at most half the smallest perpendicular
width (the shortest edge if orthorhombic), so that the minimum image is the only image in range;
a box breaks the spatial rotations.

Large N: ``energy(x, phi, neighbors)`` sums over the pairs of a neighbour list
(:mod:`affinebody.neighbors`) with the closed-form force kernel of :mod:`affinebody.pair_kernels`;
without a list the sum runs over all N(N-1)/2 pairs.

NaN-free gradients: ``r`` and ``D`` use the double-``where`` square root (gradient 0 at 0), pairs
beyond the cut-off are evaluated at a harmless reference point (identity configurations at the
cut-off distance) before masking, and the diagonal K = L is never formed (pairs K < L only).
"""

from __future__ import annotations

import abc
import dataclasses
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg
from affinebody import _pytree as pytree
from affinebody._checks import as_matrix, as_vector
from affinebody.deformation import (
    characteristic_from_traces,
    green_tensor,
    lagrange_strain,
    matrix_power_traces,
)
from affinebody.expressions import compile_expression
from affinebody.mutual import (
    affine_distance,
    affine_invariants,
    mutual_trace_invariants,
    relative_volume,
)
from affinebody.space import Space, as_space

SYMMETRIES = (
    "translation",
    "spatial-euclidean",
    "spatial-affine",
    "material-euclidean",
    "material-affine",
)
_ALL = frozenset(SYMMETRIES)
_INDEXED = re.compile(r"^(x|K|I|E|M)([1-9][0-9]*)$")


# --------------------------------------------------------------------------------------------
# Variable names


def one_body_variable_names(n: int) -> tuple[str, ...]:
    """Scalar variables a one-body expression may use in dimension ``n``."""
    idx = range(1, n + 1)
    return (
        *(f"x{a}" for a in idx),
        "det",
        "trG",
        *(f"K{a}" for a in idx),
        *(f"I{a}" for a in idx),
        *(f"E{a}" for a in idx),
    )


def pair_variable_names(n: int) -> tuple[str, ...]:
    """Scalar variables a pair expression may use in dimension ``n``."""
    idx = range(1, n + 1)
    return ("r", "D", "det", *(f"K{a}" for a in idx), *(f"M{a}" for a in idx))


_ONE_BODY_ARRAYS = frozenset({"x", "phi", "K", "I", "E"})
_PAIR_ARRAYS = frozenset({"K", "M"})


def _check_names(names: Sequence[str], owner: str, *, pair: bool) -> tuple[str, ...]:
    """Refuse variable names outside the one-body or pair vocabulary (index range is checked
    against n when the energy is evaluated)."""
    plain = {"r", "D", "det"} if pair else {"det", "trG"}
    arrays = _PAIR_ARRAYS if pair else _ONE_BODY_ARRAYS
    letters = "KM" if pair else "xKIE"
    for name in names:
        m = _INDEXED.match(name)
        if name in plain or name in arrays or (m and m.group(1) in letters):
            continue
        kind = "pair" if pair else "one-body"
        example = "r, D, det, K1, M1, K, M" if pair else "x1, det, trG, K1, I1, E1, x, phi, E"
        raise ValueError(f"{owner}: unknown {kind} variable {name!r} (allowed e.g. {example})")
    if len(set(names)) != len(names):
        raise ValueError(f"{owner}: variables {tuple(names)} contain duplicates")
    return tuple(names)


def _check_indices(names: Iterable[str], n: int, owner: str) -> None:
    for name in names:
        m = _INDEXED.match(name)
        if m and int(m.group(2)) > n:
            raise ValueError(f"{owner}: variable {name!r} does not exist in dimension n = {n}")


def _indexed(names: Iterable[str], letter: str) -> bool:
    return any(
        name == letter or (len(name) > 1 and name[0] == letter and name[1:].isdigit())
        for name in names
    )


def one_body_symmetry(names: Iterable[str]) -> frozenset[str]:
    """Symmetries of a one-body potential depending on the given variables (module docstring)."""
    names = set(names)
    sym = set(_ALL)
    if _indexed(names, "x"):
        sym -= {"translation", "spatial-euclidean", "spatial-affine"}
    if "phi" in names:
        sym -= {"spatial-euclidean", "spatial-affine", "material-euclidean", "material-affine"}
    if "E" in names:
        sym -= {"spatial-affine", "material-euclidean", "material-affine"}
    if names & {"det", "trG"} or any(_indexed(names, c) for c in "KIE"):
        sym -= {"spatial-affine", "material-affine"}
    return frozenset(sym)


def pair_symmetry(names: Iterable[str], *, periodic: bool = False) -> frozenset[str]:
    """Symmetries of a pair potential depending on the given variables (module docstring)."""
    names = set(names)
    sym = set(_ALL)
    uses_k = _indexed(names, "K")
    if periodic:
        sym -= {"spatial-euclidean", "spatial-affine"}
    if "r" in names or uses_k:
        sym -= {"spatial-affine"}
    if "D" in names or uses_k:
        sym -= {"material-affine"}
    return frozenset(sym)


# --------------------------------------------------------------------------------------------
# Evaluation of the variables


def _safe_norm(u: jax.Array) -> jax.Array:
    """|u| over the last axis with gradient 0 (not NaN) at u = 0 (double-where)."""
    s2 = jnp.sum(u * u, axis=-1)
    positive = s2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, s2, 1.0)), 0.0)


def one_body_variables(names: Iterable[str], x: jax.Array, phi: jax.Array) -> dict[str, jax.Array]:
    """The requested one-body variables per body, shapes [..., N] (or [..., N, n(, n)])."""
    names = set(names)
    n = phi.shape[-1]
    out: dict[str, jax.Array] = {}
    if "x" in names:
        out["x"] = x
    if "phi" in names:
        out["phi"] = phi
    for a in range(n):
        if f"x{a + 1}" in names:
            out[f"x{a + 1}"] = x[..., a]
    if "det" in names:
        out["det"] = linalg.det(phi)
    if names & {"trG", "K", "I"} or _indexed(names, "K") or _indexed(names, "I"):
        k = matrix_power_traces(green_tensor(phi), n)
        out["K"], out["trG"] = k, k[..., 0]
        out["I"] = characteristic_from_traces(k)
        for a in range(n):
            out[f"K{a + 1}"], out[f"I{a + 1}"] = k[..., a], out["I"][..., a]
    if _indexed(names, "E"):
        strain = lagrange_strain(phi)
        out["E"] = strain
        traces = matrix_power_traces(strain, n)
        for a in range(n):
            out[f"E{a + 1}"] = traces[..., a]
    return out


def pair_variables(
    names: Iterable[str], u: jax.Array, phi_k: jax.Array, phi_l: jax.Array
) -> dict[str, jax.Array]:
    """The requested pair variables for separations ``u = x_K - x_L`` [..., P, n] and
    configurations ``phi_k``, ``phi_l`` [..., P, n, n]; scalars have shape [..., P]."""
    names = set(names)
    n = phi_k.shape[-1]
    out: dict[str, jax.Array] = {}
    if "r" in names:
        out["r"] = _safe_norm(u)
    if "D" in names:
        out["D"] = affine_distance(u, phi_k, jnp.zeros_like(u), phi_l)
    if "det" in names:
        out["det"] = relative_volume(phi_k, phi_l)
    if _indexed(names, "K"):
        out["K"] = mutual_trace_invariants(phi_k, phi_l)
        for a in range(n):
            out[f"K{a + 1}"] = out["K"][..., a]
    if _indexed(names, "M"):
        out["M"] = affine_invariants(phi_k, phi_l)
        for a in range(n):
            out[f"M{a + 1}"] = out["M"][..., a]
    return out


def _pair_reference(name: str, value: jax.Array, n: int, r_cut: float) -> jax.Array:
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

    r_cut: float = pytree.field(converter=lambda v: _positive(v, "cutoff.r_cut"))
    r_on: float | None = pytree.field(
        default=None, converter=lambda v: None if v is None else _real(v, "cutoff.r_on"))
    variable: str = "r"

    def __post_init__(self):
        if self.r_on is None:
            pytree.initialize(self, r_on=0.9 * self.r_cut)
        if not 0 <= self.r_on < self.r_cut:
            raise ValueError(f"cutoff.r_on must satisfy 0 <= r_on < r_cut "
                             f"(got {self.r_on}, {self.r_cut})")
        if self.variable not in ("r", "D"):
            raise ValueError(f"cutoff.variable must be 'r' or 'D' (got {self.variable!r})")


def _real(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ValueError(f"{name} must be a real number (got {value!r})")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite (got {value})")
    return value


def _positive(value: Any, name: str) -> float:
    value = _real(value, name)
    if not value > 0:
        raise ValueError(f"{name} must be > 0 (got {value})")
    return value


def _real_tuple(value: Any, name: str) -> tuple[float, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence | np.ndarray):
        raise ValueError(f"{name} must be a list of numbers (got {value!r})")
    return tuple(_real(v, f"{name}[{i}]") for i, v in enumerate(value))


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
    """One term of the potential V (56): a function of named variables (module docstring).

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
        _check_indices(self.variables, phi.shape[-1], type(self).__name__)
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
    orders of a pair) and :meth:`energy_from_scalars` (the pair energies from those scalars,
    elementwise, so that its gradient gives the per-pair partial derivatives)."""

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
        """The space of the centres: free, or the periodic box ``box`` (module docstring)."""
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
    def _needed(self) -> frozenset[str]:
        extra = {self.cutoff.variable} if self.cutoff is not None else set()
        return frozenset(self.variables) | extra

    @property
    def asymmetric(self) -> bool:
        """True when f uses det Gamma (79) or M_a (30), which change under K <-> L
        (Gamma[phi_L, phi_K] = Gamma[phi_K, phi_L]^-1): f is then averaged over both orders."""
        return "det" in self.variables or _indexed(self.variables, "M")

    def scalar_requirements(self, n: int) -> tuple[frozenset[str], int, int]:
        """What :meth:`energy_from_scalars` needs in dimension n: the plain scalars among
        r, D, det, and the highest powers k, m of K_a (28) and M_a (30) used (0: none)."""
        names = self._needed
        plain = frozenset(names & {"r", "D", "det"})
        powers = []
        for letter in "KM":
            used = [int(name[1:]) for name in names if _indexed([name], letter) and name != letter]
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
        orders = [values]
        if self.asymmetric:  # average f over (K, L) and (L, K): eq. (59) with a single f
            swapped = dict(values)
            if "det" in values:
                swapped["det"] = 1.0 / values["det"]
            if "Ms" in base:
                swapped["M"] = base["Ms"]
                for a in range(base["Ms"].shape[-1]):
                    swapped[f"M{a + 1}"] = base["Ms"][..., a]
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
                    mask, value, _pair_reference(name, value, n, self.cutoff.r_cut)
                )
            total = total + jnp.where(inside, self.term(safe) * switch, 0.0)
        return total / len(orders)

    def pair_energies(self, x, phi) -> jax.Array:
        """Energies of the unordered pairs K < L (order of ``numpy.triu_indices``), [..., P]."""
        x, phi = _coordinates(x, phi)
        n, bodies = phi.shape[-1], phi.shape[-3]
        _check_indices(self.variables, n, type(self).__name__)
        self.check_dimension(n)
        k, l = np.triu_indices(bodies, 1)
        u = self.space.displacement(x[..., k, :], x[..., l, :])
        phi_k, phi_l = phi[..., k, :, :], phi[..., l, :, :]
        plain, k_powers, m_powers = self.scalar_requirements(n)
        values = pair_variables(plain | {"K", "M"} if k_powers or m_powers else plain,
                                u, phi_k, phi_l)
        base = {name: values[name] for name in plain}
        if k_powers:
            base["K"] = values["K"][..., :k_powers]
        if m_powers:
            base["M"] = values["M"][..., :m_powers]
            if self.asymmetric:
                base["Ms"] = affine_invariants(phi_l, phi_k)[..., :m_powers]
        return self.energy_from_scalars(base, n)

    def energy(self, x, phi, neighbors=None) -> jax.Array:
        """Total pair energy sum_{K<L} V_KL, shape [...] (0 for a single body).

        With a ``neighbors`` list (:mod:`affinebody.neighbors`) the sum runs over its pairs
        only, through the closed-form kernel of :mod:`affinebody.pair_kernels` (its gradient
        is that kernel's, not autodiff through the geometry); the list must cover every pair
        within the cut-off (``neighbors.check``)."""
        if neighbors is not None:
            from affinebody.pair_kernels import neighbor_energy

            x, phi = _coordinates(x, phi)
            return neighbor_energy(self, x, phi, neighbors)
        return jnp.sum(self.pair_energies(x, phi), axis=-1)

    @property
    def symmetry(self) -> frozenset[str]:
        return pair_symmetry(self._needed, periodic=self.box is not None)


def _argument(owner: str) -> Any:
    """The field ``argument`` ('r' or 'D') of a pair family named ``owner``."""

    def convert(value):
        if value not in ("r", "D"):
            raise ValueError(f"{owner}.argument must be 'r' or 'D' (got {value!r})")
        return value

    return pytree.field(default="r", converter=convert)


def _cutoff_field(owner: str) -> Any:
    def convert(value):
        if value is not None and not isinstance(value, Cutoff):
            raise ValueError(f"{owner}.cutoff must be a Cutoff (got {value!r})")
        return value

    return pytree.field(default=None, converter=convert)


def _box_field(owner: str) -> Any:
    """The field ``box``: None, n positive edges (orthorhombic), a cell matrix or a Space."""

    def convert(box):
        if box is None:
            return None
        if isinstance(box, Sequence) and all(not isinstance(b, Sequence) for b in box):
            return tuple(_positive(b, f"{owner}.box[{i}]") for i, b in enumerate(box))
        return as_space(box)  # a Space or an n x n cell matrix (triclinic)

    return pytree.field(default=None, converter=convert)


def _number(check, name: str) -> Any:
    """A required field converted by ``check(value, name)`` (_real, _positive, _real_tuple)."""
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
        return _check_names(tuple(names), owner, pair=pair)

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
    cutoff: Cutoff | None = _cutoff_field("PairPotential")
    box: tuple[float, ...] | Space | None = _box_field("PairPotential")


    def term(self, values):
        return self.function(**{name: values[name] for name in self.variables})

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

    stiffness: float = _number(_positive, "dilatation.stiffness")
    volume: float = _optional(_positive, "dilatation.volume", 1.0)
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

    lam: float = _number(_real, "elastic.lam")
    mu: float = _number(_positive, "elastic.mu")
    variables = ("E1", "E2")

    def check_dimension(self, n: int) -> None:
        if not self.lam + 2.0 * self.mu / n > 0:  # E = eps Id must cost energy
            raise ValueError(
                f"elastic needs lam + 2 mu / n > 0 in n = {n} (got lam={self.lam}, mu={self.mu})"
            )

    def term(self, values):
        return 0.5 * self.lam * values["E1"] ** 2 + self.mu * values["E2"]


@pytree.dataclass(static=True)
class ExternalHarmonic(OneBodyTerm):
    """External harmonic trap V = sum_K (k/2) |x_K - c|^2 (a translational term of (58))."""

    stiffness: float = _number(_positive, "external-harmonic.stiffness")
    centre: tuple[float, ...] | None = _optional(_real_tuple, "external-harmonic.centre")
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

    force: tuple[float, ...] = _number(_real_tuple, "external-linear.force")
    variables = ("x",)

    def check_dimension(self, n: int) -> None:
        if len(self.force) != n:
            raise ValueError(f"external-linear.force must have n = {n} components")

    def term(self, values):
        x = values["x"]
        return -jnp.sum(x * jnp.asarray(self.force), axis=-1)


# --------------------------------------------------------------------------------------------
# Built-in pair families


@pytree.dataclass(static=True)
class LennardJones(PairTerm):
    """V_KL = 4 eps ((sigma/s)^12 - (sigma/s)^6), s = r or the affine distance D (75);
    minimum -eps at s = 2^(1/6) sigma."""

    epsilon: float = _number(_positive, "lennard-jones.epsilon")
    sigma: float = _number(_positive, "lennard-jones.sigma")
    argument: str = _argument("lennard-jones")
    cutoff: Cutoff | None = _cutoff_field("LennardJones")
    box: tuple[float, ...] | Space | None = _box_field("LennardJones")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        q6 = (self.sigma / values[self.argument]) ** 6
        return 4.0 * self.epsilon * (q6 * q6 - q6)


@pytree.dataclass(static=True)
class Morse(PairTerm):
    """V_KL = depth ((1 - exp(-alpha (s - r0)))^2 - 1), s = r or D; minimum -depth at s = r0."""

    depth: float = _number(_positive, "morse.depth")
    alpha: float = _number(_positive, "morse.alpha")
    r0: float = _number(_positive, "morse.r0")
    argument: str = _argument("morse")
    cutoff: Cutoff | None = _cutoff_field("Morse")
    box: tuple[float, ...] | Space | None = _box_field("Morse")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        decay = jnp.exp(-self.alpha * (values[self.argument] - self.r0))
        return self.depth * ((1.0 - decay) ** 2 - 1.0)


@pytree.dataclass(static=True)
class Gaussian(PairTerm):
    """V_KL = amplitude exp(-s^2 / (2 width^2)), s = r or D (amplitude < 0: attraction)."""

    amplitude: float = _number(_real, "gaussian.amplitude")
    width: float = _number(_positive, "gaussian.width")
    argument: str = _argument("gaussian")
    cutoff: Cutoff | None = _cutoff_field("Gaussian")
    box: tuple[float, ...] | Space | None = _box_field("Gaussian")

    @property
    def variables(self) -> tuple[str, ...]:
        return (self.argument,)

    def term(self, values):
        s = values[self.argument]
        return self.amplitude * jnp.exp(-(s**2) / (2.0 * self.width**2))


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

    stiffness: float = _number(_positive, "harmonic-invariants.stiffness")
    invariants: str = pytree.field(default="M", converter=_invariants)
    reference: tuple[float, ...] | None = _optional(_real_tuple, "harmonic-invariants.reference")
    cutoff: Cutoff | None = _cutoff_field("HarmonicInvariants")
    box: tuple[float, ...] | Space | None = _box_field("HarmonicInvariants")

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


# --------------------------------------------------------------------------------------------
# Sums and forces


@pytree.dataclass(static=True)
class TotalPotential:
    """Sum of potentials, eq. (56); its symmetry is the intersection of the terms'."""

    terms: tuple[Any, ...]

    def energy(self, x, phi, neighbors=None) -> jax.Array:
        """Sum of the terms' energies; ``neighbors`` goes to the pair terms (see
        :meth:`PairTerm.energy`)."""
        x, phi = _coordinates(x, phi)
        total = jnp.zeros(phi.shape[:-3])
        for term in self.terms:
            if neighbors is not None and isinstance(term, PairTerm):
                total = total + term.energy(x, phi, neighbors)
            else:
                total = total + term.energy(x, phi)
        return total

    @property
    def symmetry(self) -> frozenset[str]:
        sym = _ALL
        for term in self.terms:
            sym = sym & term.symmetry
        return frozenset(sym)


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


def generalized_forces(potential, x, phi) -> tuple[jax.Array, jax.Array]:
    """(-dV/dx, -dV/dphi), shaped like x and phi (summed energy over leading batch axes,
    which are independent systems). The momentum equations are dp/dt = -dV/dx and
    dpi/dt = -(dV/dphi)^T in the paper's placement of pi (docs/theory/conventions.md)."""
    x, phi = _coordinates(x, phi)
    gx, gphi = jax.grad(lambda a, b: jnp.sum(potential.energy(a, b)), argnums=(0, 1))(x, phi)
    return -gx, -gphi


# --------------------------------------------------------------------------------------------
# Registry of config names


@dataclass(frozen=True)
class PotentialFamily:
    """A potential kind a config file can name: its parameters (name -> description)."""

    name: str
    kind: str  # "one-body" or "pair"
    summary: str
    parameters: Mapping[str, str]
    required: tuple[str, ...]
    build: Callable[[dict[str, Any], int, tuple[float, ...] | None], Any] = dataclasses.field(
        repr=False
    )


_CUTOFF_PARAMETERS = {
    "r_cut": "cut-off distance (optional; no cut-off if absent; required in a periodic box)",
    "r_on": "start of the C^2 switch (default 0.9 * r_cut)",
    "cutoff_on": "'r' or 'D': the variable the cut-off applies to (default: the argument, or r)",
}


def _cutoff_from(params: dict[str, Any], default: str) -> Cutoff | None:
    r_cut = params.pop("r_cut", None)
    r_on = params.pop("r_on", None)
    variable = params.pop("cutoff_on", default)
    if r_cut is None:
        if r_on is not None:
            raise ValueError("r_on given without r_cut")
        return None
    return Cutoff(r_cut, r_on, variable)


def _family_pair(cls):
    def build(params, n, box):
        argument = params.get("argument", "r")
        cutoff = _cutoff_from(params, argument if isinstance(argument, str) else "r")
        return cls(**params, cutoff=cutoff, box=box)

    return build


def _build_harmonic_invariants(params, n, box):
    cutoff = _cutoff_from(params, "r")
    return HarmonicInvariants(**params, cutoff=cutoff, box=box)


def _build_pair_expression(params, n, box):
    cutoff = _cutoff_from(params, "r")
    return PairPotential.from_expression(
        params.pop("expr"), n, cutoff=cutoff, box=box, field=params.pop("_field")
    )


def _build_one_body_expression(params, n, box):
    return OneBodyPotential.from_expression(params.pop("expr"), n, field=params.pop("_field"))


def _simple(cls):
    return lambda params, n, box: cls(**params)


_ARGUMENT = "'r' (default) or 'D' (affine distance (75), spatially affine invariant)"

POTENTIALS: dict[str, PotentialFamily] = {
    family.name: family
    for family in (
        PotentialFamily(
            "lennard-jones",
            "pair",
            "4 eps ((sigma/s)^12 - (sigma/s)^6), s = r or D",
            {
                "epsilon": "well depth (> 0)",
                "sigma": "length (> 0); minimum at 2^(1/6) sigma",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("epsilon", "sigma"),
            _family_pair(LennardJones),
        ),
        PotentialFamily(
            "morse",
            "pair",
            "depth ((1 - exp(-alpha (s - r0)))^2 - 1), s = r or D",
            {
                "depth": "well depth (> 0)",
                "alpha": "inverse width (> 0)",
                "r0": "position of the minimum (> 0)",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("depth", "alpha", "r0"),
            _family_pair(Morse),
        ),
        PotentialFamily(
            "gaussian",
            "pair",
            "amplitude exp(-s^2 / (2 width^2)), s = r or D",
            {
                "amplitude": "height (negative: attractive)",
                "width": "length (> 0)",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("amplitude", "width"),
            _family_pair(Gaussian),
        ),
        PotentialFamily(
            "harmonic-invariants",
            "pair",
            "(k/2) sum_a (X_a - X0_a)^2, X = M_a (30) or K_a (28)",
            {
                "stiffness": "k (> 0)",
                "invariants": "'M' (default, affine) or 'K' (Euclidean)",
                "reference": "list of n reference values X0 (default n each)",
                **_CUTOFF_PARAMETERS,
            },
            ("stiffness",),
            _build_harmonic_invariants,
        ),
        PotentialFamily(
            "pair",
            "pair",
            "any expression in r, D, det, K1..Kn, M1..Mn (77)",
            {"expr": "expression, e.g. 'exp(-D**2) * (M1 - 2)**2'", **_CUTOFF_PARAMETERS},
            ("expr",),
            _build_pair_expression,
        ),
        PotentialFamily(
            "dilatation",
            "one-body",
            "sum_K f(det phi_K), eqs. (80), (81)",
            {
                "stiffness": "k (> 0)",
                "volume": "reference det v0 (> 0, default 1)",
                "form": "'log' (default): k/2 ln(|det|/v0)^2; 'harmonic': k/2 (det - v0)^2",
            },
            ("stiffness",),
            _simple(Dilatation),
        ),
        PotentialFamily(
            "elastic",
            "one-body",
            "St Venant-Kirchhoff lam/2 (Tr E)^2 + mu Tr(E^2), E of (32)",
            {"lam": "first Lame constant (lam + 2 mu / n > 0)", "mu": "shear modulus (> 0)"},
            ("lam", "mu"),
            _simple(StVenantKirchhoff),
        ),
        PotentialFamily(
            "external-harmonic",
            "one-body",
            "(k/2) |x - centre|^2 on every body",
            {"stiffness": "k (> 0)", "centre": "list of n numbers (default the origin)"},
            ("stiffness",),
            _simple(ExternalHarmonic),
        ),
        PotentialFamily(
            "external-linear",
            "one-body",
            "-force . x on every body (uniform field)",
            {"force": "list of n numbers"},
            ("force",),
            _simple(ExternalLinear),
        ),
        PotentialFamily(
            "one-body",
            "one-body",
            "any expression in x1..xn, det, trG, K1..Kn, I1..In, E1..En",
            {"expr": "expression, e.g. '10*(det - 1)**2'"},
            ("expr",),
            _build_one_body_expression,
        ),
    )
}


def build_potential(
    kind: str,
    params: Mapping[str, Any],
    *,
    n: int,
    box: Sequence[float] | None = None,
    field: str = "potential",
):
    """The potential a config names: ``kind`` from :data:`POTENTIALS` with ``params``.

    ``box`` (periodic box edges) applies to pair families only. Errors are one-line
    ``ValueError`` messages starting ``config error: <field>:``.
    """
    family = POTENTIALS.get(kind)
    if family is None:
        raise ValueError(
            f"config error: {field}.kind: unknown potential {kind!r} "
            f"(choose from {', '.join(POTENTIALS)})"
        )
    unknown = sorted(set(params) - set(family.parameters))
    if unknown:
        raise ValueError(
            f"config error: {field}: unknown parameter(s) {', '.join(unknown)} for {kind!r} "
            f"(allowed: {', '.join(family.parameters)})"
        )
    missing = [name for name in family.required if name not in params]
    if missing:
        raise ValueError(f"config error: {field}: {kind!r} needs {', '.join(missing)}")
    if box is not None and family.kind != "pair":
        box = None  # one-body terms do not see the box
    args = dict(params)
    if "expr" in family.parameters:
        args["_field"] = f"{field}.expr"
    try:
        return family.build(args, n, None if box is None else tuple(box))
    except ValueError as err:
        message = str(err)
        if message.startswith("config error"):
            raise
        raise ValueError(f"config error: {field}: {message}") from None
    except TypeError as err:
        raise ValueError(f"config error: {field}: {err}") from None
