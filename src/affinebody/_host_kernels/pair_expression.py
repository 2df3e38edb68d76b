"""Source of the fused host pair kernel for a pair term whose f is a config expression
(:mod:`affinebody.pair_kernels`): geometry, f and its partial derivatives, chain rule and
per-body sums in one compiled loop, with no pair scalars handed to XLA in between.

:func:`fused_source` writes, for one expression, cut-off and dimension, the code appended to
the pair kernels of :mod:`affinebody._host_kernels.pair` (``_host.specialized("pair",
extra=...)``, so the file, hence the disk cache, is named by a hash that includes the
expression): ``_f`` (f and its partials, :func:`affinebody.expressions.derivative_source`),
``_pair_energies`` (what ``PairTerm.energy_from_scalars`` does around f: the cut-off mask on
its variable, the quintic switch and its derivative, the average over both orders of an
asymmetric pair with det -> 1/det and M_a -> M'_a) and ``_fused``, which runs blocks of
:data:`BLOCK` pairs through ``_geometry`` -> ``_pair_energies`` -> ``_scatter`` (the scalars
of a block stay in a few kB of scratch arrays), or, for the barostat's pass, through
``_geometry`` -> ``_pair_energies`` -> ``_virial`` (the energy and the virial).

Pairs at or beyond the cut-off are skipped: their energy and partials are 0, as the
``jnp.where`` masks of ``energy_from_scalars`` give them.
"""

from __future__ import annotations

from affinebody.expressions import CompiledExpression, derivative_source

#: Pairs per block of the fused loop (the scalars and partials of a block: ~10 kB).
BLOCK = 256

_FUSED = '''
@_jit
def _fused(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges, gradients, virial,
           gx, gphi, gb, gdet, w_out):
    """Energy of pairs start..stop-1 (cut-off and switch included); with ``gradients``
    their closed-form derivatives summed per body into gx, gphi, gb, gdet (as _scatter); with
    ``virial`` their configurational virial -sum u (dV/du)^T added into w_out (as _virial,
    from the partials df/dr and df/dD: the other pair scalars do not depend on u)."""
    # the scalars r, D, det, K, M, M' of a block and their partials (rows of scratch arrays)
    plain = np.zeros((2, 3, BLOCK))
    powers = np.zeros((2, 3, BLOCK, max(1, K_POWERS, M_POWERS)))
    s_r, s_d, s_det = plain[0, 0], plain[0, 1], plain[0, 2]
    g_r, g_d, g_det = plain[1, 0], plain[1, 1], plain[1, 2]
    s_k, s_m, s_ms = powers[0, 0], powers[0, 1], powers[0, 2]
    g_k, g_m, g_ms = powers[1, 0], powers[1, 1], powers[1, 2]
    energy = 0.0
    for lo in range(start, stop, BLOCK):
        hi = min(lo + BLOCK, stop)
        _geometry(lo, hi, i, j, x, phi, binv, det, mode, h, h_inv, edges, NEED_R, NEED_D,
                  NEED_DET, K_POWERS, M_POWERS, SWAPPED, s_r, s_d, s_det, s_k, s_m, s_ms)
        energy += _pair_energies(hi - lo, s_r, s_d, s_det, s_k, s_m, s_ms,
                                 g_r, g_d, g_det, g_k, g_m, g_ms)
        if gradients:
            _scatter(lo, hi, i, j, x, phi, binv, det, mode, h, h_inv, edges, g_r, g_d,
                     g_det, g_k, g_m, g_ms, NEED_R, NEED_D, NEED_DET, K_POWERS, M_POWERS,
                     SWAPPED, gx, gphi, gb, gdet)
        if virial:
            _virial(lo, hi, i, j, x, binv, mode, h, h_inv, edges, g_r, g_d, NEED_R, NEED_D,
                    w_out)
    return energy
'''


def _scalar(name: str, swapped: bool) -> tuple[str, str]:
    """(the value of pair variable ``name`` in row q, the partial it accumulates into)."""
    if name in ("r", "D"):
        column = name.lower()
        return f"s_{column}[q]", f"g_{column}[q]"
    if name == "det":  # the swapped order sees det Gamma' = 1/det Gamma
        return ("1.0 / s_det[q]", "g_det[q]") if swapped else ("s_det[q]", "g_det[q]")
    letter, a = name[0], int(name[1:]) - 1
    column = "ms" if letter == "M" and swapped else letter.lower()
    return f"s_{column}[q, {a}]", f"g_{column}[q, {a}]"


def fused_source(expression: CompiledExpression, n: int, plain: frozenset, k_powers: int,
                 m_powers: int, swapped: bool, asymmetric: bool, cutoff_variable: str,
                 r_on: float, r_cut: float) -> str:
    """The code appended to the pair kernels for a pair term ``f = expression`` in dimension
    ``n`` (``plain``, ``k_powers``, ``m_powers``, ``swapped``: the scalars f needs, as
    ``pair_kernels`` reads them from ``PairTerm.scalar_requirements``; ``asymmetric``: f is
    averaged over both orders; the cut-off on ``cutoff_variable`` switched from ``r_on`` to
    ``r_cut``)."""
    used = expression.used
    orders = (False, True) if asymmetric else (False,)
    s, g_s = _scalar(cutoff_variable, False)
    width = r_cut - r_on
    lines = [
        "import math",
        "",
        "_jit_numpy = numba.njit(fastmath=False, boundscheck=False, nogil=True, cache=CACHE,",
        "                        error_model='numpy')",
        "_TWO_OVER_SQRT_PI = 2.0 / math.sqrt(math.pi)",
        f"BLOCK = {BLOCK}",
        f"NEED_R = {'r' in plain}",
        f"NEED_D = {'D' in plain}",
        f"NEED_DET = {'det' in plain}",
        f"K_POWERS = {k_powers}",
        f"M_POWERS = {m_powers}",
        f"SWAPPED = {swapped}",
        "",
        "",
        "@_jit_numpy",
        derivative_source(expression, "_f"),
        "",
        "@_jit_numpy",
        "def _pair_energies(rows, s_r, s_d, s_det, s_k, s_m, s_ms, g_r, g_d, g_det, g_k, g_m,",
        "                   g_ms):",
        '    """Energies of rows 0..rows-1 summed, and df/dq of each row into g_q."""',
        "    energy = 0.0",
        "    for q in range(rows):",
    ]
    body = []
    for name in sorted(plain):
        body.append(f"{_scalar(name, False)[1]} = 0.0")
    for letter, powers in (("k", k_powers), ("m", m_powers), ("ms", m_powers if swapped else 0)):
        for a in range(powers):
            body.append(f"g_{letter}[q, {a}] = 0.0")
    body += [
        f"if not {s} < {r_cut!r}:  # masked: no energy, no partials",
        "    continue",
        f"t = min(max(({s} - {r_on!r}) / {width!r}, 0.0), 1.0)",
        "sw = 1.0 - t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)",
        "dsw = -(3.0 * t * t * (10.0 - 15.0 * t + 6.0 * t * t) + t * t * t * (12.0 * t - 15.0))"
        f" / {width!r}",
        "e = 0.0",
        "ds = 0.0",
    ]
    for k, swap in enumerate(orders):
        values = [_scalar(name, swap)[0] for name in used]
        outputs = ", ".join([f"f{k}"] + [f"d{k}_{name}" for name in used])
        body.append(f"{outputs} = _f({', '.join(values)})")
        body.append(f"e += f{k} * sw")
        body.append(f"ds += f{k} * dsw")
        for name in used:
            chain = " * (-1.0 / (s_det[q] * s_det[q]))" if name == "det" and swap else ""
            body.append(f"{_scalar(name, swap)[1]} += d{k}_{name} * sw{chain} / {len(orders)}.0")
    body += [f"{g_s} += ds / {len(orders)}.0", f"energy += e / {len(orders)}.0"]
    lines += [f"        {line}" for line in body]
    lines += ["    return energy", "", _FUSED]
    return "\n".join(lines)


__all__ = ["BLOCK", "fused_source"]
