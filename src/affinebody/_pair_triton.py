"""The JAX pair kernel's passes over pairs on a GPU as two hand-written Pallas (Triton) kernels:
the formulas of :func:`affinebody.pair_kernels._chunk_contributions` (docs/performance.md,
"Pair kernels (`affinebody.pair_kernels`)"), each one loop over the pairs that stores only
its results (``pair_kernels.pair_program`` "triton").

XLA compiles the per-pair arithmetic of a chunk as about a dozen fused loops, each storing its
per-pair results in GPU memory for the next; here one loop per stage. For a chunk of P pairs,
with u = x_K - x_L (minimum image) from XLA:

1. :func:`_partials_kernel`: gather phi, B = phi^-1 and det phi of both bodies, compute the
   scalars f needs (r, D, det Gamma, K_a, M_a, M'_a, in the order of
   :func:`affinebody.pair_kernels.scalar_columns`; a padding pair gets
   :func:`affinebody.pair_kernels.padding_value`), then f and its partials with respect to
   them (``jax.vjp`` of ``PairTerm.energy_from_values`` traced into the kernel,
   :class:`ColumnEnergy`), and write the pair energies and the partials;
2. :func:`_rows_kernel`: gather the bodies again (and compute the scalars again instead of
   loading them: one input fewer; not yet timed against loading on a GPU), read the
   partials, apply the per-pair chain rule of ``_chunk_contributions`` and write each
   pair's row of n + n^2 numbers (dV/dx, dV/dphi) for body L, and body K's rows summed over
   each run of pairs of one K (:func:`_run_sums`), which XLA then adds to the bodies (one
   scatter per side).

Where f reads a whole array K or M (``PairTerm.columnwise`` false: Triton has no [BLOCK, 3]
blocks) or does not lower to Triton, the first kernel is :func:`_scalars_kernel`, which writes
the scalars, and XLA computes f and its partials from them between the two kernels
(``jax.vjp`` of ``PairTerm.energy_from_scalars``, one fused elementwise loop), so that any
pair potential, a user's callable included, runs. On an H200 at 10^6 bodies (2026-11-29) a
pass over 2^22 pairs took 0.35 ms in the scalars kernel, 0.32 ms in XLA's f, 1.96 ms in the
rows kernel; f inside the first kernel (after that run) saves XLA's loop and its reads and
writes of every scalar, for 116 registers per thread in place of 99 (sm_90, compiled
offline: ``tools/triton_offline.py``; as many warps per SM as the rows kernel's 128).

Triton wants power-of-two block shapes, so a matrix is not a [P, n, n] block but n^2 vectors
of :data:`BLOCK` pairs (lists of lists), and every array a kernel reads or writes is one flat
vector indexed by hand: the bodies' table (:func:`table`) as ``body * C + column``, u and the
rows pair by pair (``pair * width + column``, the layout XLA's scatter reads), the scalars and
partials scalar by scalar (``q * P + pair``).

On a CPU the same kernels run in Pallas' interpreter (``interpret=True``): that is how the
tests check them against all-pairs autodiff, and they check that the kernels go through
Pallas' Triton lowering for CUDA; the product runs them on a GPU only.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from affinebody import _linalg

#: Pairs per program of the kernels (a power of two, as Triton wants). 256 rather than 128:
#: the rows kernel's runs of one K (:func:`_run_sums`) are cut at a block's ends, so longer
#: blocks leave fewer run sums to add; the forces at 10^6 bodies took 36.4 ms against 37.3
#: on an H200 (2026-11-29, ``step_phases.py --triton-blocks``, one process; at 64, 128 and 256
#: before the run sums they took 39.4, 39.3 and 39.4 ms).
BLOCK = 256
#: Warps per program: one pair per thread.
WARPS = BLOCK // 32


class Layout(NamedTuple):
    """What the kernels compute for one pair term in dimension n (static): the plain scalars
    among r, D, det, the powers k of K_a (28) and m of M_a (30), whether M'_a (swapped order)
    is needed, and ``scalars``: (name, a) of each scalar row, a = 0 for r, D, det, in the order
    of the ``base`` of ``PairTerm.energy_from_scalars`` (``pair_kernels.scalar_columns``)."""

    n: int
    plain: frozenset
    k_powers: int
    m_powers: int
    swapped: bool
    scalars: tuple[tuple[str, int], ...]

    @property
    def columns(self) -> int:
        """Columns of the bodies' table: phi (n^2), B = phi^-1 (n^2), det phi."""
        return 2 * self.n * self.n + 1


def table(phi: jax.Array, binv: jax.Array, det: jax.Array) -> jax.Array:
    """The bodies' table [N * C] the kernels gather from: per body phi and B (row-major), det."""
    bodies, n = phi.shape[0], phi.shape[-1]
    return jnp.concatenate([phi.reshape(bodies, n * n), binv.reshape(bodies, n * n),
                            det[:, None]], axis=1).reshape(-1)


# --------------------------------------------------------------------------------------------
# n x n matrices as lists of lists of [BLOCK] vectors (``_linalg.entries``)


_sum, _mm, _t = _linalg.entries_sum, _linalg.entries_matmul, _linalg.entries_transpose


def _add(a, b):
    return [[p + q for p, q in zip(row_a, row_b, strict=True)]
            for row_a, row_b in zip(a, b, strict=True)]


def _scaled(c, a):
    return [[c * v for v in row] for row in a]


def _powers_and_traces(m, powers: int):
    """m^0..m^(powers-1) (m^0, the identity, as None) and Tr(m^a), a = 1..powers."""
    n = len(m)
    mats, traces = [None], [_sum(m[i][i] for i in range(n))]
    for _ in range(1, powers):
        mats.append(m if mats[-1] is None else _mm(mats[-1], m))
        traces.append(_sum(mats[-1][i][k] * m[k][i] for i in range(n) for k in range(n)))
    return mats, traces


def _weighted(mats, partials, n):
    """W = sum_a (a + 1) (df/dq_a) m^a over a = 0..powers-1 (m^0 = Id)."""
    zero = 0.0 * partials[0]
    w = [[partials[0] if i == j else zero for j in range(n)] for i in range(n)]
    for a in range(1, len(mats)):
        w = _add(w, _scaled((a + 1) * partials[a], mats[a]))
    return w


def _matvec(a, v):
    return [_sum(a[i][k] * v[k] for k in range(len(v))) for i in range(len(a))]


def _tmatvec(a, v):
    """a^T v."""
    return [_sum(a[k][i] * v[k] for k in range(len(v))) for i in range(len(a))]


# --------------------------------------------------------------------------------------------
# the kernels


def _pallas():
    """``jax.experimental.pallas``, imported when a kernel is first built: its import takes
    about 0.3 s, which every process (the CLI's start-up) would pay otherwise."""
    from jax.experimental import pallas

    return pallas


def _pair_of_bodies(layout: Layout, pairs: int, u_ref, i_ref, j_ref, valid_ref, t_ref):
    """This program's BLOCK pairs: offset, valid mask, u and phi, B, det of both bodies."""
    pl = _pallas()
    n, columns = layout.n, layout.columns
    start = pl.program_id(0) * BLOCK
    here = pl.ds(start, BLOCK)
    valid = valid_ref[here] != 0
    lanes = start + jnp.arange(BLOCK, dtype=jnp.int32)
    u = [u_ref[lanes * n + a] for a in range(n)]

    def body(index):
        base = index * columns

        def matrix(offset):
            return [[t_ref[base + (offset + r * n + c)] for c in range(n)] for r in range(n)]

        return matrix(0), matrix(n * n), t_ref[base + 2 * n * n]

    return start, lanes, valid, u, body(i_ref[here]), body(j_ref[here])


def _scalar_values(layout: Layout, u, k, l):
    """The scalars of one block and what the chain rule reuses: a_K = B_K u, a_L = B_L u."""
    (phi_k, b_k, det_k), (phi_l, b_l, det_l) = k, l
    values, kept = {}, {}
    if "r" in layout.plain:
        r2 = _sum(c * c for c in u)
        values[("r", 0)] = jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)
    if "D" in layout.plain:
        a_k, a_l = _matvec(b_k, u), _matvec(b_l, u)
        d2 = 0.5 * (_sum(c * c for c in a_k) + _sum(c * c for c in a_l))
        values[("D", 0)] = jnp.where(d2 > 0, jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)), 0.0)
        kept["a"] = a_k, a_l
    if "det" in layout.plain:
        values[("det", 0)] = det_l / det_k
    for name, left, right, powers in (("K", _t(phi_k), phi_l, layout.k_powers),
                                      ("M", b_k, phi_l, layout.m_powers),
                                      ("Ms", b_l, phi_k, layout.m_powers * layout.swapped)):
        if powers:
            m = _mm(left, right)
            mats, traces = _powers_and_traces(m, powers)
            kept[name] = m, mats
            for a, trace in enumerate(traces):
                values[(name, a)] = trace
    return values, kept


def _padded_scalars(layout: Layout, pairs: int, padding: tuple, u_ref, i_ref, j_ref,
                    valid_ref, t_ref):
    """(start, valid, the scalars of this block's pairs in the order of ``layout.scalars``),
    each padding pair's scalars :func:`affinebody.pair_kernels.padding_value`."""
    start, _, valid, u, k, l = _pair_of_bodies(layout, pairs, u_ref, i_ref, j_ref, valid_ref,
                                               t_ref)
    values, _ = _scalar_values(layout, u, k, l)
    return start, valid, tuple(jnp.where(valid, values[key], padding[q])
                               for q, key in enumerate(layout.scalars))


def _scalars_kernel(layout: Layout, pairs: int, padding: tuple, u_ref, i_ref, j_ref,
                    valid_ref, t_ref, s_ref):
    start, _, scalars = _padded_scalars(layout, pairs, padding, u_ref, i_ref, j_ref,
                                        valid_ref, t_ref)
    pl = _pallas()
    for q, value in enumerate(scalars):
        s_ref[pl.ds(q * pairs + start, BLOCK)] = value


def _partials_kernel(layout: Layout, pairs: int, padding: tuple, energy, u_ref, i_ref, j_ref,
                     valid_ref, t_ref, e_ref, p_ref):
    """The scalars of each pair, then f (``energy``: :class:`ColumnEnergy`) and its reverse
    pass on them: the pair energies (0 for padding) and df/dscalar, scalar by scalar."""
    start, valid, scalars = _padded_scalars(layout, pairs, padding, u_ref, i_ref, j_ref,
                                            valid_ref, t_ref)
    energies, pullback = jax.vjp(energy, scalars)
    (partials,) = pullback(jnp.ones_like(energies))
    pl = _pallas()
    e_ref[pl.ds(start, BLOCK)] = jnp.where(valid, energies, 0.0)
    for q, value in enumerate(partials):
        p_ref[pl.ds(q * pairs + start, BLOCK)] = value


def _rows_kernel(layout: Layout, pairs: int, bodies: int, u_ref, i_ref, j_ref, valid_ref,
                 t_ref, p_ref, out_k_ref, k_index_ref, out_l_ref):
    """The per-pair chain rule of ``_chunk_contributions`` from the partials of f by scalar:
    each pair's row of n + n^2 numbers (dV/dx, dV/dphi) for body L, and body K's rows summed
    over each run of pairs of one K (:func:`_run_sums`), stored for XLA to add to the bodies
    (one scatter per side)."""
    start, lanes, valid, u, k, l = _pair_of_bodies(layout, pairs, u_ref, i_ref, j_ref,
                                                   valid_ref, t_ref)
    # computed again, not loaded: a few flops per scalar against a read of memory
    values, kept = _scalar_values(layout, u, k, l)
    pl = _pallas()
    row = {key: q for q, key in enumerate(layout.scalars)}

    def partial(key):  # loaded where used: loaded first, they would hold registers throughout
        return p_ref[pl.ds(row[key] * pairs + start, BLOCK)]

    n = layout.n
    (phi_k, b_k, _), (phi_l, b_l, _) = k, l
    scalar = values.__getitem__
    zero = 0.0 * u[0]
    g_u = [zero] * n
    d_k = [[zero] * n for _ in range(n)]
    d_l = [[zero] * n for _ in range(n)]
    if "r" in layout.plain:
        r = scalar(("r", 0))
        c = jnp.where(r > 0, partial(("r", 0)) / jnp.where(r > 0, r, 1.0), 0.0)
        g_u = [g + c * v for g, v in zip(g_u, u, strict=True)]
    if "D" in layout.plain:
        a_k, a_l = kept["a"]
        dist = scalar(("D", 0))
        c = jnp.where(dist > 0, partial(("D", 0)) / jnp.where(dist > 0, 2.0 * dist, 1.0), 0.0)
        v_k, v_l = _tmatvec(b_k, a_k), _tmatvec(b_l, a_l)
        g_u = [g + c * (p + q) for g, p, q in zip(g_u, v_k, v_l, strict=True)]
        d_k = _add(d_k, [[-c * v_k[a] * a_k[b] for b in range(n)] for a in range(n)])
        d_l = _add(d_l, [[-c * v_l[a] * a_l[b] for b in range(n)] for a in range(n)])
    if "det" in layout.plain:
        c = partial(("det", 0)) * scalar(("det", 0))
        d_l = _add(d_l, _scaled(c, _t(b_l)))
        d_k = _add(d_k, _scaled(-c, _t(b_k)))
    if layout.k_powers:
        _, mats = kept["K"]
        w = _weighted(mats, [partial(("K", a)) for a in range(layout.k_powers)], n)
        d_k = _add(d_k, _mm(phi_l, w))
        d_l = _add(d_l, _mm(phi_k, _t(w)))
    if layout.m_powers:
        gamma, mats = kept["M"]
        y = _mm(_weighted(mats, [partial(("M", a)) for a in range(layout.m_powers)], n), b_k)
        d_l = _add(d_l, _t(y))
        d_k = _add(d_k, _scaled(-1.0, _t(_mm(gamma, y))))
        if layout.swapped:
            gamma, mats = kept["Ms"]
            y = _mm(_weighted(mats, [partial(("Ms", a)) for a in range(layout.m_powers)], n), b_l)
            d_k = _add(d_k, _t(y))
            d_l = _add(d_l, _scaled(-1.0, _t(_mm(gamma, y))))
    side_k = g_u + [d_k[a][b] for a in range(n) for b in range(n)]
    side_l = [-g for g in g_u] + [d_l[a][b] for a in range(n) for b in range(n)]
    width = n + n * n
    body, first, last = _run_bounds(start, valid, i_ref, valid_ref, pairs)
    for q, (vk, vl) in enumerate(zip(_run_sums(valid, first, last, side_k), side_l,
                                     strict=True)):
        out_k_ref[lanes * width + q] = vk
        out_l_ref[lanes * width + q] = jnp.where(valid, vl, 0.0)
    k_index_ref[pl.ds(start, BLOCK)] = jnp.where(valid & (first | last), body, bodies)


def _run_bounds(start, valid, i_ref, valid_ref, pairs: int):
    """Body K of each lane of this block, and the lanes that begin and that end a run of
    one K (each lane of a run of one pair both)."""
    lane = jnp.arange(BLOCK, dtype=jnp.int32)
    body = i_ref[start + lane]
    before = i_ref[jnp.maximum(start + lane - 1, 0)]
    after = jnp.minimum(start + lane + 1, pairs - 1)
    next_valid = (valid_ref[after] != 0) & (lane < BLOCK - 1)
    first = (lane == 0) | (before != body)
    last = ~next_valid | (i_ref[after] != body)
    return body, first, last


def _run_sums(valid, first, last, rows):
    """Body K's rows of this block summed run by run, not left pair by pair.

    The list holds the pairs of one body K one after the other (``neighbors.build``), so a
    block of pairs is a few runs of one K each, and a scatter of each pair's row to K put ~40
    float64 atomic adds on each body's numbers one after another (the forces at 10^6 bodies on
    an H200: 39.1 ms that way, 37.3 ms with these sums). With C the running sum of a
    row over the block's lanes (C_e its value at lane e), the last lane of each run carries
    C_e and the first lane, unless it is the block's first, -C_(e-1) = v_e - C_e: XLA then adds
    only those lanes (:func:`_run_bounds`; the others' index is out of range), each run's body
    getting C at its end minus C before its start, its run's sum, whatever the order of the
    pairs (a K in two runs gets both sums)."""
    lane = jnp.arange(BLOCK, dtype=jnp.int32)
    out = []
    for row in rows:
        v = jnp.where(valid, row, 0.0)
        running = jnp.cumsum(v)
        out.append(jnp.where(last, running, 0.0)
                   - jnp.where(first & (lane > 0), running - v, 0.0))
    return out


# --------------------------------------------------------------------------------------------
# the chunk


@functools.cache
def _calls(layout: Layout, pairs: int, bodies: int, padding: tuple, interpret: bool,
           energy=None):
    """The two pallas_calls for chunks of ``pairs`` pairs (a multiple of BLOCK) of ``bodies``
    bodies: the partials kernel with ``energy`` (a :class:`ColumnEnergy`), else the scalars
    kernel; then the rows kernel."""
    scalars, width = len(layout.scalars), layout.n + layout.n * layout.n
    params = dict(grid=(pairs // BLOCK,), interpret=interpret,
                  compiler_params=None if interpret else _triton_params())
    f64 = jnp.float64
    pl = _pallas()
    rows = jax.ShapeDtypeStruct((width * pairs,), f64)
    index = jax.ShapeDtypeStruct((pairs,), jnp.int32)
    scalar_rows = jax.ShapeDtypeStruct((scalars * pairs,), f64)
    if energy is not None:
        first = pl.pallas_call(
            functools.partial(_partials_kernel, layout, pairs, padding, energy),
            out_shape=(jax.ShapeDtypeStruct((pairs,), f64), scalar_rows),
            name="affinebody_pair_partials", **params)
    else:
        first = pl.pallas_call(functools.partial(_scalars_kernel, layout, pairs, padding),
                               out_shape=scalar_rows, name="affinebody_pair_scalars", **params)
    second = pl.pallas_call(
        functools.partial(_rows_kernel, layout, pairs, bodies),
        out_shape=(rows, index, rows), name="affinebody_pair_rows", **params)
    return first, second


def _triton_params():
    from jax.experimental.pallas import triton as plt

    return plt.CompilerParams(num_warps=WARPS, num_stages=1)


def partials_of(layout: Layout, values_and_partials, scalars):
    """(energies [P], partials [len(layout.scalars) * P]): f and its partials (XLA) from the
    scalars kernel's output, the partials in the layout the rows kernel reads."""
    rows = scalars.reshape(len(layout.scalars), -1)
    base = {}
    for q, (name, _) in enumerate(layout.scalars):
        base.setdefault(name, []).append(rows[q])
    base = {name: vs[0] if name in layout.plain else jnp.stack(vs, axis=-1)
            for name, vs in base.items()}
    energies, partials = values_and_partials(base)
    names = dict.fromkeys(name for name, _ in layout.scalars)  # in the scalars' order
    return energies, jnp.concatenate([partials[name].T.reshape(-1) for name in names])


def chunk_rows(layout: Layout, values_and_partials, padding: tuple, u, i, j, valid,
               body_table, interpret: bool = False, energy=None):
    """Energy of a chunk of pairs and its rows: (E, g_u [P, n], side_K [P, n + n^2], K [P],
    side_L [P, n + n^2]): side_L holds each pair's row (dV/dx, dV/dphi) for its body L;
    side_K the rows for body K summed over each run of pairs of one K (:func:`_run_sums`), to
    be added to body K[p] (an index N, out of range, where a lane adds nothing).

    ``layout``: what to compute (:class:`Layout`); ``values_and_partials``: base -> (energies
    [P], partials), f and its partials in XLA between the two kernels; ``padding``: each
    scalar's value for a padding pair; ``u`` [P, n]; ``i``, ``j`` [P] int32; ``valid`` [P]
    bool; ``body_table``: the bodies' :func:`table`; ``interpret``: run in Pallas'
    interpreter (CPU tests); ``energy``: None, or f as a :class:`ColumnEnergy`, which the
    first kernel then evaluates (``values_and_partials`` is not used)."""
    pairs, n = u.shape
    width = n + n * n
    size = -(-pairs // BLOCK) * BLOCK
    if size != pairs:
        extra = size - pairs
        u = jnp.concatenate([u, jnp.zeros((extra, n), u.dtype)])
        i, j = (jnp.concatenate([a, jnp.zeros(extra, a.dtype)]) for a in (i, j))
        valid = jnp.concatenate([valid, jnp.zeros(extra, bool)])
    first, second = _calls(layout, size, body_table.shape[0] // layout.columns, padding,
                           interpret, energy)
    args = (u.reshape(-1), i.astype(jnp.int32), j.astype(jnp.int32), valid.astype(jnp.int32),
            body_table)
    if energy is not None:
        energies, flat = first(*args)
    else:
        energies, flat = partials_of(layout, values_and_partials, first(*args))
    side_k, k_index, side_l = second(*args, flat)
    side_l = side_l.reshape(size, width)[:pairs]
    return (jnp.sum(energies), -side_l[:, :n], side_k.reshape(size, width)[:pairs],
            k_index[:pairs], side_l)


@dataclasses.dataclass(frozen=True)
class ColumnEnergy:
    """f of a pair term as the partials kernel evaluates it: the pair energies [BLOCK] from one
    vector per scalar, in the order of ``layout.scalars`` (``PairTerm.energy_from_values``:
    the swapped order, cut-off and switch included). For a term whose f reads only scalars
    (``PairTerm.columnwise``), not a whole array K or M: Triton has no [BLOCK, 3] blocks."""

    term: object
    layout: Layout

    def __call__(self, scalars):
        values, swapped = {}, {}
        for (name, a), value in zip(self.layout.scalars, scalars, strict=True):
            if name in self.layout.plain:
                values[name] = value
            elif name == "Ms":
                swapped[f"M{a + 1}"] = value
            else:
                values[f"{name}{a + 1}"] = value
        return self.term.energy_from_values(values, swapped or None, self.layout.n)
