"""Source of the host pair kernels, written out per pair term and dimension: the pair
geometry (u, r, D, det Gamma, K_a, M_a, M'_a) and its closed-form chain rule as straight-line
code over named scalars, one pair at a time (docs/performance.md, "Pair kernels
(`affinebody.pair_kernels`)", which derives the closed forms).

Why generated: Numba keeps scalars in registers, but a small array (a 3-vector made with
``np.empty``) lives in memory, and LLVM reloads it around every store into an output array,
which might alias it. Written with arrays, one pair of the demo potential cost 99 ns on one
core; written out as scalars, geometry, f and chain rule in one loop, 53-54 ns
(``benchmarks/step_phases.py --bodies 4096``; docs/performance.md, "Pair kernels
(`affinebody.pair_kernels`)").

The formulas: for bodies K = a, L = b of a pair,
u = x_K - x_L (minimum image), r = |u|, D^2 = (|B_K u|^2 + |B_L u|^2) / 2 with B = phi^-1
(eq. (75)), det Gamma = det phi_L / det phi_K (eq. (79)), K_a = Tr((phi_K^T phi_L)^a)
(eq. (28)), M_a = Tr((B_K phi_L)^a) and M'_a the same with K and L exchanged (eq. (30)). From the
partials g_q = df/dq of a pair, with W = sum_a a g_{q_a} m^(a-1) for q_a = Tr(m^a):

- dV/dx_K = -dV/dx_L = g_r u / r + g_D (B_K^T B_K u + B_L^T B_L u) / (2 D);
- dV/dB_K += g_D (B_K u) u^T / (2 D) + (phi_L W_M)^T, and the same for L with B_L, W_M';
- dV/dphi_K += phi_L W_K + (W_M' B_L)^T, dV/dphi_L += phi_K W_K^T + (W_M B_K)^T;
- dV/d det phi_L += g_det / det phi_K, dV/d det phi_K -= g_det det Gamma / det phi_K.

The chain rule through B = phi^-1 and det phi is applied per body afterwards
(``pair._merge_finish``, or ``pair_kernels._finish`` in JAX).

:func:`kernels_source` writes the three kernels of the two-callback path (f in XLA between
them): ``_geometry``, ``_scatter`` and ``_virial``; :mod:`.pair_expression` writes the fused
kernel from the same pieces (:class:`Pair`).
"""

from __future__ import annotations

from typing import NamedTuple


def _sum(terms: list[str]) -> str:
    """The source of the sum of ``terms`` (0.0 when there are none)."""
    return " + ".join(terms) if terms else "0.0"


class Pair(NamedTuple):
    """The pieces of code for one pair term in dimension n (``plain``: the plain scalars among
    r, D, det; ``k_powers``, ``m_powers``: how many traces of powers of K and M; ``swapped``:
    whether M'_a is needed too). Each piece is a list of lines of the loop body over pairs,
    with ``a``, ``b`` the two bodies; the scalars are named ``s_r``, ``s_d``, ``s_det``,
    ``s_k{a}``, ``s_m{a}``, ``s_ms{a}`` (a = 0: the trace of the first power) and their
    partials ``g_...`` alike."""

    n: int
    plain: frozenset
    k_powers: int
    m_powers: int
    swapped: bool

    @property
    def needs_binv(self) -> bool:
        return "D" in self.plain or self.m_powers > 0

    @property
    def needs_phi(self) -> bool:
        return self.k_powers > 0 or self.m_powers > 0

    def scalars(self) -> list[str]:
        """The scalar names, in the order of ``pair_kernels.scalar_columns``."""
        names = [{"r": "s_r", "D": "s_d", "det": "s_det"}[q] for q in sorted(self.plain)]
        for letter, powers in (("k", self.k_powers), ("m", self.m_powers),
                               ("ms", self.m_powers if self.swapped else 0)):
            names += [f"s_{letter}{a}" for a in range(powers)]
        return names

    # -- before the loop ---------------------------------------------------------------------

    def prologue(self) -> list[str]:
        """The box as scalars: edges (mode 1) and the cell and its inverse (mode 2)."""
        n = self.n
        lines = [f"e{d} = edges[{d}]" for d in range(n)]
        for r in range(n):
            for c in range(n):
                lines += [f"h{r}{c} = h[{r}, {c}]", f"hi{r}{c} = h_inv[{r}, {c}]"]
        return lines

    # -- the geometry ------------------------------------------------------------------------

    def displacement(self) -> list[str]:
        """u = x_K - x_L, minimum image as ``space.Space.displacement``: mode 0 free space,
        1 an orthorhombic box, 2 a general cell (fractional coordinates rounded)."""
        n = range(self.n)
        lines = [f"u{d} = x[a, {d}] - x[b, {d}]" for d in n]
        lines += ["if mode == 1:"]
        lines += [f"    u{d} -= e{d} * np.round(u{d} / e{d})" for d in n]
        lines += ["elif mode == 2:"]
        lines += [f"    fr{d} = {_sum([f'hi{d}{e} * u{e}' for e in n])}" for d in n]
        lines += [f"    fr{d} -= np.round(fr{d})" for d in n]
        lines += [f"    u{d} = {_sum([f'h{d}{e} * fr{e}' for e in n])}" for d in n]
        return lines

    def loads(self) -> list[str]:
        """phi, B and det phi of both bodies as scalars (``ba{r}{c}`` = B_K[r, c], ...)."""
        n = range(self.n)
        lines = []
        for name, array, needed in (("b", "binv", self.needs_binv), ("p", "phi", self.needs_phi)):
            if needed:
                lines += [f"{name}{side}{r}{c} = {array}[{side}, {r}, {c}]"
                          for side in "ab" for r in n for c in n]
        if "det" in self.plain:
            lines += ["deta = det[a]", "detb = det[b]"]
        return lines

    def distance(self) -> list[str]:
        """r = |u|."""
        return [f"s_r = np.sqrt({_sum([f'u{d} * u{d}' for d in range(self.n)])})"]

    def affine_distance(self) -> list[str]:
        """k = B_K u, l = B_L u, D = sqrt((|k|^2 + |l|^2) / 2) (eq. (75))."""
        n = range(self.n)
        lines = [f"k{r} = {_sum([f'ba{r}{c} * u{c}' for c in n])}" for r in n]
        lines += [f"l{r} = {_sum([f'bb{r}{c} * u{c}' for c in n])}" for r in n]
        squares = [f"(k{r} * k{r} + l{r} * l{r})" for r in n]
        return lines + [f"s_d = np.sqrt(0.5 * ({_sum(squares)}))"]

    def invariants(self) -> list[str]:
        """det Gamma, and the traces of powers of m = phi_K^T phi_L (K_a), B_K phi_L (M_a),
        B_L phi_K (M'_a); the powers m^a of each (a >= 1) stay for the chain rule."""
        n = range(self.n)
        lines = ["s_det = detb / deta"] if "det" in self.plain else []
        products = [("k", self.k_powers, lambda r, c, k: f"pa{k}{r} * pb{k}{c}")]
        products.append(("m", self.m_powers, lambda r, c, k: f"ba{r}{k} * pb{k}{c}"))
        if self.swapped:
            products.append(("ms", self.m_powers, lambda r, c, k: f"bb{r}{k} * pa{k}{c}"))
        for name, powers, term in products:
            if powers == 0:
                continue
            if powers == 1:  # Tr m without forming m
                lines.append(f"s_{name}0 = {_sum([term(r, r, k) for r in n for k in n])}")
                continue
            for r in n:
                for c in n:
                    lines.append(f"{name}1_{r}{c} = {_sum([term(r, c, k) for k in n])}")
            for a in range(2, powers):
                for r in n:
                    for c in n:
                        lines.append(f"{name}{a}_{r}{c} = "
                                     + _sum([f"{name}{a - 1}_{r}{k} * {name}1_{k}{c}" for k in n]))
            for a in range(powers):  # Tr(m^(a+1)) = sum m^a[r, k] m[k, r]
                if a == 0:
                    lines.append(f"s_{name}0 = {_sum([f'{name}1_{r}{r}' for r in n])}")
                else:
                    lines.append(f"s_{name}{a} = " + _sum(
                        [f"{name}{a}_{r}{k} * {name}1_{k}{r}" for r in n for k in n]))
        return lines

    def geometry(self) -> list[str]:
        """All the scalars of the pair, after :meth:`displacement` and :meth:`loads`."""
        lines = self.distance() if "r" in self.plain else []
        lines += self.affine_distance() if "D" in self.plain else []
        return lines + self.invariants()

    # -- the chain rule ----------------------------------------------------------------------

    def _weight(self, name: str, powers: int):
        """(lines, entry): W = sum_a (a+1) g_{name}a m^a for the traces of m = ``name``,
        as a function entry(r, c) giving its entry's name, or None where it is 0."""
        n = range(self.n)
        if powers == 1:  # W = g I
            return [], lambda r, c: f"g_{name}0" if r == c else None
        lines = []
        for r in n:
            for c in n:
                terms = [f"g_{name}0"] if r == c else []
                terms += [f"{a + 1}.0 * g_{name}{a} * {name}{a}_{r}{c}" for a in range(1, powers)]
                lines.append(f"w{name}{r}{c} = {_sum(terms)}")
        return lines, lambda r, c: f"w{name}{r}{c}"

    def force(self) -> list[str]:
        """gu = dV/du (the r and D terms: the only scalars that depend on u), into ``gu{d}``."""
        n = range(self.n)
        if not self.has_force:
            return []
        lines = []
        if "r" in self.plain:
            lines.append("c_r = g_r / s_r if s_r > 0.0 else 0.0")
        if "D" in self.plain:
            lines.append("c_d = g_d / (2.0 * s_d) if s_d > 0.0 else 0.0")
        for d in n:
            terms = [f"c_r * u{d}"] if "r" in self.plain else []
            if "D" in self.plain:
                inner = [f"ba{r}{d} * k{r}" for r in n] + [f"bb{r}{d} * l{r}" for r in n]
                terms.append(f"c_d * ({_sum(inner)})")
            lines.append(f"gu{d} = {_sum(terms)}")
        return lines

    @property
    def has_force(self) -> bool:
        return bool({"r", "D"} & self.plain)

    def scatter(self) -> list[str]:
        """The pair's derivatives added to its two bodies' sums gx, gphi, gb, gdet (after
        :meth:`force`)."""
        n = range(self.n)
        lines = []
        if self.has_force:
            lines += [f"gx[a, {d}] += gu{d}" for d in n] + [f"gx[b, {d}] -= gu{d}" for d in n]
        weights = {}
        for name, powers in (("k", self.k_powers), ("m", self.m_powers),
                             ("ms", self.m_powers if self.swapped else 0)):
            if powers:
                extra, weights[name] = self._weight(name, powers)
                lines += extra

        def product(left, right):  # the terms of sum_k left[k] right[k], zeros left out
            return [f"{x} * {y}" for x, y in zip(left, right, strict=True)
                    if x is not None and y is not None]

        def row(w, r):
            return [w(r, k) for k in n]

        def column(w, c):
            return [w(k, c) for k in n]

        for r in n:
            for c in n:
                terms = {("b", "a"): [], ("b", "b"): [], ("p", "a"): [], ("p", "b"): []}
                if "D" in self.plain:
                    terms["b", "a"].append(f"c_d * k{r} * u{c}")
                    terms["b", "b"].append(f"c_d * l{r} * u{c}")
                b_k = [f"ba{k}{r}" for k in n]  # column r of B_K, and of B_L
                b_l = [f"bb{k}{r}" for k in n]
                if "m" in weights:  # B_K += (phi_L W)^T, phi_L += (W B_K)^T
                    w = weights["m"]
                    terms["b", "a"] += product([f"pb{c}{k}" for k in n], column(w, r))
                    terms["p", "b"] += product(row(w, c), b_k)
                if "ms" in weights:
                    w = weights["ms"]
                    terms["b", "b"] += product([f"pa{c}{k}" for k in n], column(w, r))
                    terms["p", "a"] += product(row(w, c), b_l)
                if "k" in weights:  # phi_K += phi_L W, phi_L += phi_K W^T
                    w = weights["k"]
                    terms["p", "a"] += product([f"pb{r}{k}" for k in n], column(w, c))
                    terms["p", "b"] += product([f"pa{r}{k}" for k in n], row(w, c))
                for (kind, side), added in terms.items():
                    if added:
                        array = "gb" if kind == "b" else "gphi"
                        lines.append(f"{array}[{side}, {r}, {c}] += {_sum(added)}")
        if "det" in self.plain:
            lines += ["gdet[b] += g_det / deta", "gdet[a] -= g_det * s_det / deta"]
        return lines

    def virial_lines(self) -> list[str]:
        """The pair's configurational virial -u (dV/du)^T added to ``v{r}{c}`` (after
        :meth:`force`)."""
        n = range(self.n)
        return [f"v{r}{c} -= u{r} * gu{c}" for r in n for c in n] if self.has_force else []

    def virial_start(self) -> list[str]:
        return [f"v{r}{c} = 0.0" for r in range(self.n) for c in range(self.n)]

    def virial_end(self) -> list[str]:
        return [f"w_out[{r}, {c}] += v{r}{c}" for r in range(self.n) for c in range(self.n)]


def indent(lines: list[str], depth: int) -> list[str]:
    return [" " * (4 * depth) + line for line in lines]


def _columns(pair: Pair) -> list[tuple[str, str]]:
    """(scalar name, how its row is indexed in the column arrays): the arrays ``out_r``,
    ``out_d``, ``out_det`` [rows] and ``out_k``, ``out_m``, ``out_ms`` [rows, powers]."""
    out = []
    for name in pair.scalars():
        column = name[2:].rstrip("0123456789")
        index = name[2 + len(column):]
        out.append((name, f"{column}[q, {index}]" if index else f"{column}[q]"))
    return out


def kernels_source(n: int, plain: frozenset, k_powers: int, m_powers: int,
                   swapped: bool) -> str:
    """The kernels of the two-callback path for one pair term (f evaluated by XLA between
    them), appended to ``pair.py``: ``_geometry`` (the scalars of pairs start..stop-1 into
    rows 0..stop-start-1 of ``out_*``), ``_scatter`` (their derivatives from the partials
    ``in_*``, summed per body) and ``_virial`` (-sum u (dV/du)^T into w_out)."""
    pair = Pair(n, frozenset(plain), k_powers, m_powers, swapped)
    columns = _columns(pair)
    arrays = ("r", "d", "det", "k", "m", "ms")
    start = ["for p in range(start, stop):", "    q = p - start", "    a = i[p]", "    b = j[p]"]
    body = pair.displacement() + pair.loads() + pair.geometry()
    geometry = ["@_jit_loop",
                "def _geometry(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges, "
                + ", ".join(f"out_{a}" for a in arrays) + "):"]
    geometry += indent(pair.prologue() + start, 1) + indent(body, 2)
    geometry += indent([f"out_{column} = {name}" for name, column in columns], 2)
    scatter = ["@_jit_loop",
               "def _scatter(start, stop, i, j, x, phi, binv, det, mode, h, h_inv, edges, "
               + ", ".join(f"in_{a}" for a in arrays) + ", gx, gphi, gb, gdet):"]
    partials = [f"g{name[1:]} = in_{column}" for name, column in columns]
    scatter += indent(pair.prologue() + start, 1)
    scatter += indent(body + partials + pair.force() + pair.scatter(), 2)
    # the virial needs only u, r and D
    moving = Pair(n, frozenset(plain) & {"r", "D"}, 0, 0, False)
    virial = ["@_jit_loop", "def _virial(start, stop, i, j, x, binv, mode, h, h_inv, edges, in_r, "
              "in_d, w_out):"]
    virial += indent(moving.prologue() + moving.virial_start() + start, 1)
    moving_partials = [f"g{name[1:]} = in_{column}" for name, column in _columns(moving)]
    virial += indent(moving.displacement() + moving.loads() + moving.geometry()
                     + moving_partials + moving.force() + moving.virial_lines(), 2)
    virial += indent(moving.virial_end(), 1)
    return "\n".join(geometry + ["", ""] + scatter + ["", ""] + virial) + "\n"


__all__ = ["Pair", "indent", "kernels_source"]
