"""The physical space the centres x_K live in: free space or a periodic box (orthorhombic or
triclinic), with the displacement u = x_K - x_L under the minimum-image convention.

A periodic box is the lattice H Z^n, with the lattice vectors as the *columns* of the cell
matrix H [n, n] (det H > 0); x = H s with fractional coordinates s. An orthorhombic box is
H = diag(edges). The displacement is

    u = H (s - round(s)),   s = H^-1 (x_K - x_L),

(for an orthorhombic box ``u - L round(u / L)``, the same formula written per axis).

Why this is the minimum image for every pair in range: the perpendicular width of the cell
across face a is w_a = 1 / |row a of H^-1|, so a vector u has |s_a| = |(H^-1 u)_a| <= |u| / w_a.
If some image of a pair lies within r < min_a w_a / 2, all its fractional components are in
(-1/2, 1/2), so rounding picks exactly that image; and it is the only one, since two images
differ by a lattice vector, whose length is at least min_a w_a. Hence cut-offs must satisfy
r_cut <= :attr:`Space.max_cutoff` = min_a w_a / 2 (a neighbour list: r_cut + skin). Pairs
farther apart may get a non-nearest image, which is beyond the cut-off anyway.

A periodic box breaks spatial rotations and the spatial affine symmetry (76) of a potential:
only translations (and the lattice's own symmetries) remain.

``Space`` is a small frozen (hashable) dataclass, a static argument of compiled functions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg, _pytree


@_pytree.dataclass(static=True)
class Space:
    """Free space (``cell=None``) or the periodic lattice with cell matrix ``cell`` (columns are
    the lattice vectors). Build with :func:`free_space`, :func:`orthorhombic`,
    :func:`triclinic` or :func:`as_space`."""

    cell: tuple[tuple[float, ...], ...] | None = None
    dimension: int | None = None

    def __post_init__(self):
        if self.cell is None:
            return
        h = np.asarray(self.cell, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] != h.shape[1] or h.shape[0] < 1:
            raise ValueError(f"space.cell must be an n x n matrix (got shape {h.shape})")
        if not np.all(np.isfinite(h)):
            raise ValueError("space.cell must be finite")
        det = float(np.linalg.det(h))
        if not det > 0:
            raise ValueError(
                f"space.cell must have det > 0 (right-handed lattice vectors as columns; "
                f"got det = {det:.6g})"
            )
        _pytree.initialize(self, cell=tuple(tuple(float(v) for v in row) for row in h),
                           dimension=h.shape[0])

    # ------------------------------------------------------------------ geometry
    @property
    def periodic(self) -> bool:
        """True for a periodic box."""
        return self.cell is not None

    @property
    def orthorhombic(self) -> bool:
        """True for a periodic box with a diagonal cell matrix."""
        return self.periodic and bool(np.all(self.matrix == np.diag(np.diag(self.matrix))))

    @property
    def matrix(self) -> np.ndarray:
        """Cell matrix H [n, n] (columns: lattice vectors)."""
        if self.cell is None:
            raise ValueError("free space has no cell matrix")
        return np.asarray(self.cell, dtype=np.float64)

    @property
    def edges(self) -> np.ndarray:
        """Edges of an orthorhombic box (the diagonal of H)."""
        return np.diag(self.matrix).copy()

    @property
    def inverse(self) -> np.ndarray:
        """H^-1 (rows: reciprocal vectors without the 2 pi)."""
        return np.linalg.inv(self.matrix)

    @property
    def widths(self) -> np.ndarray:
        """Perpendicular widths w_a = 1 / |row a of H^-1| of the cell (the edges if
        orthorhombic)."""
        return 1.0 / np.linalg.norm(self.inverse, axis=1)

    @property
    def max_cutoff(self) -> float:
        """The largest cut-off for which the minimum image is exact: min_a w_a / 2 (inf in free
        space)."""
        return math.inf if self.cell is None else 0.5 * float(np.min(self.widths))

    @property
    def volume(self) -> float:
        """det H (inf in free space)."""
        return math.inf if self.cell is None else float(np.linalg.det(self.matrix))

    def check_dimension(self, n: int, owner: str = "space") -> None:
        """ValueError unless the box is n-dimensional (free space fits every n)."""
        if self.dimension is not None and self.dimension != n:
            raise ValueError(f"{owner}: the box is {self.dimension}-dimensional but n = {n}")

    def check_cutoff(self, r: float, owner: str = "cut-off") -> None:
        """ValueError when a range r exceeds :attr:`max_cutoff` (minimum image would miss
        images in range)."""
        if r > self.max_cutoff * (1 + 1e-12):
            raise ValueError(
                f"{owner} = {r:.6g} exceeds half the smallest perpendicular width of the box "
                f"{self.max_cutoff:.6g}: the minimum image would miss images in range "
                f"(use a larger box or a smaller cut-off/skin)"
            )

    # ------------------------------------------------------------------ maps
    def displacement(self, x_k: jax.Array, x_l: jax.Array, cell=None) -> jax.Array:
        """u = x_K - x_L, the minimum image in a periodic box; shape broadcast of the inputs.

        cell: None (this box) or the cell matrix [n, n] of the box as it is now, an array that
        may be traced (a box that a barostat deforms; the static box is then its reference)."""
        u = x_k - x_l
        if self.cell is None:
            return u
        if cell is not None:
            s = u @ _linalg.inv(cell).T
            return (s - jnp.round(s)) @ cell.T
        if self.orthorhombic:
            edges = jnp.asarray(self.edges)
            return u - edges * jnp.round(u / edges)
        h, h_inv = jnp.asarray(self.matrix), jnp.asarray(self.inverse)
        s = u @ h_inv.T
        return (s - jnp.round(s)) @ h.T

    def fractional(self, x: jax.Array) -> jax.Array:
        """s = H^-1 x (unwrapped)."""
        if self.cell is None:
            raise ValueError("free space has no fractional coordinates")
        return x @ jnp.asarray(self.inverse).T

    def wrap(self, x: jax.Array) -> jax.Array:
        """Positions mapped into the cell H [0, 1)^n (the identity in free space)."""
        if self.cell is None:
            return x
        s = self.fractional(x)
        return (s - jnp.floor(s)) @ jnp.asarray(self.matrix).T

    def distance(self, x_k: jax.Array, x_l: jax.Array) -> jax.Array:
        """|x_K - x_L| (minimum image)."""
        u = self.displacement(x_k, x_l)
        return jnp.sqrt(jnp.sum(u * u, axis=-1))


def free_space() -> Space:
    """Unbounded R^n."""
    return Space(None)


def orthorhombic(edges: Sequence[float]) -> Space:
    """Periodic box [0, L_1) x ... x [0, L_n)."""
    values = _edges(edges, "box")
    return Space(tuple(tuple(v if i == j else 0.0 for j in range(len(values)))
                       for i, v in enumerate(values)))


def triclinic(matrix: Any) -> Space:
    """Periodic box spanned by the columns of ``matrix`` (det > 0)."""
    h = np.asarray(matrix, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"box matrix must be n x n (got shape {h.shape})")
    return Space(tuple(map(tuple, h)))


def as_space(box: Any) -> Space:
    """A Space from ``None`` (free), a Space, n edges (orthorhombic) or an n x n matrix
    (triclinic, columns = lattice vectors)."""
    if box is None:
        return free_space()
    if isinstance(box, Space):
        return box
    array = np.asarray(box, dtype=object)
    if array.ndim == 1:
        return orthorhombic(box)
    if array.ndim == 2:
        return triclinic(np.asarray(box, dtype=np.float64))
    raise ValueError(f"box must be n edges or an n x n cell matrix (got {box!r})")


def _edges(edges: Any, name: str) -> tuple[float, ...]:
    if isinstance(edges, str) or not isinstance(edges, Sequence | np.ndarray):
        raise ValueError(f"{name} must be a list of n positive edges (got {edges!r})")
    out = []
    for i, e in enumerate(edges):
        if isinstance(e, bool) or not isinstance(e, int | float | np.floating | np.integer):
            raise ValueError(f"{name}[{i}] must be a real number (got {e!r})")
        if not (math.isfinite(float(e)) and float(e) > 0):
            raise ValueError(f"{name}[{i}] must be > 0 and finite (got {e})")
        out.append(float(e))
    if not out:
        raise ValueError(f"{name} must have n >= 1 edges")
    return tuple(out)


__all__ = [
    "Space", "free_space", "orthorhombic", "triclinic", "as_space"
]
