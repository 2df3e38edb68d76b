"""Cell list and half neighbour list of body centres, with a skin, for pair potentials with a
cut-off on the distance r or on the affine distance D of eq. (75).

Reach of a body. A cut-off on r reaches r_cut. A cut-off on D reaches farther when bodies
stretch: with a_K = phi_K^-1 u, D^2 = (|a_K|^2 + |a_L|^2)/2 >= |u|^2 / max(s_K, s_L)^2, where s_K
is the largest singular value of phi_K, so D < D_cut implies |u| < D_cut max(s_K, s_L). The
spatial reach is therefore

    rho = r_cut (cut-off on r),    rho = D_cut max_K s_max(phi_K) (cut-off on D),

and the list holds every pair K < L with |x_K - x_L| < rho + skin at the time of the build
(minimum image in a periodic box, :mod:`affinebody.space`). It stays complete while

    2 max_K |x_K(t) - x_K(build)| + rho(t) - rho(build) <= skin,

which :func:`needs_rebuild` tests; :func:`update` rebuilds inside compiled code when it fails.

A box that changes (a barostat, ``HamiltonianSystem.cell``). The spec's box is then only the
reference; build, update and check take the current cell matrix H_t, and the list remembers the
cell H_0 of its build. Cells are a grid in fractional coordinates s = H^-1 x, so a move of the
barostat (x -> mu x, H -> mu H) moves no body between cells. With A = H_0 H_t^-1 and
m_K = H_0 (s_K(t) - s_K(build)) (the motion relative to the box, in the build's frame), a pair
in range now, |u_t| < rho(t), had at the build the image u_0 = A u_t - (m_K - m_L) with
|u_0| <= |A| rho(t) + 2 max_K |m_K|, so the list stays complete while

    |A| rho(t) + 2 max_K |m_K| <= rho(build) + skin,     |A| the largest singular value,

(the fixed-box rule when A = Id), and while rho(t) + skin <= half the smallest perpendicular
width of H_t (the minimum image, :mod:`affinebody.space`). A build checks that its cells are
at least rho + skin wide in the current cell; :func:`allocate` with ``cell`` chooses cells
:data:`BOX_HEADROOM` wider than needed, so that the box may shrink by that much before a
reallocation (``REACH_OVERFLOW``) gives a finer grid for the box as it is.

Fixed shapes. A list is a pytree of arrays of fixed capacity (:class:`NeighborList`), so
building and using it compiles once. Capacities are chosen by :func:`allocate` from the actual
configuration with some room to spare; a build that does not fit sets ``overflow`` (bit 1: pair
capacity, bit 2: a cell's capacity, bit 4: the reach outgrew the cells or half the box) and the
list must then not be used: :func:`check` raises, and :func:`allocate` again (on the current
configuration) gives a bigger list. Memory is linear in N: cells [N_cells, cell_capacity] and
pairs [capacity], plus a chunk of candidates at a time during the build.

Build (one jitted function, also on a GPU): cell index of every centre (fractional coordinates
in a box), bodies sorted by cell into a table [N_cells, cell_capacity], then chunks of bodies
scan the 3^n neighbouring cells, keep partners L > K within rho + skin and write them into the
pair arrays (``i < j``), K in an order in space (:func:`visiting_order`: row by row over
cells of about one body each): consecutive pairs are near one another in space whatever the
numbering of the bodies, so the pair kernels find their data in cache (with the pairs in
order of K, a numbering that had lost its order in space, as a liquid's does as it diffuses,
made a step 2.2x slower at 97 336 bodies). Cells are at least rho + skin wide in every lattice
direction (wider in a dilute box: at most ``CELLS_PER_BODY`` cells per body), so a pair in
range is always in neighbouring cells; in free space the grid covers the bounding box at
allocation and centres outside it are clamped into the edge cells, which keeps that property
(clamping moves cell indices by no more than the positions differ).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import _host
from affinebody import _linalg as linalg
from affinebody.space import Space, as_space

PAIR_OVERFLOW, CELL_OVERFLOW, REACH_OVERFLOW = 1, 2, 4
#: Candidate pairs examined per pass of a build (memory of the pass: ~ 20 bytes each). XLA
#: allocates the temporaries of a build at every execution of a step that contains it, even
#: when the build is not taken, so a large pass costs every step (measured: 1 << 22 made a
#: 4096-body step 30 % slower than 1 << 18, and the build itself 1.7x slower).
_CANDIDATES_PER_CHUNK = 1 << 18
#: The same on a GPU, where each pass is a trip of a device loop (its condition read by the
#: host) and a few launches: 10^6 bodies take ~12 passes instead of ~800 (~0.3 GB per pass).
_ACCELERATOR_CANDIDATES_PER_CHUNK = 1 << 24
#: Relative room in the cells' widths of a list for a box that changes (``allocate(...,
#: cell=...)``): the box may shrink by this factor before a reallocation gives new cells.
BOX_HEADROOM = 0.1
#: Relative growth of the list radius that a new list's cells allow, by cut-off variable: none
#: for r, 1/4 for D, whose reach grows as bodies stretch (``allocate(reach_headroom=...)``).
REACH_HEADROOM = {"r": 0.0, "D": 0.25}
#: Room a new list has for more pairs than it found (or than a uniform fluid has, in a box).
CAPACITY_FACTOR = 1.25
#: Most cells per body (at least 8 cells): the table [N_cells, cell_capacity] stays linear in
#: N in a dilute box or a wide free space, whose cells are then made wider than the radius.
CELLS_PER_BODY = 2


def candidates_per_chunk() -> int:
    """Candidate pairs per pass of :func:`build_jax` on the default backend."""
    return (_CANDIDATES_PER_CHUNK if jax.default_backend() == "cpu"
            else _ACCELERATOR_CANDIDATES_PER_CHUNK)


class NeighborList(NamedTuple):
    """Half list of pairs i < j (a pytree). Entries ``count:`` are padding (``i = j = N``)."""

    i: jax.Array  # [capacity] int32
    j: jax.Array  # [capacity] int32
    count: jax.Array  # [] int32: pairs found (may exceed capacity: then overflow)
    overflow: jax.Array  # [] int32: bit flags PAIR/CELL/REACH_OVERFLOW
    reference_x: jax.Array  # [N, n] centres at the build
    reach: jax.Array  # [] spatial reach rho at the build
    #: the cell matrix [n, n] at the build of a box that a barostat deforms (None: the
    #: spec's static box; "A box that changes" in the module docstring)
    cell: jax.Array | None = None


@dataclass(frozen=True)
class NeighborSpec:
    """Static description of a list (hashable; a static argument of compiled functions)."""

    space: Space
    cutoff: float
    variable: str
    skin: float
    bodies: int
    capacity: int
    cell_capacity: int
    grid: tuple[int, ...]
    max_radius: float
    origin: tuple[float, ...] | None = None  # free space: lower corner of the grid
    cell_size: tuple[float, ...] | None = None  # free space: cell edges

    @property
    def n(self) -> int:
        return len(self.grid)


# --------------------------------------------------------------------------------------------
# reach


@jax.jit
def largest_singular_values(phi: jax.Array) -> jax.Array:
    """s_max(phi_K) = sqrt(largest eigenvalue of G = phi^T phi), shape [..., N].

    Closed form for n <= 3 (the trigonometric solution of the characteristic cubic), slightly
    enlarged (relative 1e-12) so that it bounds s_max from above; eigvalsh for n > 3."""
    g = jnp.swapaxes(phi, -1, -2) @ phi
    n = phi.shape[-1]
    if n == 1:
        lam = g[..., 0, 0]
    elif n == 2:
        mean = 0.5 * (g[..., 0, 0] + g[..., 1, 1])
        half = 0.5 * (g[..., 0, 0] - g[..., 1, 1])
        lam = mean + jnp.sqrt(half * half + g[..., 0, 1] ** 2)
    elif n == 3:
        q = (g[..., 0, 0] + g[..., 1, 1] + g[..., 2, 2]) / 3.0
        off = g[..., 0, 1] ** 2 + g[..., 0, 2] ** 2 + g[..., 1, 2] ** 2
        dev = (g[..., 0, 0] - q) ** 2 + (g[..., 1, 1] - q) ** 2 + (g[..., 2, 2] - q) ** 2
        p = jnp.sqrt((dev + 2.0 * off) / 6.0)
        safe_p = jnp.where(p > 0, p, 1.0)
        b = (g - q[..., None, None] * jnp.eye(3)) / safe_p[..., None, None]
        half_det = 0.5 * linalg.det(b)
        angle = jnp.arccos(jnp.clip(half_det, -1.0, 1.0)) / 3.0
        lam = jnp.where(p > 0, q + 2.0 * p * jnp.cos(angle), q)
    else:
        lam = jnp.linalg.eigvalsh(g)[..., -1]
    scale = jnp.max(jnp.abs(g), axis=(-2, -1))
    return jnp.sqrt(jnp.maximum(lam, 0.0) + 1e-12 * scale)


def spatial_reach(cutoff: float, variable: str, phi: jax.Array) -> jax.Array:
    """rho = r_cut, or D_cut max_K s_max(phi_K) for a cut-off on D (module docstring)."""
    if variable == "r":
        return jnp.asarray(cutoff, dtype=phi.dtype)
    return cutoff * jnp.max(largest_singular_values(phi))


# --------------------------------------------------------------------------------------------
# cells


def _cell_coordinates(spec: NeighborSpec, x: jax.Array, cell=None, refine: int = 1
                      ) -> jax.Array:
    """Integer cell coordinates [N, n] of the centres in the grid of ``spec``, each cell cut
    into ``refine`` parts along every axis."""
    grid = jnp.asarray(spec.grid) * refine
    if cell is not None:
        s = x @ linalg.inv(cell).T
        s = s - jnp.floor(s)
        c = jnp.floor(s * grid).astype(jnp.int32)
    elif spec.space.periodic:
        s = spec.space.fractional(x)
        s = s - jnp.floor(s)
        c = jnp.floor(s * grid).astype(jnp.int32)
    else:
        c = jnp.floor((x - jnp.asarray(spec.origin)) / (jnp.asarray(spec.cell_size) / refine))
        c = c.astype(jnp.int32)
    return jnp.clip(c, 0, grid - 1)


def visiting_refinement(spec: NeighborSpec) -> int:
    """How many parts a cell is cut into along each axis for :func:`visiting_order`: cells of
    about one body each (3 for a crystal in cells of rho + skin; 1 in a dilute box)."""
    per_cell = spec.bodies / max(1, int(np.prod(spec.grid)))
    return max(1, round(per_cell ** (1.0 / len(spec.grid))))


def visiting_order(spec: NeighborSpec, x: jax.Array, cell=None) -> tuple[jax.Array, int]:
    """(flat index [N] of every centre's cell in the refined grid of
    :func:`visiting_refinement`, row by row (the last axis fastest), and the number of such
    cells): the builds visit the bodies K in order of it, then of index. Row by row over cells
    of one body, as the lattice generator numbers its sites, so a crystal is visited in about
    the order of its numbers (with cells of rho + skin, ~24 bodies, a crystal of 97 336 ran 5 %
    slower per step than visited by number), and a diffused numbering in an order in space."""
    refine = visiting_refinement(spec)
    grid = tuple(g * refine for g in spec.grid)
    coords = _cell_coordinates(spec, x, cell, refine)
    return coords @ jnp.asarray(_strides(grid)), int(np.prod(grid))


def _strides(grid: tuple[int, ...]) -> np.ndarray:
    """Strides of the flat cell index, the last axis fastest (row by row, as the lattice
    generator numbers its sites): the build visits the bodies of a lattice in about the order
    of their numbers."""
    return np.cumprod((1,) + tuple(grid[::-1])[:-1])[::-1].astype(np.int32)


def _stencil(spec: NeighborSpec) -> np.ndarray:
    """Offsets [S, n] of the neighbouring cells (distinct modulo the grid in a box)."""
    per_axis = []
    for g in spec.grid:
        if spec.space.periodic:
            per_axis.append(sorted({o % g for o in (-1, 0, 1)}))
        else:
            per_axis.append([-1, 0, 1])
    mesh = np.meshgrid(*per_axis, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=-1).astype(np.int32)


def cell_table(spec: NeighborSpec, x: jax.Array,
               cell=None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(cell coordinates [N, n], table [N_cells, cell_capacity] of body indices padded with N,
    largest occupancy); ``cell``: the current cell of a box that changes, or None."""
    bodies = x.shape[0]
    coords = _cell_coordinates(spec, x, cell)
    flat = coords @ jnp.asarray(_strides(spec.grid))
    order = jnp.argsort(flat).astype(jnp.int32)
    ordered = flat[order]
    cells = jnp.arange(int(np.prod(spec.grid)), dtype=flat.dtype)
    start = jnp.searchsorted(ordered, cells, side="left")
    occupancy = jnp.searchsorted(ordered, cells, side="right") - start
    slot = jnp.arange(spec.cell_capacity)
    index = jnp.minimum(start[:, None] + slot[None, :], bodies - 1)
    table = jnp.where(slot[None, :] < occupancy[:, None], order[index], bodies)
    return coords, table.astype(jnp.int32), jnp.max(occupancy)


# --------------------------------------------------------------------------------------------
# build, update, check


def perpendicular_widths(cell: jax.Array) -> jax.Array:
    """w_a = 1 / |row a of H^-1| of a (possibly traced) cell matrix H [n, n]."""
    return 1.0 / jnp.sqrt(jnp.sum(linalg.inv(cell) ** 2, axis=-1))


def _reach_overflow(spec: NeighborSpec, radius, cell) -> jax.Array:
    """Whether cells of ``spec`` cannot hold a list of ``radius``: beyond ``max_radius`` in
    the static box; in a box that changes (``cell``), wider than a cell of the grid or than
    half the box's smallest perpendicular width, now."""
    if cell is None:
        return radius > spec.max_radius
    widths = perpendicular_widths(cell)
    return ((radius > jnp.min(widths / jnp.asarray(spec.grid)))
            | (radius > 0.5 * jnp.min(widths)))


def build(spec: NeighborSpec, x: jax.Array, phi: jax.Array, cell=None) -> NeighborList:
    """The half list of ``spec`` for centres x [N, n] and configurations phi [N, n, n]
    (jit-compatible; ``spec`` is static). Check ``overflow`` before using it. ``cell``: the
    current cell matrix of a box that a barostat deforms (the spec's box is its reference;
    module docstring), or None.

    On a CPU backend with Numba this is :func:`_host_build` (compiled loops, no cell
    capacity to fill: ~50x faster at 4096 bodies); elsewhere the JAX build below. Both give
    the same pairs in the same order (tested)."""
    if _host.in_use():
        return _host_build(spec, x, phi, cell)
    return build_jax(spec, x, phi, cell)


def build_jax(spec: NeighborSpec, x: jax.Array, phi: jax.Array, cell=None) -> NeighborList:
    """:func:`build` in JAX (a GPU: no host round trip). Pairs in order of K
    (:func:`visiting_order`, then index), then of the stencil cell, then of L within a cell."""
    bodies, n = x.shape
    reach = spatial_reach(spec.cutoff, spec.variable, phi)
    radius = reach + spec.skin
    coords, table, occupancy = cell_table(spec, x, cell)
    stencil = jnp.asarray(_stencil(spec))
    strides = jnp.asarray(_strides(spec.grid))
    grid = jnp.asarray(spec.grid)
    width = stencil.shape[0] * spec.cell_capacity
    chunk = max(1, min(bodies, candidates_per_chunk() // width))
    chunks = -(-bodies // chunk)
    visit = jnp.argsort(visiting_order(spec, x, cell)[0]).astype(jnp.int32)  # stable
    ids = jnp.arange(chunks * chunk, dtype=jnp.int32).reshape(chunks, chunk)
    order_pad = jnp.concatenate([visit, jnp.full((1,), bodies, jnp.int32)])
    x_pad = jnp.concatenate([x, x[:1]])
    coords_pad = jnp.concatenate([coords, coords[:1]])
    capacity = spec.capacity

    def scan_chunk(carry, body):
        pairs_i, pairs_j, total = carry
        body = order_pad[jnp.minimum(body, bodies)]  # the padding body N has no partners
        neighbour = coords_pad[body][:, None, :] + stencil[None]
        if spec.space.periodic:
            inside = jnp.ones(neighbour.shape[:2], dtype=bool)
            neighbour = neighbour % grid
        else:
            inside = jnp.all((neighbour >= 0) & (neighbour < grid), axis=-1)
            neighbour = jnp.clip(neighbour, 0, grid - 1)
        candidate = table[neighbour @ strides]  # [chunk, S, cap]
        candidate = jnp.where(inside[..., None], candidate, bodies).reshape(body.shape[0], -1)
        u = spec.space.displacement(x_pad[body][:, None, :], x_pad[candidate], cell)
        keep = (
            (candidate < bodies)
            & (candidate > body[:, None])
            & (body[:, None] < bodies)
            & (jnp.sum(u * u, axis=-1) < radius * radius)
        )
        counts = jnp.sum(keep, axis=1, dtype=jnp.int32)
        first = total + jnp.cumsum(counts) - counts
        position = first[:, None] + jnp.cumsum(keep, axis=1, dtype=jnp.int32) - 1
        position = jnp.where(keep, position, capacity)  # out of range: dropped
        pairs_i = pairs_i.at[position].set(
            jnp.broadcast_to(body[:, None], position.shape), mode="drop"
        )
        pairs_j = pairs_j.at[position].set(candidate, mode="drop")
        return (pairs_i, pairs_j, total + jnp.sum(counts, dtype=jnp.int32)), None

    empty = jnp.full((capacity,), bodies, dtype=jnp.int32)
    (pairs_i, pairs_j, total), _ = lax.scan(scan_chunk, (empty, empty, jnp.int32(0)), ids)
    overflow = (
        jnp.where(total > capacity, PAIR_OVERFLOW, 0)
        | jnp.where(occupancy > spec.cell_capacity, CELL_OVERFLOW, 0)
        | jnp.where(_reach_overflow(spec, radius, cell), REACH_OVERFLOW, 0)
    ).astype(jnp.int32)
    return NeighborList(pairs_i, pairs_j, total, overflow, x, reach, cell)


build_jit = jax.jit(build, static_argnums=0)


#: Fewest bodies worth handing to threads in the host build (below, one thread).
HOST_THREAD_MIN_BODIES = 2048


@functools.cache
def _host_kernels(n: int, periodic: bool):
    """The compiled build for dimension n (:mod:`affinebody._host_kernels.cells`, specialized
    and cached on disk by :func:`affinebody._host.specialized`)."""
    return _host.specialized("cells", N=n, PERIODIC=bool(periodic))


def _host_pairs(bodies: int, capacity: int, pairs_i, pairs_j, search) -> int:
    """Fill pairs_i, pairs_j (padded with ``bodies``) by ``search(first, last, offset, room)``
    (the pairs of the bodies at positions first..last-1 of the visiting order, written from
    row ``offset`` while they fit in ``room`` rows; returns how many there are) over
    :data:`affinebody._host.PARTS` fixed parts of the bodies, on up to as many threads: part k
    writes into its share of the rows, then the parts are moved together in order, so the
    list is the one-pass list whatever the thread count. Where a part has more pairs than its
    share (an uneven system), the bodies are searched again in one pass. Returns the number
    of pairs (more than ``capacity``: overflow)."""
    parts = _host.PARTS
    shares = _host.part_ranges(capacity, parts)

    def work(k, first, last):
        lo, hi = shares[k]
        return search(first, last, lo, hi - lo)

    count = _host.thread_count(bodies, HOST_THREAD_MIN_BODIES)
    found = _host.in_parts(work, bodies, parts, count)
    if any(f > hi - lo for f, (lo, hi) in zip(found, shares, strict=True)):
        total = search(0, bodies, 0, capacity)
    else:
        total = 0
        for f, (lo, _) in zip(found, shares, strict=True):
            pairs_i[total:total + f] = pairs_i[lo:lo + f]  # moves left: total <= lo
            pairs_j[total:total + f] = pairs_j[lo:lo + f]
            total += f
    pairs_i[min(total, capacity):] = bodies
    pairs_j[min(total, capacity):] = bodies
    return total


def _host_build(spec: NeighborSpec, x: jax.Array, phi: jax.Array, cell=None) -> NeighborList:
    """:func:`build` with compiled CPU loops through ``_host.callback``: a counting sort of
    the bodies by cell (no cell capacity), then, for each body K in the order of
    :func:`visiting_order` (another counting sort), the cells of the
    stencil in order and their bodies L > K in index order, as :func:`build_jax` (the bodies
    in fixed parts on up to two threads, :func:`_host_pairs`)."""
    bodies, n = x.shape
    reach = spatial_reach(spec.cutoff, spec.variable, phi)
    radius = reach + spec.skin
    coords = _cell_coordinates(spec, x, cell)
    flat = coords @ jnp.asarray(_strides(spec.grid))
    fine, fine_cells = visiting_order(spec, x, cell)
    space = spec.space
    if cell is not None:  # the current cell, an operand (the general minimum image)
        mode, h, h_inv, edges = 2, cell, linalg.inv(cell), np.ones(n)
    elif space.periodic:
        mode = 1 if space.orthorhombic else 2
        h, h_inv, edges = space.matrix, space.inverse, space.edges
    else:
        mode, h, h_inv, edges = 0, np.eye(n), np.eye(n), np.ones(n)
    grid, strides, stencil = (np.asarray(spec.grid, np.int64),
                              _strides(spec.grid).astype(np.int64),
                              _stencil(spec).astype(np.int64))

    def host(flat, fine, coords, x, radius, h, h_inv):
        kernels = _host_kernels(n, space.periodic)
        start, order = kernels.order_by_cell(np.asarray(flat, np.int64), int(np.prod(grid)))
        visit = kernels.order_by_cell(np.asarray(fine, np.int64), fine_cells)[1]
        coords, x = np.asarray(coords, np.int64), np.asarray(x)
        h, h_inv = np.asarray(h, np.float64), np.asarray(h_inv, np.float64)
        radius2 = float(radius) ** 2
        pairs_i = np.empty(spec.capacity, np.int32)
        pairs_j = np.empty(spec.capacity, np.int32)

        def search(first, last, offset, room):
            return kernels.pairs(first, last, visit, coords, x, start, order, grid, strides,
                                 stencil, mode, h, h_inv, np.asarray(edges, np.float64), radius2,
                                 offset, room, pairs_i, pairs_j)

        total = _host_pairs(bodies, spec.capacity, pairs_i, pairs_j, search)
        return pairs_i, pairs_j, np.asarray(min(total, np.iinfo(np.int32).max), np.int32)

    shapes = (jax.ShapeDtypeStruct((spec.capacity,), jnp.int32),) * 2 + (
        jax.ShapeDtypeStruct((), jnp.int32),)
    pairs_i, pairs_j, total = _host.callback(
        host, shapes, flat, fine, coords, x, radius, jnp.asarray(h, x.dtype),
        jnp.asarray(h_inv, x.dtype), vmap_method="sequential")
    overflow = (jnp.where(total > spec.capacity, PAIR_OVERFLOW, 0)
                | jnp.where(_reach_overflow(spec, radius, cell), REACH_OVERFLOW, 0)
                ).astype(jnp.int32)
    return NeighborList(pairs_i, pairs_j, total, overflow, x, reach, cell)


def needs_rebuild(spec: NeighborSpec, neighbors: NeighborList, x, phi,
                  cell=None) -> jax.Array:
    """True when 2 max_K |x_K - x_K(build)| + rho - rho(build) exceeds the skin (the list
    might miss a pair in range), or the list overflowed. ``cell``: the current cell of a box
    that changes (the list must have been built with one): then the rule of the module
    docstring, |A| rho + 2 max_K |m_K| > rho(build) + skin, or rho + skin beyond half the
    box's smallest perpendicular width."""
    reach = spatial_reach(spec.cutoff, spec.variable, phi)
    if cell is None:
        moved = spec.space.displacement(x, neighbors.reference_x)
        largest = jnp.sqrt(jnp.max(jnp.sum(moved * moved, axis=-1)))
        growth = reach - neighbors.reach
        return (2.0 * largest + growth > spec.skin) | (neighbors.overflow != 0)
    if neighbors.cell is None:
        raise ValueError("neighbors.needs_rebuild: a list for a box that changes must be "
                         "built with its cell (neighbors.build(spec, x, phi, cell))")
    stretch = neighbors.cell @ linalg.inv(cell)  # A = H_0 H_t^-1
    moved = spec.space.displacement(x @ stretch.T, neighbors.reference_x, neighbors.cell)
    largest = jnp.sqrt(jnp.max(jnp.sum(moved * moved, axis=-1)))
    grown = largest_singular_values(stretch[None])[0] * reach + 2.0 * largest
    return ((grown > neighbors.reach + spec.skin) | ~fits_box(spec, phi, cell)
            | (neighbors.overflow != 0))


def fits_box(spec: NeighborSpec, phi, cell) -> jax.Array:
    """Whether reach + skin is at most half the smallest perpendicular width of the (traced)
    cell: the largest list radius for which the minimum image is exact."""
    reach = spatial_reach(spec.cutoff, spec.variable, phi)
    return reach + spec.skin <= 0.5 * jnp.min(perpendicular_widths(cell))


def update(spec: NeighborSpec, neighbors: NeighborList, x, phi, cell=None) -> NeighborList:
    """``neighbors`` if still complete, else a fresh build (jit-compatible, one lax.cond);
    ``cell`` as in :func:`needs_rebuild`."""
    return lax.cond(
        needs_rebuild(spec, neighbors, x, phi, cell),
        lambda: build(spec, x, phi, cell),
        lambda: neighbors,
    )


class NeighborListOverflow(ValueError):
    """A list's capacity was exceeded: reallocate (``neighbors.allocate``) and rebuild."""


def check(neighbors: NeighborList) -> NeighborList:
    """Raise :class:`NeighborListOverflow` (saying which capacity) if the list overflowed."""
    flags = int(neighbors.overflow)
    if flags == 0:
        return neighbors
    reasons = []
    if flags & PAIR_OVERFLOW:
        reasons.append(f"{int(neighbors.count)} pairs exceed the pair capacity "
                       f"{neighbors.i.shape[0]}")
    if flags & CELL_OVERFLOW:
        reasons.append("a cell holds more bodies than the cell capacity")
    if flags & REACH_OVERFLOW:
        reasons.append(f"the reach {float(neighbors.reach):.6g} + skin outgrew the cells or half "
                       f"the box (bodies stretched)")
    raise NeighborListOverflow(
        "neighbour list overflow: " + "; ".join(reasons)
        + ": call neighbors.allocate(...) on the current configuration to reallocate"
    )


def allocate(
    space,
    x,
    phi,
    cutoff: float,
    variable: str = "r",
    skin: float = 0.3,
    *,
    capacity_factor: float = CAPACITY_FACTOR,
    cell_factor: float = 2.5,
    reach_headroom: float | None = None,
    capacity: int | None = None,
    cell_capacity: int | None = None,
    cell=None,
    box_headroom: float = BOX_HEADROOM,
) -> tuple[NeighborSpec, NeighborList]:
    """Choose capacities for the configuration (x, phi) and build the list (eager).

    space: a :class:`~affinebody.space.Space` or anything :func:`~affinebody.space.as_space`
    takes (None: free space). cutoff, variable: the potential's cut-off (``"r"`` or ``"D"``).
    capacity_factor, cell_factor: room for fluctuations of the pair count and cell occupancy
    (2.5: a lattice that clusters as it vibrates was seen to reach 2.4x its mean occupancy).
    reach_headroom: relative growth of the list radius the cells allow before a reallocation
    (default 0 for r, 0.25 for D, where stretching bodies reach farther).
    capacity, cell_capacity: fixed capacities instead of measured ones (the same capacities
    give the same spec, hence no recompilation, for different configurations).
    cell: the current cell matrix [n, n] of a box that a barostat deforms (``space`` is its
    reference box): the cells are then a grid of this cell, ``box_headroom`` (relative) wider
    than the radius needs, and the list is built in it (module docstring).
    """
    space = as_space(space)
    x = jnp.asarray(x, dtype=jnp.float64)
    phi = jnp.asarray(phi, dtype=jnp.float64)
    if x.ndim != 2 or phi.shape != (*x.shape, x.shape[1]):
        raise ValueError(f"neighbors.allocate needs x [N, n] and phi [N, n, n] "
                         f"(got {x.shape} and {phi.shape})")
    bodies, n = x.shape
    space.check_dimension(n, "neighbors.allocate")
    if variable not in ("r", "D"):
        raise ValueError(f"neighbors.variable must be 'r' or 'D' (got {variable!r})")
    if not (cutoff > 0 and skin >= 0):
        raise ValueError(f"neighbors needs cutoff > 0 and skin >= 0 (got {cutoff}, {skin})")
    if reach_headroom is None:
        reach_headroom = REACH_HEADROOM[variable]
    radius = float(spatial_reach(cutoff, variable, phi)) + skin
    now, room = space, 1.0
    if cell is not None:
        if not space.periodic:
            raise ValueError("neighbors.allocate: a cell needs a periodic reference box")
        cell = jnp.asarray(cell, dtype=jnp.float64)
        now, room = as_space(np.asarray(cell)), 1.0 + box_headroom
    now.check_cutoff(radius, "neighbour-list radius (reach + skin)")
    max_radius = min(radius * (1.0 + reach_headroom), now.max_cutoff)
    x_np = np.asarray(x)
    most_cells = max(8, CELLS_PER_BODY * bodies)
    if space.periodic:
        grid = tuple(int(max(1, math.floor(w / (max_radius * room)))) for w in now.widths)
        while np.prod(grid, dtype=float) > most_cells:  # a dilute box: larger cells
            grid = tuple(max(1, math.floor(g / 1.26)) for g in grid)
        origin = size = None
        s = x_np @ now.inverse.T
        coords = np.clip(np.floor((s - np.floor(s)) * grid).astype(int), 0, np.array(grid) - 1)
    else:
        lo, hi = x_np.min(axis=0), x_np.max(axis=0)
        edge = max_radius
        while True:
            extent = hi - lo
            grid = tuple(int(max(1, math.ceil(e / edge + 1e-9))) for e in extent)
            if np.prod(grid, dtype=float) <= most_cells:
                break
            edge *= 1.26
        origin, size = tuple(map(float, lo)), (float(edge),) * n
        coords = np.clip(np.floor((x_np - lo) / edge).astype(int), 0, np.array(grid) - 1)
    flat = coords @ _strides(grid)
    occupancy = int(np.bincount(flat, minlength=int(np.prod(grid))).max())
    if cell_capacity is None:
        cell_capacity = int(math.ceil(occupancy * cell_factor)) + 1
    sized = lambda capacity: NeighborSpec(  # noqa: E731
        space, float(cutoff), variable, float(skin), bodies, capacity, cell_capacity, grid,
        max_radius, origin, size)
    if capacity is None:
        # a crystal that melts fills its shells: room for a uniform fluid at least (periodic)
        floor = uniform_pair_count(now, bodies, radius) if space.periodic else 0
        if floor:  # first at the floor: one build, unless more pairs are found than that
            spec = sized(max(64, int(math.ceil(floor * capacity_factor))))
            first = build_jit(spec, x, phi, cell)
            if int(first.count) <= floor:
                return spec, check(first)
            count = int(first.count)
        else:  # free space: count the pairs first (a list of capacity 1 overflows, counting)
            count = int(build_jit(sized(1), x, phi, cell).count)
        capacity = max(64, int(math.ceil(count * capacity_factor)))
    spec = sized(capacity)
    return spec, check(build_jit(spec, x, phi, cell))


#: Reallocations in a row (no step kept in between) before a run gives up on its list.
MAX_REALLOCATIONS_IN_A_ROW = 8


def reallocate(spec: NeighborSpec, x, phi, *, flags: int, pairs: int,
               reach: float | None = None, cell=None,
               box_headroom: float = BOX_HEADROOM) -> tuple[NeighborSpec, NeighborList]:
    """The one capacity policy: a list for (x, phi) after ``spec`` overflowed with ``flags``
    (``PAIR_/CELL_/REACH_OVERFLOW``), having seen ``pairs`` pairs and a spatial ``reach``.

    Capacities never shrink, so repeated reallocations make progress: the pair capacity grows
    to at least 3/2 of the pairs seen, the cell capacity doubles, and a reach that outgrew the
    cells gets 5/4 of the room it needed as headroom (a new grid); the list's radius
    (``max_radius``, which sets the cells) is never made smaller than it was, so a pair or
    cell overflow after a reach overflow does not take back the room that one gave.
    Deterministic in its arguments, so a resumed run rebuilds exactly the list of the
    uninterrupted one. Raises ``NeighborListOverflow`` (or the space's ValueError for a reach
    beyond half the box) when no list can be built. ``cell``: the current cell of a box that
    changes (the new grid is one of it, with ``box_headroom`` as in :func:`allocate`), or
    None.
    """
    x, phi = jnp.asarray(x), jnp.asarray(phi)
    capacity, cell_capacity = spec.capacity, spec.cell_capacity
    if flags & PAIR_OVERFLOW:
        capacity = max(capacity, int(math.ceil(1.5 * pairs)))
    if flags & CELL_OVERFLOW:
        cell_capacity = 2 * cell_capacity
    radius = float(spatial_reach(spec.cutoff, spec.variable, phi)) + spec.skin
    headroom = max(REACH_HEADROOM[spec.variable], spec.max_radius / radius - 1.0)
    if flags & REACH_OVERFLOW:
        needed = (spec.skin if reach is None else float(reach) + spec.skin) / radius
        headroom = max(headroom, 0.25, 1.25 * needed - 1.0)
    args = (spec.space, x, phi, spec.cutoff, spec.variable, spec.skin)
    try:  # one build at the grown capacities
        return allocate(*args, capacity=capacity, cell_capacity=cell_capacity,
                        reach_headroom=headroom, cell=cell,
                        box_headroom=box_headroom)
    except NeighborListOverflow:  # other cells (a new grid): measure them
        measured, _ = allocate(*args, reach_headroom=headroom, cell=cell,
                        box_headroom=box_headroom)
        return allocate(*args, capacity=max(capacity, measured.capacity),
                        cell_capacity=max(cell_capacity, measured.cell_capacity),
                        reach_headroom=headroom, cell=cell,
                        box_headroom=box_headroom)


#: The fields of a :class:`NeighborSpec` that allocation chooses (the others come from the
#: system: space, cut-off, variable, skin, bodies): what a checkpoint keeps of a run's list.
SIZE_FIELDS = ("capacity", "cell_capacity", "grid", "max_radius", "origin", "cell_size")


def sizes(spec: NeighborSpec) -> dict:
    """The :data:`SIZE_FIELDS` of ``spec`` that are set (plain ints, floats and tuples)."""
    return {name: getattr(spec, name) for name in SIZE_FIELDS
            if getattr(spec, name) is not None}


def resized(spec: NeighborSpec, values: dict) -> NeighborSpec:
    """``spec`` with the sizes ``values`` (as :func:`sizes` gives them, or read back from a
    file as arrays), the rest of it kept."""
    def exact(name, value):
        if name in ("capacity", "cell_capacity"):
            return int(value)
        if name == "max_radius":
            return float(value)
        kind = int if name == "grid" else float
        return tuple(kind(v) for v in np.asarray(value).ravel())

    return dataclasses.replace(spec, **{name: exact(name, values[name]) for name in SIZE_FIELDS
                                        if name in values})


def list_at(base: NeighborSpec, x, phi, cell=None) -> tuple[NeighborSpec, NeighborList]:
    """A list for (x, phi) with ``base``'s capacities, or :func:`reallocate`'s when they do
    not hold it: a function of ``base`` and the configuration alone (checkpoints, resume);
    ``cell``: the current cell of a box that changes, or None."""
    x, phi = jnp.asarray(x), jnp.asarray(phi)
    cell = None if cell is None else jnp.asarray(cell, dtype=x.dtype)
    built = build_jit(base, x, phi, cell)
    flags = int(built.overflow)
    if not flags:
        return base, built
    return reallocate(base, x, phi, flags=flags, pairs=int(built.count),
                      reach=float(built.reach), cell=cell)


def uniform_pair_count(space: Space, bodies: int, radius: float) -> int:
    """Pairs closer than ``radius`` in a periodic box if the bodies were spread uniformly:
    N (N - 1) / 2 times the volume of the n-ball of that radius over the box volume.

    A list allocated for a perfect lattice counts its shells, and the first shell just outside
    the radius moves in as soon as the lattice vibrates (measured: a simple cubic lattice at
    spacing 1 and radius 2.8 has 41 pairs per body, 53 after 1000 steps of the scale benchmark,
    ``benchmarks/run_scale.py``):
    allocating for at least the uniform count spares the run its reallocations (each a
    recompilation)."""
    n = space.dimension
    ball = math.pi ** (n / 2) / math.gamma(n / 2 + 1) * radius**n
    return int(math.ceil(0.5 * bodies * (bodies - 1) * ball / abs(float(np.linalg.det(
        np.asarray(space.matrix))))))


def uniform_list_bytes(space: Space, bodies: int, radius: float) -> float:
    """Bytes of the pair arrays (i, j: int32) of a list that :func:`allocate` makes for
    ``bodies`` spread uniformly in a periodic box (:func:`uniform_pair_count`, with
    :data:`CAPACITY_FACTOR`): at least what a run with this list needs, known before it is
    built (a box far too small for its bodies asks for more than a machine has)."""
    return 8.0 * CAPACITY_FACTOR * uniform_pair_count(space, bodies, radius)


def brute_force_pairs(space, x, radius: float) -> np.ndarray:
    """All pairs i < j with |x_i - x_j| < radius (minimum image), [P, 2] in NumPy; O(N^2), for
    tests."""
    space = as_space(space)
    k, l = np.triu_indices(x.shape[0], 1)
    u = np.asarray(space.displacement(jnp.asarray(x)[k], jnp.asarray(x)[l]))
    keep = np.sum(u * u, axis=-1) < radius * radius
    return np.stack([k[keep], l[keep]], axis=-1)


def pairs_of(neighbors: NeighborList) -> np.ndarray:
    """The valid pairs of a list, [count, 2] in NumPy (for tests and inspection)."""
    count = min(int(neighbors.count), neighbors.i.shape[0])
    return np.stack([np.asarray(neighbors.i[:count]), np.asarray(neighbors.j[:count])], axis=-1)


__all__ = [
    "BOX_HEADROOM", "REACH_HEADROOM", "SIZE_FIELDS", "candidates_per_chunk", "resized", "sizes",
    "NeighborList", "NeighborSpec",
    "largest_singular_values", "spatial_reach", "cell_table", "visiting_refinement",
    "visiting_order", "perpendicular_widths", "build",
    "build_jax", "build_jit", "needs_rebuild", "fits_box", "update", "NeighborListOverflow",
    "check", "allocate", "MAX_REALLOCATIONS_IN_A_ROW", "reallocate", "list_at",
    "uniform_pair_count", "uniform_list_bytes", "CAPACITY_FACTOR", "brute_force_pairs", "pairs_of"
]
