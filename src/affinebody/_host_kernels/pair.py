"""Numba kernels of the host pair path (:mod:`affinebody.pair_kernels`): the template the
loops over pairs are appended to (written out per pair term by
:mod:`affinebody._host_kernels.pair_source` and :mod:`affinebody._host_kernels.pair_expression`),
and, per body, the parts' sums added and the chain rule through B = phi^-1 and det phi
(``_merge_finish``); ``_fused_thread``, one thread's share of a whole fused evaluation when
each part has a thread of its own, its phases separated by a barrier in shared memory.

The dimension ``N`` is a module constant, which Numba compiles as a constant, so the small
loops over components unroll (about 5x faster than a run-time n). The loader
(:func:`affinebody._host.specialized`) writes this module once per dimension and pair term to
a cache folder, with the constants block set and the generated loops appended, and imports it
from there: with ``CACHE`` true Numba keeps the compiled code next to that file, and later
processes load it instead of compiling it again.
"""

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils
from numba.extending import intrinsic

# --- constants (written by affinebody._host.specialized)
N = 3
CACHE = False
# --- end of constants

_jit = numba.njit(fastmath=False, boundscheck=False, nogil=True, cache=CACHE)
# the generated loops over pairs (pair_source, pair_expression): a division by zero gives inf
# or nan, as in JAX (which the run's finiteness check reports), not an exception inside a
# callback; 'contract' lets LLVM fuse a * b + c into one FMA and 'arcp' turn x / y into
# x * (1 / y) (each a rounding difference of an ulp; no other fast-math assumption):
# together ~12 % off the demo's pair loop (measured at 4096 bodies, docs/performance.md)
_jit_loop = numba.njit(fastmath={"contract", "arcp"}, error_model="numpy", boundscheck=False,
                       nogil=True, cache=CACHE)
# what a _jit_loop function calls that computes (the fused kernel's _f and _fused): inlined by
# Numba into its caller, compiled with the caller's flags and nowhere on its own. A callee
# compiled on its own was a second copy of its code: the caller's machine code called the copy
# linked into its own module where loaded from the cache, but the callee's own library in the
# process that compiled it, and the two copies' FMA contractions differed (a run's pressure an
# ulp apart, frame 34 of 41, between the process that compiled the kernel and every later one)
_inline_loop = numba.njit(fastmath={"contract", "arcp"}, error_model="numpy", boundscheck=False,
                          nogil=True, inline="always")


@intrinsic
def _load_acquire(typingctx, flags, index):
    """flags[index], read with acquire ordering (what the thread that stored it wrote before
    is visible after), and read again on every call (never hoisted out of a loop)."""
    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        array = context.make_array(array_type)(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, array_type, array, [args[1]])
        return builder.load_atomic(pointer, "acquire", 8)
    return flags.dtype(flags, index), codegen


@intrinsic
def _store_release(typingctx, flags, index, value):
    """flags[index] = value with release ordering (after everything written before it)."""
    def codegen(context, builder, signature, args):
        array_type, _, value_type = signature.args
        array = context.make_array(array_type)(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, array_type, array, [args[1]])
        value = context.cast(builder, args[2], value_type, array_type.dtype)
        builder.store_atomic(value, pointer, "release", 8)
        return context.get_dummy_value()
    return numba.types.none(flags, index, value), codegen


@intrinsic
def _yield_core(typingctx):
    """sched_yield(): let another thread have this core (resolved by name, so the machine
    code can be cached)."""
    def codegen(context, builder, signature, args):
        function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.IntType(32), []), "sched_yield")
        builder.call(function, [])
        return context.get_dummy_value()
    return numba.types.none(), codegen


#: spins on a barrier before each yield of the core (a few microseconds)
_SPINS = 2000
#: what a thread that failed writes into its entry of a barrier: past every phase, so that
#: the others do not wait for it (``_host.side_by_side``'s ``failed``)
FAILED = 1 << 62


@_jit
def _arrive_and_wait(arrived, k, phase):
    """Thread k has finished ``phase``; returns once every thread (one per entry of
    ``arrived``) has. Waits by spinning, yielding the core every few microseconds, so a
    thread that shares its core with the one it waits for lets it run."""
    _store_release(arrived, k, phase)
    spins = 0
    for other in range(arrived.shape[0]):
        while _load_acquire(arrived, other) < phase:
            spins += 1
            if spins % _SPINS == 0:
                _yield_core()


# a singular phi gives inf or nan, as _linalg.inv does in JAX (the run's finiteness check
# reports it), not a ZeroDivisionError inside a callback
@numba.njit(fastmath=False, boundscheck=False, nogil=True, cache=CACHE, error_model="numpy")
def _inverse_det(start, stop, phi, binv, det):
    """B = phi^-1 into binv and det phi into det for bodies start..stop-1, as
    affinebody._linalg.inv and det compute them: Gaussian elimination of [phi | Id] with the
    same partial pivoting (a row below becomes the pivot row where its |entry| is larger),
    back substitution, det the signed product of the pivots."""
    rows = np.empty((N, 2 * N))
    for body in range(start, stop):
        for r in range(N):
            for c in range(N):
                rows[r, c] = phi[body, r, c]
                rows[r, N + c] = 1.0 if r == c else 0.0
        sign = 1.0
        for col in range(N - 1):
            for r in range(col + 1, N):
                if abs(rows[r, col]) > abs(rows[col, col]):
                    for c in range(2 * N):
                        rows[r, c], rows[col, c] = rows[col, c], rows[r, c]
                    sign = -sign
            for r in range(col + 1, N):
                factor = rows[r, col] / rows[col, col]
                for c in range(2 * N):
                    rows[r, c] = rows[r, c] - factor * rows[col, c]
        d = sign
        for r in range(N):
            d = d * rows[r, r]
        det[body] = d
        for r in range(N - 1, -1, -1):
            for c in range(N):
                acc = rows[r, N + c]
                for k in range(r + 1, N):
                    acc = acc - rows[r, k] * binv[body, k, c]
                binv[body, r, c] = acc / rows[r, r]


@_jit
def _merge_finish(start, stop, gx_parts, gphi_parts, gb_parts, gdet_parts, binv, det,
                  gx_out, gphi_out):
    """Bodies start..stop-1: the per-body sums of the parts added in part order, then the
    chain rule through B = phi^-1 and det phi, gphi_out = g_phi - B^T g_B B^T + g_det det B^T
    (as pair_kernels._finish)."""
    parts = gx_parts.shape[0]
    gb = np.empty((N, N))
    tmp = np.empty((N, N))
    for body in range(start, stop):
        for d in range(N):
            acc = 0.0
            for p in range(parts):
                acc += gx_parts[p, body, d]
            gx_out[body, d] = acc
        gdet = 0.0
        for p in range(parts):
            gdet += gdet_parts[p, body]
        for r in range(N):
            for c in range(N):
                acc = 0.0
                for p in range(parts):
                    acc += gb_parts[p, body, r, c]
                gb[r, c] = acc
        for r in range(N):  # tmp = B^T gB
            for c in range(N):
                acc = 0.0
                for k in range(N):
                    acc += binv[body, k, r] * gb[k, c]
                tmp[r, c] = acc
        for r in range(N):
            for c in range(N):
                acc = 0.0
                for k in range(N):
                    acc += tmp[r, k] * binv[body, c, k]
                g = 0.0
                for p in range(parts):
                    g += gphi_parts[p, body, r, c]
                gphi_out[body, r, c] = g - acc + gdet * det[body] * binv[body, c, r]


#: the phases of ``_fused_thread`` (bits of its ``phases``)
PREPARE, PAIRS, MERGE = 1, 2, 4


@_jit_loop
def _fused_thread(k, phases, arrived, lo, hi, start, stop, i, j, x, phi, binv, det, mode, h,
                  h_inv, edges, gradients, virial, gx, gphi, gb, gdet, w, g_x, g_phi):
    """Part k of a fused evaluation, in three phases: PREPARE zeroes part k's sums and
    computes B and det phi of bodies start..stop-1; PAIRS sums the pairs lo..hi-1 into part
    k's sums (``_fused``, appended to this module) and returns their energy; MERGE (with
    gradients) adds the parts' sums of bodies start..stop-1 and applies the chain rule.
    ``phases`` says which to run. With a thread per part, each runs all three, and
    ``arrived`` (one entry per thread, zero at the start) is the barrier between them; one
    thread runs the phases one at a time for every part, ``arrived`` empty. Both ways run this
    one compiled function, so every bit is the same: LLVM's FMA contraction depends on
    where a loop is inlined, and ``_fused`` called on its own had given dV/dx an ulp apart."""
    barrier = arrived.shape[0] > 0
    energy = 0.0
    if phases & PREPARE:
        gx[k][...] = 0.0
        gphi[k][...] = 0.0
        gb[k][...] = 0.0
        gdet[k][...] = 0.0
        w[k][...] = 0.0
        _inverse_det(start, stop, phi, binv, det)
    if barrier:
        _arrive_and_wait(arrived, k, 1)
    if phases & PAIRS:
        energy = _fused(lo, hi, i, j, x, phi, binv, det, mode, h, h_inv, edges,  # noqa: F821
                        gradients, virial, gx[k], gphi[k], gb[k], gdet[k], w[k])
    if gradients and barrier:
        _arrive_and_wait(arrived, k, 2)
    if gradients and phases & MERGE:
        _merge_finish(start, stop, gx, gphi, gb, gdet, binv, det, g_x, g_phi)
    return energy
