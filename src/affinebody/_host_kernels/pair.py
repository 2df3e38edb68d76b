"""Numba kernels of the host pair path (:mod:`affinebody.pair_kernels`): the scalar pair
variables of a chunk of pairs (``_geometry``), their closed-form derivatives summed per body
(``_scatter``) and, for the fused kernel, the parts' sums added and the per-body chain rule through
B = phi^-1 and det phi (``_merge_finish``).

The dimension ``N`` is a module constant, which Numba compiles as a constant, so the small
loops over components unroll (about 5x faster than a run-time n). The loader
(:func:`affinebody._host.specialized`) writes this module once per dimension to a cache folder,
with the constants block set, and imports it from there: with ``CACHE`` true Numba keeps the
compiled code next to that file, and later processes load it instead of compiling it again.
Imported directly, the module is the n = 3 version without a disk cache.
"""

import numba
import numpy as np

# --- constants (written by affinebody._host.specialized)
N = 3
CACHE = False
# --- end of constants

_jit = numba.njit(fastmath=False, boundscheck=False, nogil=True, cache=CACHE)
# a call of a jitted helper with array arguments cost ~50 ns per pair here (measured; more than
# the arithmetic), so the per-pair code is written out inside the two loops
_inline = numba.njit(fastmath=False, boundscheck=False, nogil=True, inline="always")


@_inline
def _power_traces(m, powers, mats, traces_out, p):
    """mats[a] = m^a for a < powers; traces_out[p, a] = Tr(m^(a+1))."""
    for r in range(N):
        for c in range(N):
            mats[0, r, c] = 1.0 if r == c else 0.0
    for a in range(1, powers):
        for r in range(N):
            for c in range(N):
                acc = 0.0
                for k in range(N):
                    acc += mats[a - 1, r, k] * m[k, c]
                mats[a, r, c] = acc
    for a in range(powers):
        acc = 0.0
        for r in range(N):
            for k in range(N):
                acc += mats[a, r, k] * m[k, r]
        traces_out[p, a] = acc

@_jit
def _geometry(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges,
              need_r, need_d, need_det, k_powers, m_powers, swapped,
              r_out, d_out, det_out, k_out, m_out, ms_out):
    """Scalar pair variables of pairs start..stop-1 into rows 0..stop-start-1."""
    u = np.empty(N)
    s = np.empty(N)
    m = np.empty((N, N))
    mats = np.empty((max(1, max(k_powers, m_powers)), N, N))
    for p in range(start, stop):
        q = p - start
        a, b = i[p], j[p]
        for d in range(N):  # u = x_K - x_L, minimum image (space.Space.displacement)
            u[d] = x[a, d] - x[b, d]
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
        if need_r:
            r2 = 0.0
            for d in range(N):
                r2 += u[d] * u[d]
            r_out[q] = np.sqrt(r2)
        if need_d:
            d2 = 0.0
            for r in range(N):
                ak = 0.0
                al = 0.0
                for c in range(N):
                    ak += binv[a, r, c] * u[c]
                    al += binv[b, r, c] * u[c]
                d2 += ak * ak + al * al
            d_out[q] = np.sqrt(0.5 * d2)
        if need_det:
            det_out[q] = det[b] / det[a]
        if k_powers > 0:
            for r in range(N):
                for c in range(N):
                    acc = 0.0
                    for k in range(N):
                        acc += phi[a, k, r] * phi[b, k, c]
                    m[r, c] = acc
            _power_traces(m, k_powers, mats, k_out, q)
        if m_powers > 0:
            if m_powers == 1:  # Tr(B_K phi_L) without forming Gamma
                acc = 0.0
                acc_s = 0.0
                for r in range(N):
                    for k in range(N):
                        acc += binv[a, r, k] * phi[b, k, r]
                        acc_s += binv[b, r, k] * phi[a, k, r]
                m_out[q, 0] = acc
                if swapped:
                    ms_out[q, 0] = acc_s
            else:
                for r in range(N):
                    for c in range(N):
                        acc = 0.0
                        for k in range(N):
                            acc += binv[a, r, k] * phi[b, k, c]
                        m[r, c] = acc
                _power_traces(m, m_powers, mats, m_out, q)
                if swapped:
                    for r in range(N):
                        for c in range(N):
                            acc = 0.0
                            for k in range(N):
                                acc += binv[b, r, k] * phi[a, k, c]
                            m[r, c] = acc
                    _power_traces(m, m_powers, mats, ms_out, q)

@_inline
def _weight(m, powers, partial_row, mats, w):
    """mats[a] = m^a; w = sum_a (a+1) partial_row[a] m^a."""
    for r in range(N):
        for c in range(N):
            mats[0, r, c] = 1.0 if r == c else 0.0
            w[r, c] = partial_row[0] if r == c else 0.0
    for a in range(1, powers):
        for r in range(N):
            for c in range(N):
                acc = 0.0
                for k in range(N):
                    acc += mats[a - 1, r, k] * m[k, c]
                mats[a, r, c] = acc
                w[r, c] += (a + 1) * partial_row[a] * acc

@_jit
def _scatter(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges,
             g_r, g_d, g_det, g_k, g_m, g_ms, need_r, need_d, need_det,
             k_powers, m_powers, swapped, gx, gphi, gb, gdet):
    """Closed-form geometric derivatives of pairs start..stop-1, summed per body (u, r, D
    and det Gamma recomputed exactly as :func:`_geometry` computed them)."""
    m = np.empty((N, N))
    w = np.empty((N, N))
    mats = np.empty((max(1, max(k_powers, m_powers)), N, N))
    u = np.empty(N)
    s = np.empty(N)
    ak = np.empty(N)
    al = np.empty(N)
    for p in range(start, stop):
        q = p - start
        a, b = i[p], j[p]
        # the minimum image again, written out as in _geometry: measured at 4096 bodies, an
        # inlined Numba helper made both kernels ~30 % slower, a called one 1.3-2x slower
        for d in range(N):  # u = x_K - x_L, minimum image (space.Space.displacement)
            u[d] = x[a, d] - x[b, d]
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
        if need_r and g_r[q] != 0.0:
            r2 = 0.0
            for d in range(N):
                r2 += u[d] * u[d]
            r = np.sqrt(r2)
            if r > 0:
                c = g_r[q] / r
                for d in range(N):
                    gx[a, d] += c * u[d]
                    gx[b, d] -= c * u[d]
        if need_d and g_d[q] != 0.0:
            d2 = 0.0
            for r in range(N):
                sk = 0.0
                sl = 0.0
                for k in range(N):
                    sk += binv[a, r, k] * u[k]
                    sl += binv[b, r, k] * u[k]
                ak[r] = sk
                al[r] = sl
                d2 += sk * sk + sl * sl
            dist = np.sqrt(0.5 * d2)
            if dist > 0:
                c = g_d[q] / (2.0 * dist)
                for k in range(N):
                    gu = 0.0
                    for r in range(N):
                        gu += binv[a, r, k] * ak[r] + binv[b, r, k] * al[r]
                    gx[a, k] += c * gu
                    gx[b, k] -= c * gu
                for r in range(N):
                    for k in range(N):
                        gb[a, r, k] += c * ak[r] * u[k]
                        gb[b, r, k] += c * al[r] * u[k]
        if need_det and g_det[q] != 0.0:
            gdet[b] += g_det[q] / det[a]
            gdet[a] -= g_det[q] * (det[b] / det[a]) / det[a]
        if k_powers > 0:
            for r in range(N):
                for c in range(N):
                    acc = 0.0
                    for k in range(N):
                        acc += phi[a, k, r] * phi[b, k, c]
                    m[r, c] = acc
            _weight(m, k_powers, g_k[q], mats, w)
            for r in range(N):  # phi_K += phi_L W, phi_L += phi_K W^T
                for c in range(N):
                    acc_k = 0.0
                    acc_l = 0.0
                    for k in range(N):
                        acc_k += phi[b, r, k] * w[k, c]
                        acc_l += phi[a, r, k] * w[c, k]
                    gphi[a, r, c] += acc_k
                    gphi[b, r, c] += acc_l
        if m_powers > 0:
            for side in range(2 if swapped else 1):
                k_body, l_body = (a, b) if side == 0 else (b, a)
                row = g_m[q] if side == 0 else g_ms[q]
                if m_powers == 1:
                    c = row[0]
                    for r in range(N):  # B_K += c phi_L^T, phi_L += c B_K^T
                        for k in range(N):
                            gb[k_body, r, k] += c * phi[l_body, k, r]
                            gphi[l_body, r, k] += c * binv[k_body, k, r]
                    continue
                for r in range(N):
                    for c in range(N):
                        acc = 0.0
                        for k in range(N):
                            acc += binv[k_body, r, k] * phi[l_body, k, c]
                        m[r, c] = acc
                _weight(m, m_powers, row, mats, w)
                for r in range(N):  # B_K += (phi_L W)^T, phi_L += (W B_K)^T
                    for c in range(N):
                        acc_b = 0.0
                        acc_p = 0.0
                        for k in range(N):
                            acc_b += phi[l_body, c, k] * w[k, r]
                            acc_p += w[c, k] * binv[k_body, k, r]
                        gb[k_body, r, c] += acc_b
                        gphi[l_body, r, c] += acc_p

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

@_jit
def _virial(start, stop, i, j, x, binv, mode, h, h_inv, edges, g_r, g_d, need_r, need_d,
            w_out):
    """w_out -= sum over pairs start..stop-1 of u (dV/du)^T, dV/du from the partials df/dr
    and df/dD (the configurational virial, pair_kernels.pair_virial). The minimum image and
    dD/du are written out as in _scatter, for the reason given there (inlined helpers ~30 %
    slower, measured)."""
    u = np.empty(N)
    s = np.empty(N)
    gu = np.empty(N)
    ak = np.empty(N)
    al = np.empty(N)
    for p in range(start, stop):
        q = p - start
        a, b = i[p], j[p]
        for d in range(N):  # u = x_K - x_L, minimum image (space.Space.displacement)
            u[d] = x[a, d] - x[b, d]
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
        for d in range(N):
            gu[d] = 0.0
        if need_r and g_r[q] != 0.0:
            r2 = 0.0
            for d in range(N):
                r2 += u[d] * u[d]
            r = np.sqrt(r2)
            if r > 0:
                for d in range(N):
                    gu[d] += g_r[q] / r * u[d]
        if need_d and g_d[q] != 0.0:
            d2 = 0.0
            for r in range(N):
                sk = 0.0
                sl = 0.0
                for k in range(N):
                    sk += binv[a, r, k] * u[k]
                    sl += binv[b, r, k] * u[k]
                ak[r] = sk
                al[r] = sl
                d2 += sk * sk + sl * sl
            dist = np.sqrt(0.5 * d2)
            if dist > 0:
                c = g_d[q] / (2.0 * dist)
                for k in range(N):
                    acc = 0.0
                    for r in range(N):
                        acc += binv[a, r, k] * ak[r] + binv[b, r, k] * al[r]
                    gu[k] += c * acc
        for r in range(N):
            for c in range(N):
                w_out[r, c] -= u[r] * gu[c]
