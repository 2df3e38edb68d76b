"""Source of the fused host pair kernel for a pair term whose f is a config expression
(:mod:`affinebody.pair_kernels`): geometry, f and its partial derivatives, chain rule and
per-body sums in one compiled loop over the pairs, one pair at a time, with nothing stored in
between.

:func:`fused_source` writes, for one expression, cut-off and dimension, the code appended to
the pair kernels of :mod:`affinebody._host_kernels.pair` (``_host.specialized("pair",
extra=...)``, so the file, hence the disk cache, is named by a hash that includes the
expression): ``_f`` (f and its partials, :func:`affinebody.expressions.derivative_source`)
and ``_fused``, whose loop body is, per pair, the geometry of
:class:`affinebody._host_kernels.pair_source.Pair` (the cut-off variable first), what
``PairTerm.energy_from_scalars`` does around f (the cut-off mask on its variable, the quintic
switch and its derivative, the average over both orders of an asymmetric pair with
det -> 1/det and M_a -> M'_a), then the chain rule into the per-body sums and, for the
barostat's pass, the configurational virial.

Pairs at or beyond the cut-off are skipped: their energy and partials are 0, as the
``jnp.where`` masks of ``energy_from_scalars`` give them.
"""

from __future__ import annotations

from affinebody._host_kernels.pair_source import Pair, indent
from affinebody.expressions import CompiledExpression, derivative_source


def _scalar(name: str, swapped: bool) -> tuple[str, str]:
    """(the value of pair variable ``name`` in the loop, the partial it accumulates into),
    named as :class:`Pair` names them; ``swapped``: in the order L, K."""
    if name in ("r", "D"):
        column = name.lower()
        return f"s_{column}", f"g_{column}"
    if name == "det":  # the swapped order sees det Gamma' = 1/det Gamma
        return ("1.0 / s_det", "g_det") if swapped else ("s_det", "g_det")
    letter, a = name[0], int(name[1:]) - 1
    column = "ms" if letter == "M" and swapped else letter.lower()
    return f"s_{column}{a}", f"g_{column}{a}"


def _energy(pair: Pair, expression: CompiledExpression, asymmetric: bool,
            cutoff_variable: str, r_on: float, r_cut: float) -> list[str]:
    """The lines that add the pair's energy to ``energy`` and set the partials ``g_...`` of
    f times the switch (eq. (59) averaged over both orders where ``asymmetric``)."""
    used = expression.used
    orders = (False, True) if asymmetric else (False,)
    s, g_s = _scalar(cutoff_variable, False)
    width = r_cut - r_on
    lines = [f"g{name[1:]} = 0.0" for name in pair.scalars()]
    lines += [
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
        lines.append(f"{outputs} = _f({', '.join(values)})")
        lines.append(f"e += f{k} * sw")
        lines.append(f"ds += f{k} * dsw")
        for name in used:
            chain = " * (-1.0 / (s_det * s_det))" if name == "det" and swap else ""
            lines.append(f"{_scalar(name, swap)[1]} += d{k}_{name} * sw{chain} / {len(orders)}.0")
    return lines + [f"{g_s} += ds / {len(orders)}.0", f"energy += e / {len(orders)}.0"]


def fused_source(expression: CompiledExpression, n: int, plain: frozenset, k_powers: int,
                 m_powers: int, swapped: bool, asymmetric: bool, cutoff_variable: str,
                 r_on: float, r_cut: float) -> str:
    """The code appended to the pair kernels for a pair term ``f = expression`` in dimension
    ``n`` (``plain``, ``k_powers``, ``m_powers``, ``swapped``: the scalars f needs, as
    ``pair_kernels`` reads them from ``PairTerm.scalar_requirements``; ``asymmetric``: f is
    averaged over both orders; the cut-off on ``cutoff_variable`` switched from ``r_on`` to
    ``r_cut``)."""
    pair = Pair(n, frozenset(plain), k_powers, m_powers, swapped)
    # the cut-off variable first: a pair beyond it costs only that
    if cutoff_variable == "r":
        first = pair.distance()
        rest = pair.loads() + (pair.affine_distance() if "D" in pair.plain else [])
    else:
        first = pair.loads() + pair.affine_distance()
        rest = pair.distance() if "r" in pair.plain else []
    cut = _scalar(cutoff_variable, False)[0]
    body = ["a = i[p]", "b = j[p]", *pair.displacement(), *first,
            f"if not {cut} < {r_cut!r}:  # masked: no energy, no partials",
            "    continue", *rest, *pair.invariants(),
            *_energy(pair, expression, asymmetric, cutoff_variable, r_on, r_cut),
            "if gradients or virial:", *indent(pair.force(), 1),
            "    if gradients:", *indent(pair.scatter(), 2),
            "    if virial:", *indent(pair.virial_lines(), 2)]
    lines = [
        "import math",
        "",
        "_TWO_OVER_SQRT_PI = 2.0 / math.sqrt(math.pi)",
        "",
        "",
        "@_inline_loop",
        derivative_source(expression, "_f"),
        "",
        "",
        "@_inline_loop",
        "def _fused(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges, gradients,",
        "           virial, gx, gphi, gb, gdet, w_out):",
        '    """Energy of pairs start..stop-1 (cut-off and switch included); with ``gradients``',
        "    their closed-form derivatives summed per body into gx, gphi, gb, gdet; with",
        "    ``virial`` their configurational virial -sum u (dV/du)^T added into w_out (from the",
        '    partials df/dr and df/dD: the other pair scalars do not depend on u)."""',
        *indent(pair.prologue() + pair.virial_start() + ["energy = 0.0"], 1),
        "    for p in range(start, stop):",
        *indent(body, 2),
        *indent(pair.virial_end() + ["return energy"], 1),
    ]
    return "\n".join(lines) + "\n"


__all__ = ["fused_source"]
