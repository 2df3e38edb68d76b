"""Variables of the potentials and the symmetries they imply (``affinebody.potentials``).

The one-body variables (57) x_a, det, trG, K_a (17), I_a (19), E_a (32) and the pair variables
(59)-(62), (77), (78) r, D (75), det Gamma (79), K_a (28), M_a (30): their names, their values
for given configurations, and the symmetry groups a function of them has (31), (76), (79).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody.deformation import (
    characteristic_from_traces,
    green_tensor,
    lagrange_strain,
    matrix_power_traces,
)
from affinebody.mutual import (
    affine_distance,
    affine_invariants,
    mutual_trace_invariants,
    relative_volume,
)

#: The symmetry labels of the potentials (shared with ``affinebody.kinetic``).
SYMMETRIES = (
    "translation",
    "spatial-euclidean",
    "spatial-affine",
    "material-euclidean",
    "material-affine",
)
#: Every symmetry: a constant potential has them all.
ALL_SYMMETRIES = frozenset(SYMMETRIES)
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


def check_variable_names(names: Sequence[str], owner: str, *, pair: bool) -> tuple[str, ...]:
    """``names`` as a tuple; ValueError naming ``owner`` for a name outside the one-body or
    pair vocabulary (the index range is checked against n when the energy is evaluated)."""
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


def check_variable_indices(names: Iterable[str], n: int, owner: str) -> None:
    """ValueError naming ``owner`` if an indexed variable (x_a, K_a, I_a, E_a, M_a) has a > n."""
    for name in names:
        m = _INDEXED.match(name)
        if m and int(m.group(2)) > n:
            raise ValueError(f"{owner}: variable {name!r} does not exist in dimension n = {n}")


def uses_indexed(names: Iterable[str], letter: str) -> bool:
    """True if ``names`` holds the array ``letter`` (e.g. ``"K"``) or one of its entries K1..Kn."""
    return any(
        name == letter or (len(name) > 1 and name[0] == letter and name[1:].isdigit())
        for name in names
    )


def one_body_symmetry(names: Iterable[str]) -> frozenset[str]:
    """Symmetries of a one-body potential depending on the given variables (package docstring)."""
    names = set(names)
    sym = set(ALL_SYMMETRIES)
    if uses_indexed(names, "x"):
        sym -= {"translation", "spatial-euclidean", "spatial-affine"}
    if "phi" in names:
        sym -= {"spatial-euclidean", "spatial-affine", "material-euclidean", "material-affine"}
    if "E" in names:
        sym -= {"spatial-affine", "material-euclidean", "material-affine"}
    if names & {"det", "trG"} or any(uses_indexed(names, c) for c in "KIE"):
        sym -= {"spatial-affine", "material-affine"}
    return frozenset(sym)


def pair_symmetry(names: Iterable[str], *, periodic: bool = False) -> frozenset[str]:
    """Symmetries of a pair potential depending on the given variables (package docstring)."""
    names = set(names)
    sym = set(ALL_SYMMETRIES)
    uses_k = uses_indexed(names, "K")
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
    """|u| over the last axis with gradient 0 (not NaN) at u = 0 (double-where); NaN for a
    NaN u (the fallback is 0 x |u|^2, not 0: a NaN fails ``s2 > 0`` and read as r = 0)."""
    s2 = jnp.sum(u * u, axis=-1)
    positive = s2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, s2, 1.0)), 0.0 * s2)


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
    if names & {"trG", "K", "I"} or uses_indexed(names, "K") or uses_indexed(names, "I"):
        k = matrix_power_traces(green_tensor(phi), n)
        out["K"], out["trG"] = k, k[..., 0]
        out["I"] = characteristic_from_traces(k)
        for a in range(n):
            out[f"K{a + 1}"], out[f"I{a + 1}"] = k[..., a], out["I"][..., a]
    if uses_indexed(names, "E"):
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
    if uses_indexed(names, "K"):
        out["K"] = mutual_trace_invariants(phi_k, phi_l)
        for a in range(n):
            out[f"K{a + 1}"] = out["K"][..., a]
    if uses_indexed(names, "M"):
        out["M"] = affine_invariants(phi_k, phi_l)
        for a in range(n):
            out[f"M{a + 1}"] = out["M"][..., a]
    return out


__all__ = [
    "ALL_SYMMETRIES", "SYMMETRIES", "check_variable_indices", "check_variable_names",
    "one_body_symmetry", "one_body_variable_names", "one_body_variables", "pair_symmetry",
    "pair_variable_names", "pair_variables", "uses_indexed",
]
