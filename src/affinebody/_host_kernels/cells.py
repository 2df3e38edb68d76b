"""Numba kernel of the host neighbour-list build (:mod:`affinebody.neighbors`): a counting sort
of the bodies by cell, then for each body in an order in space, the cells of the stencil and
their bodies of larger index, in the same order as the JAX build.

``N`` (the dimension) and ``PERIODIC`` are module constants, compiled as constants so the loops
unroll; :func:`affinebody._host.specialized` writes this module once per (N, PERIODIC) to a
cache folder and imports it from there, so that Numba's disk cache (``CACHE``) spares later
processes the compilation. Imported directly it is the 3D periodic version without a cache.
"""

import numba
import numpy as np

# --- constants (written by affinebody._host.specialized)
N = 3
PERIODIC = True
CACHE = False
# --- end of constants


_jit = numba.njit(boundscheck=False, nogil=True, cache=CACHE)


@_jit
def order_by_cell(flat, cells):
    """Counting sort of the bodies by cell, then index: (start [cells + 1], order [bodies]),
    the bodies of cell c being order[start[c]:start[c + 1]]."""
    bodies = flat.shape[0]
    start = np.zeros(cells + 1, np.int64)
    for k in range(bodies):
        start[flat[k] + 1] += 1
    for c in range(cells):
        start[c + 1] += start[c]
    order = np.empty(bodies, np.int64)
    fill = start[:-1].copy()
    for k in range(bodies):
        order[fill[flat[k]]] = k
        fill[flat[k]] += 1
    return start, order


@_jit
def pairs(first, last, visit, coords, x, start, order, grid, strides, stencil, mode, h, h_inv,
          edges, radius2, offset, room, pairs_i, pairs_j):
    """The pairs (k, l > k) closer than sqrt(radius2) of the bodies k = visit[first..last-1],
    in order (k, then the stencil's cells, then the cell's bodies by index), written from
    pairs_i[offset] on while they fit in ``room`` rows; returns how many there are. ``visit``
    is an order in space (``neighbors.visiting_order``), not by index: consecutive pairs then
    touch bodies near one another, whose data stays in cache, however the bodies are
    numbered (a liquid's numbering loses its order in space as it diffuses)."""
    u = np.empty(N)
    s = np.empty(N)
    total = 0
    for position in range(first, last):
        k = visit[position]
        for o in range(stencil.shape[0]):
            cell = 0
            inside = True
            for d in range(N):
                c = coords[k, d] + stencil[o, d]
                if PERIODIC:
                    c %= grid[d]
                elif c < 0 or c >= grid[d]:
                    inside = False
                cell += c * strides[d]
            if not inside:
                continue
            for slot in range(start[cell], start[cell + 1]):
                other = order[slot]
                if other <= k:
                    continue
                # minimum image, as space.Space.displacement, written out as in the pair
                # kernels (an inlined Numba helper made those ~30 % slower, measured)
                for d in range(N):
                    u[d] = x[k, d] - x[other, d]
                if mode == 1:
                    for d in range(N):
                        u[d] -= edges[d] * np.round(u[d] / edges[d])
                elif mode == 2:
                    for d in range(N):
                        acc = 0.0
                        for e in range(N):
                            acc += h_inv[d, e] * u[e]
                        s[d] = acc - np.round(acc)
                    for d in range(N):
                        acc = 0.0
                        for e in range(N):
                            acc += h[d, e] * s[e]
                        u[d] = acc
                r2 = 0.0
                for d in range(N):
                    r2 += u[d] * u[d]
                if r2 < radius2:
                    if total < room:
                        pairs_i[offset + total] = k
                        pairs_j[offset + total] = other
                    total += 1
    return total
