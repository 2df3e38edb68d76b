"""Fast pair energy and generalised forces over a list of pairs: the binary potentials
(59)-(62), (75)-(78) of :mod:`affinebody.potentials` with the chain rule split in two.

A pair term is ``V_KL = f(r, D, det, K_a, M_a)`` (cut-off, switch and the average over both
orders of (59) included, :meth:`PairTerm.energy_from_scalars`). Its gradient is

    dV/dz = sum over the scalars q of (df/dq) (dq/dz),   z = x_K, phi_K, x_L, phi_L,

where **autodiff touches only the scalar function f** (elementwise over pairs, so one reverse
pass gives df/dq for every pair), and the geometric derivatives dq/dz are written once, in
closed form, in terms of per-body quantities computed once per evaluation, not per pair:
B_K = phi_K^-1 and det phi_K. With u = x_K - x_L (minimum image), a_K = B_K u,
Gamma = B_K phi_L (21), Gamma' = B_L phi_K, G = phi_K^T phi_L (20):

==========================  ====================================================================
r = |u|                     dr/du = u / r
D^2 = (|a_K|^2+|a_L|^2)/2   dD/du = (B_K^T a_K + B_L^T a_L)/(2D), dD/dB_K = a_K u^T/(2D)   (75)
det = det phi_L/det phi_K   d/d(det phi_L) = 1/det phi_K, d/d(det phi_K) = -det/det phi_K   (79)
M_a = Tr(Gamma^a)           with W = sum_a a (df/dM_a) Gamma^(a-1):
                            df/dB_K = (phi_L W)^T, df/dphi_L = (W B_K)^T                    (30)
M'_a = Tr(Gamma'^a)         the same with K and L exchanged (the swapped order of (59))
K_a = Tr(G^a)               with W = sum_a a (df/dK_a) G^(a-1):
                            df/dphi_K = phi_L W, df/dphi_L = phi_K W^T                      (28)
==========================  ====================================================================

The chain rule through B = phi^-1 and det phi,

    dV/dphi = (dV/dphi)_direct - B^T (dV/dB) B^T + (dV/d det) det(phi) B^T,

is applied once per body by the host kernel (contributions summed per body first: dV/dx,
dV/dphi direct, dV/dB, dV/d det) and per pair by the JAX kernel, where it simplifies
(:func:`_chunk_contributions`) and each pair then adds one row of n + n^2 numbers to each of its
bodies (one scatter per side: on a GPU, four narrower scatters per side and a per-body finish
made the forces at 10^6 bodies 58.8 ms where they take 44.4 ms, docs/performance.md).

Two implementations of the same formulas, same interface
``energy_and_gradients(pot, space, x, phi, i, j, count) -> (E, dV/dx, dV/dphi)``, and the
product runs both, one per backend (:func:`pair_sum` chooses):

- the host kernel (:func:`energy_and_gradients_host`): compiled CPU code (Numba) for the
  geometry and for the chain rule and per-body sums, reached from compiled JAX code through two host
  callbacks (``_host.callback``) per chunk of pairs, with f and its partial derivatives evaluated by
  XLA between them (fused, elementwise); where f is a config expression (``PairTerm.expression``:
  ``kind = "pair"``, and the Lennard-Jones, Morse and Gaussian families), one callback for the whole
  list instead, f and its partials compiled into the same loop
  (:mod:`affinebody._host_kernels.pair_expression`) and the chain rule through B and det phi
  applied per body in Numba too. On a CPU the arrays stay in host
  memory, so the callbacks cost no transfer. Each chunk is split into
  :data:`affinebody._host.PARTS` fixed parts summed in a fixed order and run on as many threads as
  the process may use, so results do not depend on the core count;
- :func:`energy_and_gradients` in JAX (jit, CPU or GPU; chunks of pairs in a ``lax.scan`` so
  memory stays linear in N): the path on a GPU (no host round trip inside the loop) and where
  Numba is missing. Its per-pair arithmetic is :func:`_chunk_contributions` as XLA fuses it, or
  on a GPU the same formulas as two hand-written Pallas (Triton) kernels
  (:mod:`affinebody._pair_triton`; :func:`pair_program`).

:func:`neighbor_energy` wraps :func:`pair_sum` as a ``jax.custom_vjp`` energy, so ``jax.grad``
of a potential evaluated with a neighbour list uses these closed forms, whichever kernel runs.
``pair_sum(..., virial=True)`` also returns the virial W = -sum u (dV/du)^T of
:func:`pair_virial` from the same pass (an NPT step's last force evaluation,
``pressure.energy_forces_virial``).
"""

from __future__ import annotations

import functools
import types
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import _linalg as linalg
from affinebody import _pair_triton
from affinebody.expressions import CompiledExpression
from affinebody.space import Space

#: Pairs per pass of the JAX kernel on a CPU (where it runs without Numba, and in tests).
PAIR_CHUNK = 1 << 16
#: Pairs per pass of the JAX kernel on a GPU: every pass is a handful of kernel launches and
#: one trip of a device loop, so passes must be few and large (memory ~1 kB per pair of a pass).
ACCELERATOR_PAIR_CHUNK = 1 << 22
#: Largest chunk of pairs per host-kernel pass: bounds the pair scalars held at once (about
#: 0.15 GB) while keeping the per-chunk copies of the per-body sums few (10^6 bodies in 3D:
#: about 25 chunks per evaluation, their copies ~10 % of its time).
HOST_CHUNK_PAIRS = 1 << 21
#: Fewest pairs worth handing to threads (below, the parts run one after the other).
#: Re-measured for the fused kernel with its barrier (2026-11-28, two cores of the Intel VM,
#: ``step_phases.py``'s loop with this and the drift's threshold patched): at 8807 pairs (216
#: bodies) a pair evaluation took 0.69-0.74 ms on two threads against 0.86-0.92 on one, at
#: 13 990 pairs 1.01-1.10 against 1.56-1.62; smaller lattices do not fit the cut-off's box.
HOST_THREAD_MIN_ROWS = 4096


# --------------------------------------------------------------------------------------------
# shared pieces


def _requirements(pot, n: int):
    plain, k_powers, m_powers = pot.scalar_requirements(n)
    return plain, k_powers, m_powers, bool(pot.asymmetric) and m_powers > 0


def padding_value(name: str, n: int, r_cut: float) -> float:
    """The value of scalar ``name`` for a harmless padding pair: beyond the cut-off (r and D
    at 4 r_cut), identity configurations (det Gamma = 1, K_a = M_a = n)."""
    return 4.0 * r_cut if name in ("r", "D") else 1.0 if name == "det" else float(n)


def scalar_columns(plain, k_powers: int, m_powers: int, swapped: bool,
                   rows: int) -> dict[str, tuple[int, ...]]:
    """Shapes of the scalar pair arrays of ``rows`` pairs that f needs: r, D, det [rows] and
    K, M, Ms [rows, powers] (the ``base`` of ``PairTerm.energy_from_scalars``)."""
    out = {name: (rows,) for name in sorted(plain)}
    for name, powers in (("K", k_powers), ("M", m_powers), ("Ms", m_powers if swapped else 0)):
        if powers:
            out[name] = (rows, powers)
    return out


def _padding_base(pot, n: int, size: int, plain, k_powers, m_powers, swapped, xp=jnp):
    """Scalars of a harmless padding pair (:func:`padding_value`), ``size`` of each."""
    columns = scalar_columns(plain, k_powers, m_powers, swapped, size)
    return {name: xp.full(shape, padding_value(name, n, pot.cutoff.r_cut))
            for name, shape in columns.items()}


def _require_cutoff(pot) -> None:
    if getattr(pot, "cutoff", None) is None:
        raise ValueError(
            f"{type(pot).__name__}: a neighbour list needs a cut-off (set cutoff=Cutoff(r_cut))"
        )


def _scalar_values_and_partials(pot, n: int):
    """base -> (pair energies [P], df/dbase), one forward and one reverse elementwise pass."""

    def run(base):
        energies, pullback = jax.vjp(lambda b: pot.energy_from_scalars(b, n), base)
        (partials,) = pullback(jnp.ones_like(energies))
        return energies, partials

    return run


def pair_chunk() -> int:
    """Pairs per pass of :func:`energy_and_gradients` on the default backend."""
    return PAIR_CHUNK if jax.default_backend() == "cpu" else ACCELERATOR_PAIR_CHUNK


_mm = linalg.matmul


def _matrix_power_traces(m: jax.Array, powers: int) -> tuple:
    """Tr(m^a) for a = 1..powers and the list of matrix powers m^0..m^(powers-1)."""
    eye = jnp.broadcast_to(jnp.eye(m.shape[-1]), m.shape)
    mats = [eye]
    for _ in range(1, powers):
        mats.append(_mm(mats[-1], m))
    traces = [jnp.einsum("...ij,...ji->...", mats[a], m) for a in range(powers)]
    return jnp.stack(traces, axis=-1), mats


def _weighted(mats, partials) -> jax.Array:
    """W = sum_a a (df/dq_a) m^(a-1)."""
    return sum((a + 1) * partials[..., a, None, None] * mats[a] for a in range(len(mats)))


def _finish(phi, binv, det, g_phi, g_binv, g_det):
    binv_t = jnp.swapaxes(binv, -1, -2)
    return g_phi - binv_t @ g_binv @ binv_t + (g_det * det)[:, None, None] * binv_t


# --------------------------------------------------------------------------------------------
# JAX kernel


def _mm_t(a: jax.Array, b: jax.Array) -> jax.Array:
    """(a b)^T = b^T a^T over the last two axes, written so that no transposed copy of a
    product is stored (on a GPU a separate transpose is one more pass over the pairs)."""
    return _mm(jnp.swapaxes(b, -1, -2), jnp.swapaxes(a, -1, -2))


def _chunk_contributions(pot, space: Space, n, x, phi, binv, det, i, j, valid, cell=None):
    """Energy of one chunk of pairs and, per pair, dV/du [P, n] and the whole dV_KL/dphi_K,
    dV_KL/dphi_L [P, n, n], the chain rule through B = phi^-1 and det phi applied per pair
    (``cell``: the current cell of a box that a barostat deforms, or None).

    With dphi_K -= B_K^T (dV/dB_K) B_K^T and += (dV/d det phi_K) det(phi_K) B_K^T, the
    derivatives of the module docstring's table become, per scalar q (c_q = df/dq):

    - D (75): dphi_K -= c (B_K^T a_K) a_K^T with c = c_D / (2D) (as B_K^T a_K u^T B_K^T), the
      same with L;
    - det (79): dphi_L += c_det det B_L^T, dphi_K -= c_det det B_K^T;
    - M_a (30), Y = W B_K: dphi_L += Y^T, dphi_K -= (Gamma Y)^T (as B_K^T (phi_L W)^T B_K^T);
      M'_a the same with K and L exchanged;
    - K_a (28): dphi_K += phi_L W, dphi_L += phi_K W^T (no B involved).
    """
    plain, k_powers, m_powers, swapped = _requirements(pot, n)
    u = space.displacement(x[i], x[j], cell)
    phi_k, phi_l, b_k, b_l = phi[i], phi[j], binv[i], binv[j]
    base = {}
    r2 = jnp.sum(u * u, axis=-1)
    if "r" in plain:
        base["r"] = jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)) * (r2 > 0)
    if "D" in plain:
        a_k = jnp.einsum("pij,pj->pi", b_k, u)
        a_l = jnp.einsum("pij,pj->pi", b_l, u)
        d2 = 0.5 * (jnp.sum(a_k * a_k, -1) + jnp.sum(a_l * a_l, -1))
        base["D"] = jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)) * (d2 > 0)
    if "det" in plain:
        base["det"] = det[j] / det[i]
    if k_powers:
        g_mat = _mm(jnp.swapaxes(phi_k, -1, -2), phi_l)
        base["K"], k_mats = _matrix_power_traces(g_mat, k_powers)
    if m_powers:
        gamma = _mm(b_k, phi_l)
        base["M"], m_mats = _matrix_power_traces(gamma, m_powers)
        if swapped:
            gamma_s = _mm(b_l, phi_k)
            base["Ms"], ms_mats = _matrix_power_traces(gamma_s, m_powers)
    pad = _padding_base(pot, n, u.shape[0], plain, k_powers, m_powers, swapped)
    base = {key: jnp.where(valid.reshape(valid.shape + (1,) * (v.ndim - 1)), v, pad[key])
            for key, v in base.items()}
    energies, partials = _scalar_values_and_partials(pot, n)(base)
    g_u = jnp.zeros_like(u)
    d_phik = d_phil = jnp.zeros_like(phi_k)
    if "r" in plain:
        r = base["r"]
        g_u = g_u + (partials["r"] / jnp.where(r > 0, r, 1.0) * (r > 0))[:, None] * u
    if "D" in plain:
        dist = base["D"]
        c = partials["D"] / jnp.where(dist > 0, 2.0 * dist, 1.0) * (dist > 0)
        v_k = jnp.einsum("pji,pj->pi", b_k, a_k)
        v_l = jnp.einsum("pji,pj->pi", b_l, a_l)
        g_u = g_u + c[:, None] * (v_k + v_l)
        d_phik = d_phik - c[:, None, None] * v_k[:, :, None] * a_k[:, None, :]
        d_phil = d_phil - c[:, None, None] * v_l[:, :, None] * a_l[:, None, :]
    if "det" in plain:
        c = (partials["det"] * base["det"])[:, None, None]
        d_phil = d_phil + c * jnp.swapaxes(b_l, -1, -2)
        d_phik = d_phik - c * jnp.swapaxes(b_k, -1, -2)
    if k_powers:
        w = _weighted(k_mats, partials["K"])
        d_phik = d_phik + _mm(phi_l, w)
        d_phil = d_phil + _mm(phi_k, jnp.swapaxes(w, -1, -2))
    if m_powers:
        y = _mm(_weighted(m_mats, partials["M"]), b_k)
        d_phil = d_phil + jnp.swapaxes(y, -1, -2)
        d_phik = d_phik - _mm_t(gamma, y)
        if swapped:
            y = _mm(_weighted(ms_mats, partials["Ms"]), b_l)
            d_phik = d_phik + jnp.swapaxes(y, -1, -2)
            d_phil = d_phil - _mm_t(gamma_s, y)
    return jnp.sum(energies), (g_u, d_phik, d_phil)


def _pair_chunks(i, j, chunk: int):
    """The pair indices (i, j) and their positions, padded and cut into [chunks, chunk]."""
    capacity = i.shape[0]
    chunk = max(1, min(chunk, capacity))
    chunks = -(-capacity // chunk)
    fill = chunks * chunk - capacity
    index = jnp.arange(chunks * chunk).reshape(chunks, chunk)
    i_all = jnp.concatenate([i, jnp.zeros(fill, i.dtype)]).reshape(chunks, chunk)
    j_all = jnp.concatenate([j, jnp.zeros(fill, j.dtype)]).reshape(chunks, chunk)
    return i_all, j_all, index


def _pair_pass(pot, x, phi, i, j, chunk: int | None):
    """What a chunked pass over pairs needs: N, n, phi^-1, det phi, the chunked indices
    (``chunk`` pairs per pass, default :func:`pair_chunk`)."""
    _require_cutoff(pot)
    chunk = pair_chunk() if chunk is None else chunk
    bodies, n = x.shape
    return bodies, n, linalg.inv(phi), linalg.det(phi), _pair_chunks(i, j, chunk)


#: Whether :func:`_over_chunks` passes over the chunks of a list that hold only padding.
SKIP_PADDING_PASSES = True


def _over_chunks(step, init, chunks, starts, count):
    """``lax.scan`` of ``step(carry, chunk)`` over ``chunks`` (final carry only), passing
    over (``lax.cond``) each chunk whose first position ``starts[k]`` is at or past
    ``count``: such a chunk holds only padding pairs. A list's capacity has room to spare (at
    10^6 bodies 57.5 M pairs for 40.8 M in use: 14 passes where 10 hold pairs), and a pass
    over padding runs the same arithmetic as a pass over pairs (the JAX kernel's forces at
    32 768 bodies on a CPU: 660-684 ms with the skip, 772-860 ms without; docs/performance.md,
    "Running on an NVIDIA GPU"). With :data:`SKIP_PADDING_PASSES` off, every chunk is passed
    over (a GPU may pay for a conditional per pass: ``step_phases.py --no-padding-skip``
    times both there)."""
    def filled(carry, chunk):
        start, block = chunk
        if not SKIP_PADDING_PASSES:
            return step(carry, block), None
        return lax.cond(start < count, lambda c: step(c, block), lambda c: c, carry), None

    return lax.scan(filled, init, (starts, chunks))[0]


def _valid_pairs(ii, jj, idx, count, bodies: int):
    """(i, j, valid) of a chunk: pairs at positions >= count become a harmless pair (0, 1)."""
    valid = idx < count
    return (jnp.where(valid, ii, 0), jnp.where(valid, jj, jnp.minimum(1, bodies - 1)), valid)


#: How :func:`energy_and_gradients` may compute the rows of a chunk of pairs (its ``program``).
PAIR_PROGRAMS = ("xla", "triton", "triton-interpret")


#: The environment variable that chooses the program of :func:`pair_program` ("xla" or
#: "triton"), e.g. to time both on a GPU or to skip the check of the Triton kernels.
PAIR_PROGRAM_VARIABLE = "AFFINEBODY_PAIR_PROGRAM"


def pair_program(pot=None, n: int | None = None) -> str:
    """How :func:`energy_and_gradients` runs its passes over pairs by default: the program
    named by ``$AFFINEBODY_PAIR_PROGRAM`` if set; else on a GPU ``"triton"`` (the Pallas
    kernels of :mod:`affinebody._pair_triton`) when they build there for ``pot`` in dimension
    n (:func:`triton_builds`; a warning and ``"xla"`` when they do not), ``"xla"`` elsewhere."""
    import os

    chosen = os.environ.get(PAIR_PROGRAM_VARIABLE, "").strip()
    if chosen:
        products = [p for p in PAIR_PROGRAMS if p != "triton-interpret"]  # not the tests' one
        if chosen not in products:
            raise ValueError(f"{PAIR_PROGRAM_VARIABLE}={chosen}: expected "
                             f"{' or '.join(products)}")
        if chosen == "triton" and jax.default_backend() != "gpu":
            raise ValueError(f"{PAIR_PROGRAM_VARIABLE}=triton needs a GPU (JAX's backend here "
                             f"is {jax.default_backend()}): unset it or set it to xla")
        return chosen
    if jax.default_backend() != "gpu":
        return "xla"
    return "triton" if pot is None or triton_builds(*_triton_layout(pot, n)) else "xla"


@functools.cache
def triton_builds(layout, padding: tuple, program: str = "triton", energy=None) -> bool:
    """Whether the Triton kernels of ``layout`` build and run on the default backend (once per
    process and layout: one small chunk, compiled and run). A JAX whose Pallas has no Triton
    backend, or an XLA whose Triton rejects a kernel, would otherwise stop every run on a
    GPU; here it gives a warning, and the forces run as XLA programs (``"xla"``), which are
    the same formulas. ``program``: ``"triton-interpret"`` checks the interpreter instead.
    ``energy``: f as the partials kernel evaluates it (:class:`_pair_triton.ColumnEnergy`),
    checked with that kernel in place of the scalars kernel (where it does not build, f and
    its partials run in XLA between the two kernels instead)."""
    import warnings

    n, pairs = layout.n, _pair_triton.BLOCK
    eye = np.eye(n).reshape(-1)
    # two bodies at phi = Id, every pair (0, 1) at u = (1, ..., 1); numpy arrays, since this
    # may be called while a run is traced (the kernels are compiled and run apart from it)
    args = (np.ones((pairs, n)), np.zeros(pairs, np.int32), np.ones(pairs, np.int32),
            np.ones(pairs, bool), np.tile(np.concatenate([eye, eye, [1.0]]), 2))

    def chunk(u, i, j, valid, table):
        return _pair_triton.chunk_rows(layout, lambda base: (
            sum(jnp.sum(v, axis=tuple(range(1, v.ndim))) for v in base.values()),
            {name: jnp.ones_like(v) for name, v in base.items()}),
            padding, u, i, j, valid, table, interpret=program == "triton-interpret",
            energy=energy)

    try:
        compiled = jax.jit(chunk).lower(*args).compile()
        jax.block_until_ready(compiled(*args))
    except Exception as err:  # noqa: BLE001 - whatever stops them, the XLA programs run
        first = (str(err).strip().splitlines() or [""])[0][:200]
        what, instead = (("f in the Triton pair kernel does", "the Triton kernels with f in XLA "
                          "between them") if energy is not None
                         else ("the Triton pair kernels do", "XLA programs"))
        warnings.warn(f"{what} not build here ({type(err).__name__}: {first}); the pair "
                      f"forces run as {instead} (the same formulas; "
                      f"{PAIR_PROGRAM_VARIABLE}=xla skips this check)", RuntimeWarning,
                      stacklevel=2)
        return False
    return True


#: Whether the Triton program computes f and its partials in its first kernel where the pair
#: term allows it (f reads only scalars, ``PairTerm.columnwise``) rather than in XLA between
#: its two kernels (``benchmarks/step_phases.py --f-in-xla`` times the other way too).
F_IN_TRITON = True


def triton_energy(pot, n: int, program: str):
    """f of ``pot`` for the Triton program's first kernel (:class:`_pair_triton.ColumnEnergy`),
    or None where XLA computes f between the kernels: f reads a whole array K or M,
    :data:`F_IN_TRITON` is off, or (on a GPU, the program not chosen by
    ``$AFFINEBODY_PAIR_PROGRAM``) the kernel with this f does not build there
    (:func:`triton_builds`: a user's f may use an operation that Triton lacks)."""
    import os

    if not (F_IN_TRITON and pot.columnwise):
        return None
    layout, padding = _triton_layout(pot, n)
    energy = _pair_triton.ColumnEnergy(pot, layout)
    if program != "triton" or os.environ.get(PAIR_PROGRAM_VARIABLE, "").strip():
        return energy
    return energy if triton_builds(layout, padding, program, energy) else None


def _triton_layout(pot, n: int):
    """The :class:`_pair_triton.Layout` of ``pot`` in dimension n and each scalar's value for
    a padding pair (:func:`padding_value`)."""
    requirements = _requirements(pot, n)
    scalars = tuple((name, a) for name, shape in scalar_columns(*requirements, rows=1).items()
                    for a in range(shape[1] if len(shape) == 2 else 1))
    padding = tuple(padding_value(name, n, pot.cutoff.r_cut) for name, _ in scalars)
    return _pair_triton.Layout(n, *requirements, scalars), padding


def _triton_chunk(pot, space: Space, n, x, table, i, j, valid, cell, interpret: bool):
    """(E, g_u, side_K, K, side_L) of a chunk from the Triton kernels (``table``: the
    bodies'; side_K summed over runs of one K, to be added to bodies K,
    :func:`_pair_triton.chunk_rows`): f in the first kernel where :func:`triton_energy`
    gives it, else in XLA between the two."""
    layout, padding = _triton_layout(pot, n)
    u = space.displacement(x[i], x[j], cell)
    energy = triton_energy(pot, n, "triton-interpret" if interpret else "triton")
    return _pair_triton.chunk_rows(layout, _scalar_values_and_partials(pot, n), padding, u, i,
                                   j, valid, table, interpret, energy)


def energy_and_gradients(pot, space: Space, x, phi, i, j, count, chunk: int | None = None,
                         cell=None, virial: bool = False, program: str | None = None):
    """(E, dV/dx [N, n], dV/dphi [N, n, n]) of ``pot`` summed over the pairs (i[p], j[p]),
    p < count (JAX; jit with ``pot``, ``space``, ``chunk`` static), and with ``virial`` the
    virial W [n, n] of :func:`pair_virial` from the same pass, fourth. Pairs beyond ``count``
    are padding. Memory: one chunk of pairs at a time (default :func:`pair_chunk`). ``cell``:
    the current cell of a box that a barostat deforms (``space`` its reference), or None.

    Each pair's whole contribution (dV/dx and dV/dphi, :func:`_chunk_contributions`) goes to
    each of its bodies as one row of n + n^2 numbers, in one scatter-add per side: on a GPU
    the float64 atomic adds of the scatters are a large part of the time, and one wide row
    per pair costs less than the same numbers in several narrower scatters. The Triton
    program sums body K's rows over each run of pairs of one K first (the list keeps a body's
    pairs together), so that a few lanes per block add to K, not every pair
    (:func:`_pair_triton._run_sums`). Chunks that hold only padding are passed over
    (:func:`_over_chunks`).

    ``program``: how the rows are computed: ``"xla"`` (:func:`_chunk_contributions` as XLA
    fuses it; differentiable), ``"triton"`` (the same formulas as the two Pallas kernels of
    :mod:`affinebody._pair_triton`; a GPU only), ``"triton-interpret"`` (those kernels in
    Pallas' interpreter: tests on a CPU) or None (:func:`pair_program`)."""
    bodies, n, binv, det, (i_all, j_all, index) = _pair_pass(pot, x, phi, i, j, chunk)
    program = pair_program(pot, n) if program is None else program
    if program not in PAIR_PROGRAMS:
        raise ValueError(f"pair program {program!r}: expected one of {', '.join(PAIR_PROGRAMS)}")
    table = _pair_triton.table(phi, binv, det) if program != "xla" else None

    def step(carry, block):
        energy, total, w = carry
        ii, jj, idx = block
        ii, jj, valid = _valid_pairs(ii, jj, idx, count, bodies)
        if program == "xla":
            e, (g_u, d_phik, d_phil) = _chunk_contributions(pot, space, n, x, phi, binv, det,
                                                            ii, jj, valid, cell)
            rows = g_u.shape[0]
            side_k = jnp.concatenate([g_u, d_phik.reshape(rows, n * n)], axis=1)
            side_l = jnp.concatenate([-g_u, d_phil.reshape(rows, n * n)], axis=1)
            k = jnp.where(valid, ii, bodies)
        else:  # body K's rows summed over each run of pairs of one K: a few adds per block
            e, g_u, side_k, k, side_l = _triton_chunk(pot, space, n, x, table, ii, jj, valid,
                                                      cell, program == "triton-interpret")
        if virial:
            w = w - _pair_virial_sum(space, x, ii, jj, valid, g_u, cell)
        # padding pairs add nothing: their index is out of range and dropped (sending them to
        # one body instead serialises millions of atomic adds on a GPU)
        total = total.at[k].add(side_k, mode="drop")
        total = total.at[jnp.where(valid, jj, bodies)].add(side_l, mode="drop")
        return energy + e, total, w

    init = (jnp.zeros((), x.dtype), jnp.zeros((bodies, n + n * n), x.dtype),
            jnp.zeros((n, n), x.dtype))
    energy, total, w = _over_chunks(step, init, (i_all, j_all, index), index[:, 0], count)
    out = (energy, total[:, :n], total[:, n:].reshape(phi.shape))
    return out + (w,) if virial else out


def _pair_virial_sum(space: Space, x, i, j, valid, g_u, cell):
    """sum_p u_p (dV_p/du)^T over the valid pairs of a chunk (minus the virial's part)."""
    u = space.displacement(x[i], x[j], cell)
    return jnp.einsum("pa,pb->ab", u, jnp.where(valid[:, None], g_u, 0.0))


energy_and_gradients_jit = jax.jit(energy_and_gradients, static_argnums=(0, 1, 7),
                                   static_argnames=("virial", "program"))


def pair_virial(pot, space: Space, x, phi, i, j, count, cell=None, chunk: int | None = None,
                energy: bool = False):
    """The configurational virial W [n, n] of ``pot`` over the pairs (i[p], j[p]), p < count
    (with ``energy``: (E, W), the pairs' energy from the same pass):

        W_ab = - sum_p u_a (dV_p/du)_b,   u = x_K - x_L (minimum image),

    that is -dV/d(eps) for the strain x -> (Id + eps)^T x of the centres and of the box at
    fixed phi (docs/pressure.md). dV_p/du is the same closed-form per-pair gradient the
    forces of :func:`energy_and_gradients` scatter (r and D (75) both depend on u); memory:
    one chunk of pairs at a time. ``cell``: the current cell of a box that a barostat deforms
    (``space`` is then its reference), or None. On a CPU with Numba (and ``chunk`` None) the
    host kernel computes it (:func:`pair_sum`'s choice), else the JAX kernel."""
    if chunk is None and host_kernel_in_use():
        _require_cutoff(pot)
        e, w = _host_pair_sum(pot, space, x, phi, i, j, count, gradients=False, cell=cell,
                              virial=True)
        return (e, w) if energy else w
    bodies, n, binv, det, (i_all, j_all, index) = _pair_pass(pot, x, phi, i, j, chunk)

    def step(carry, block):
        e, total = carry
        ii, jj, idx = block
        ii, jj, valid = _valid_pairs(ii, jj, idx, count, bodies)
        part, (g_u, *_) = _chunk_contributions(pot, space, n, x, phi, binv, det, ii, jj,
                                               valid, cell)
        return e + part, total - _pair_virial_sum(space, x, ii, jj, valid, g_u, cell)

    zero = (jnp.zeros((), dtype=x.dtype), jnp.zeros((n, n), dtype=x.dtype))
    e, total = _over_chunks(step, zero, (i_all, j_all, index), index[:, 0], count)
    return (e, total) if energy else total


@partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _energy_over_pairs(pot, space, x, phi, i, j, count, cell):
    if host_kernel_in_use():  # the energy alone: no chain rule (observables, checks)
        return _host_pair_sum(pot, space, x, phi, i, j, count, gradients=False, cell=cell)
    # the XLA program, whose gradients XLA drops (the Triton kernels would compute them)
    return energy_and_gradients(pot, space, x, phi, i, j, count, cell=cell, program="xla")[0]


def _energy_over_pairs_fwd(pot, space, x, phi, i, j, count, cell):
    energy, g_x, g_phi = pair_sum(pot, space, x, phi, i, j, count, cell)
    return energy, (g_x, g_phi, i, j, count, cell)


def _energy_over_pairs_bwd(pot, space, residuals, cotangent):
    g_x, g_phi, i, j, count, cell = residuals
    zero_int = np.zeros((), dtype=jax.dtypes.float0)
    # the cell enters held fixed (neighbor_energy stops its gradient): its cotangent is 0
    return (cotangent * g_x, cotangent * g_phi,
            np.zeros(i.shape, dtype=jax.dtypes.float0),
            np.zeros(j.shape, dtype=jax.dtypes.float0), zero_int,
            None if cell is None else jnp.zeros_like(cell))


_energy_over_pairs.defvjp(_energy_over_pairs_fwd, _energy_over_pairs_bwd)


def neighbor_energy(pot, x, phi, neighbors, cell=None) -> jax.Array:
    """sum over the list's pairs of V_KL for x [N, n], phi [N, n, n]; differentiable
    (``jax.grad``) in x and phi with the closed-form gradients of this module. ``cell``: the
    current cell of a box that a barostat deforms (the list built in it), or None; it enters
    held fixed (``lax.stop_gradient``): the strain derivative is :func:`pair_virial`."""
    if x.ndim != 2:
        raise ValueError(f"a neighbour list serves one system: x must be [N, n] (got {x.shape})")
    _require_cutoff(pot)
    if cell is not None:
        cell = lax.stop_gradient(jnp.asarray(cell, dtype=x.dtype))
    return _energy_over_pairs(pot, pot.space, x, phi, neighbors.i, neighbors.j,
                              jnp.minimum(neighbors.count, neighbors.i.shape[0]), cell)


# --------------------------------------------------------------------------------------------
# Numba kernel (CPU)

from affinebody import _host  # noqa: E402
from affinebody._host import in_use as _host_in_use  # noqa: E402
from affinebody._host_kernels.pair_expression import fused_source  # noqa: E402
from affinebody._host_kernels.pair_source import kernels_source  # noqa: E402


@functools.cache
def _numba_kernels(n: int, plain: frozenset, k_powers: int, m_powers: int, swapped: bool):
    """The compiled kernels of the two-callback path for a pair term that needs these scalars
    in dimension n (written out by :func:`affinebody._host_kernels.pair_source.kernels_source`,
    cached on disk by :func:`affinebody._host.specialized`)."""
    source = kernels_source(n, plain, k_powers, m_powers, swapped)
    kernels = _host.specialized("pair", extra=source, N=n)
    return types.SimpleNamespace(geometry=kernels._geometry, scatter=kernels._scatter,
                                 virial=kernels._virial)


@functools.cache
def _fused_source(pot, n: int) -> str | None:
    """The generated source of the fused host kernel of ``pot`` in dimension n (f and its
    partials compiled with the geometry and the chain rule,
    :mod:`affinebody._host_kernels.pair_expression`), or None where f is not a config
    expression (then XLA evaluates f between two callbacks)."""
    expression = pot.expression
    if not isinstance(expression, CompiledExpression) or not set(expression.used) <= set(
            pot.variables):  # a variable f uses but the term does not declare: JAX refuses it
        return None
    plain, k_powers, m_powers, swapped = _requirements(pot, n)
    cutoff = pot.cutoff
    return fused_source(expression, n, plain, k_powers, m_powers, swapped,
                        bool(pot.asymmetric), cutoff.variable, float(cutoff.r_on),
                        float(cutoff.r_cut))


def fused_on_host(pot, n: int) -> bool:
    """Whether the host kernel sums ``pot`` with the fused kernel (``pot.expression``: a config
    expression, or a built-in family's f written as one; :func:`_fused_source`) rather than
    with XLA evaluating f between two host calls (False without a cut-off: no list, no host
    kernel)."""
    return pot.cutoff is not None and _fused_source(pot, n) is not None


@functools.cache
def _fused_kernel(n: int, source: str):
    """The compiled fused kernel: the pair kernels of dimension n with ``source`` appended
    (cached on disk under a hash of the whole text, :func:`affinebody._host.specialized`):
    ``fused_thread`` (one part's phases: its sums zeroed and B, det phi of its bodies; its
    pairs, the energy and its gradients or its virial; the parts' sums of its bodies with
    the chain rule), ``phases``, the bits that select them, and ``failed``, what a thread
    that raised writes into the barrier so that the other does not wait for it."""
    kernels = _host.specialized("pair", extra=source, N=n)
    return types.SimpleNamespace(fused_thread=kernels._fused_thread,
                                 phases=(kernels.PREPARE, kernels.PAIRS, kernels.MERGE),
                                 failed=kernels.FAILED)


#: Threads the host kernel uses (:func:`affinebody._host.host_threads`, shared by every host
#: kernel).
host_threads = _host.host_threads


def _thread_count(rows: int) -> int:
    """Threads for ``rows`` pairs: one below HOST_THREAD_MIN_ROWS."""
    return _host.thread_count(rows, HOST_THREAD_MIN_ROWS)


def _in_parts(work, rows: int) -> list:
    """``work(part, lo, hi)`` over :data:`affinebody._host.PARTS` fixed parts of range(rows),
    on up to :func:`affinebody._host.host_threads` threads (Numba releases the GIL); results
    in part order."""
    return _host.in_parts(work, rows, _host.PARTS, _thread_count(rows))


class _HostGeometry(NamedTuple):
    """What the host kernel needs of a potential and a space (static, per compilation)."""

    n: int
    plain: frozenset
    k_powers: int
    m_powers: int
    swapped: bool
    mode: int
    h: np.ndarray
    h_inv: np.ndarray
    edges: np.ndarray
    r_cut: float  # the potential's cut-off (padding pairs lie beyond it)

    @classmethod
    def of(cls, pot, space: Space, n: int, moving: bool = False) -> _HostGeometry:
        """``moving``: the box is a cell that a barostat deforms, given to the kernels as an
        operand (the general minimum image, mode 2)."""
        plain, k_powers, m_powers, swapped = _requirements(pot, n)
        if moving:
            mode, h, h_inv, edges = 2, np.eye(n), np.eye(n), np.ones(n)
        elif space.periodic:
            mode = 1 if space.orthorhombic else 2
            h, h_inv, edges = space.matrix, space.inverse, space.edges
        else:
            mode, h, h_inv, edges = 0, np.eye(n), np.eye(n), np.ones(n)
        return cls(n, plain, k_powers, m_powers, swapped, mode, np.asarray(h, np.float64),
                   np.asarray(h_inv, np.float64), np.asarray(edges, np.float64),
                   float(pot.cutoff.r_cut))

    def columns(self, rows: int) -> dict[str, tuple[int, ...]]:
        """Shapes of the scalar arrays of ``rows`` pairs (:func:`scalar_columns`)."""
        return scalar_columns(self.plain, self.k_powers, self.m_powers, self.swapped, rows)

    def kernels(self):
        """The compiled two-callback kernels for these scalars (:func:`_numba_kernels`)."""
        return _numba_kernels(self.n, self.plain, self.k_powers, self.m_powers, self.swapped)


def _host_geometry(g: _HostGeometry, x, phi, binv, det, i, j, valid, h, h_inv):
    """The pair scalars of the chunk (i, j): computed for its first ``valid`` pairs, the
    harmless padding values (beyond the cut-off, identity configurations) in the other rows.
    Only the scalars cross back to XLA (the displacements are recomputed by the scatter):
    what crosses a callback costs a copy, ~1 ns per byte here."""
    kernels = g.kernels()
    # callbacks receive jax.Arrays: as NumPy arrays (no copy on a CPU) Numba indexes them
    # as typed arrays, not as generic buffers (which made the kernels ~2x slower)
    x, phi, binv, det, h, h_inv = (np.asarray(a) for a in (x, phi, binv, det, h, h_inv))
    rows = i.shape[0]
    valid = int(valid)
    out = {key: np.empty(shape) for key, shape in g.columns(rows).items()}
    for key, value in out.items():
        value[valid:] = padding_value(key, g.n, g.r_cut)
    empty1, empty2 = np.zeros(1), np.zeros((1, 1))
    i = np.ascontiguousarray(i)
    j = np.ascontiguousarray(j)

    def work(_, lo, hi):
        view = {key: a[lo:hi] for key, a in out.items()}
        kernels.geometry(0, hi - lo, i[lo:hi], j[lo:hi], x, phi, binv, det, g.mode, h,
                         h_inv, g.edges, view.get("r", empty1), view.get("D", empty1),
                         view.get("det", empty1), view.get("K", empty2),
                         view.get("M", empty2), view.get("Ms", empty2))

    _in_parts(work, valid)
    return tuple(out[key] for key in g.columns(rows))


def _host_scatter(g: _HostGeometry, sums, x, phi, binv, det, i, j, valid, partials, h, h_inv):
    """``sums`` (dV/dx, dV/dphi direct, dV/dB, dV/d det per body) plus the closed-form
    geometric derivatives of the chunk's first ``valid`` pairs, from df/dq (``partials``)."""
    kernels = g.kernels()
    valid = int(valid)
    i = np.ascontiguousarray(i)
    j = np.ascontiguousarray(j)
    x, phi, binv, det, h, h_inv = (np.asarray(a) for a in (x, phi, binv, det, h, h_inv))
    keys = list(g.columns(i.shape[0]))
    partials = dict(zip(keys, (np.asarray(a) for a in partials), strict=True))
    empty1, empty2 = np.zeros(1), np.zeros((1, 1))

    def work(_, lo, hi):
        acc = tuple(np.zeros(np.shape(a)) for a in sums)
        rows = lambda key, empty: partials[key][lo:hi] if key in partials else empty  # noqa: E731
        kernels.scatter(0, hi - lo, i[lo:hi], j[lo:hi], x, phi, binv, det, g.mode, h,
                        h_inv, g.edges, rows("r", empty1), rows("D", empty1),
                        rows("det", empty1), rows("K", empty2), rows("M", empty2),
                        rows("Ms", empty2), *acc)
        return acc

    out = tuple(np.array(a, dtype=np.float64) for a in sums)
    for part in _in_parts(work, valid):  # a fixed order: the same sums on any thread count
        for total, add in zip(out, part, strict=True):
            total += add
    return out


def _host_virial(g: _HostGeometry, x, binv, i, j, valid, partials, h, h_inv):
    """-sum u (dV/du)^T [n, n] of the chunk's first ``valid`` pairs (parts summed in a fixed
    order, as :func:`_host_scatter`)."""
    kernels = g.kernels()
    valid = int(valid)
    i, j = np.ascontiguousarray(i), np.ascontiguousarray(j)
    x, binv, h, h_inv = (np.asarray(a) for a in (x, binv, h, h_inv))
    partials = dict(zip(list(g.columns(i.shape[0])), (np.asarray(a) for a in partials),
                        strict=True))
    empty1 = np.zeros(1)

    def work(_, lo, hi):
        out = np.zeros((g.n, g.n))
        rows = lambda key: partials[key][lo:hi] if key in partials else empty1  # noqa: E731
        kernels.virial(0, hi - lo, i[lo:hi], j[lo:hi], x, binv, g.mode, h, h_inv, g.edges,
                       rows("r"), rows("D"), out)
        return out

    total = np.zeros((g.n, g.n))
    for part in _in_parts(work, valid):
        total += part
    return total


def _host_fused(g: _HostGeometry, source: str, gradients: bool, virial: bool, x, phi, i, j,
                count, h, h_inv, *, results):
    """The fused kernel over the list's first ``count`` pairs, in :data:`affinebody._host.PARTS`
    fixed parts, each with sums of its own added in part order (the same bits on any thread
    count). Fills ``results`` (XLA's result buffers, ``_host.callback``'s ``fills_results``):
    E, then dV/dx, dV/dphi with ``gradients`` (per-body sums, then the chain rule through
    B = phi^-1 and det phi per body, ``_merge_finish`` in parts of the bodies, written in
    place), then the virial W [n, n] of :func:`pair_virial` with ``virial``: all from the
    same pass.
    One callback for the whole list: no pair scalars are held, so no chunks. B and det phi
    are computed here first (``_inverse_det``, as ``_linalg.inv`` and ``det`` compute them),
    once per body: in XLA they had been a dozen small operations of ~0.25 ms per step at
    4096 bodies, against ~0.1 ms here (docs/performance.md, "Two cores: XLA's threads and
    the host kernels'"). With a thread per part, the whole evaluation is one hand-off: each
    thread zeroes its part's sums, inverts its share of the bodies, sums its pairs and merges
    its share of the bodies, with barriers between (``_fused_thread``); on one thread the same
    compiled function runs the phases one after the other, every part each."""
    kernels = _fused_kernel(g.n, source)
    valid = min(int(count), i.shape[0])  # an overflowed list counts pairs it could not hold
    i, j = np.ascontiguousarray(i), np.ascontiguousarray(j)
    x, phi, h, h_inv = (np.asarray(a) for a in (x, phi, h, h_inv))
    bodies, n = x.shape
    binv, det = np.empty_like(phi), np.empty(bodies)
    rows = bodies if gradients else 1  # the kernel adds nothing to the sums without gradients
    parts = _host.PARTS
    gx, gphi, gb = (np.empty((parts, rows, *shape)) for shape in ((n,), (n, n), (n, n)))
    gdet, w = np.empty((parts, rows)), np.empty((parts, n, n))
    g_x, g_phi = results[1:3] if gradients else (gx[0], gphi[0])  # not written without
    pair_parts, body_parts = _host.part_ranges(valid, parts), _host.part_ranges(bodies, parts)

    def part(k, phases, arrived):
        return kernels.fused_thread(k, phases, arrived, *pair_parts[k], *body_parts[k], i, j, x,
                                    phi, binv, det, g.mode, h, h_inv, g.edges, gradients,
                                    virial, gx, gphi, gb, gdet, w, g_x, g_phi)

    if _thread_count(valid) == parts:
        arrived = np.zeros(parts, np.int64)
        every = sum(kernels.phases)

        def release(k):  # thread k raised: the other must not wait for it at a barrier
            arrived[k] = kernels.failed

        energies = _host.side_by_side(lambda k: part(k, every, arrived), parts, failed=release)
    else:  # one phase at a time, every part each (the merge adds nothing without gradients)
        alone = np.zeros(0, np.int64)
        prepare, pairs, merge = kernels.phases
        for k in range(parts):
            part(k, prepare, alone)
        energies = [part(k, pairs, alone) for k in range(parts)]
        for k in range(parts):
            part(k, merge, alone)
    energy, total = 0.0, np.zeros((n, n))
    for k, e in enumerate(energies):  # a fixed order
        energy += e
        total += w[k]
    results[0][...] = energy
    if virial:
        results[-1][...] = total


def _host_chunk(capacity: int) -> int:
    """Pairs per host-kernel pass for a list of ``capacity`` pairs (a function of the
    capacity only, so the summation order, hence every bit, is the same on every run)."""
    return max(1, min(capacity, HOST_CHUNK_PAIRS))


def _host_pair_sum(pot, space: Space, x, phi, i, j, count, gradients: bool = True,
                   cell=None, virial: bool = False):
    """(E, dV/dx, dV/dphi) with the compiled host kernel, from compiled JAX code: per chunk of
    pairs, a host callback (``_host.callback``) computes the geometry (Numba), XLA the scalar
    function f and its partial derivatives (fused, elementwise), a second callback the closed-form
    chain rule and the per-body sums; the per-body chain rule through B = phi^-1 and det phi
    finishes in JAX. Where f is a config expression (``pot.expression``: a ``kind = "pair"``
    term, or a family that writes its f as one), one callback over
    the whole list runs the fused kernel instead (f and its partials compiled with the
    geometry and the chain rule, :func:`_fused_source`, then the chain rule through B and
    det phi, :func:`_host_fused`), the virial pass too. No JAX
    runs inside a callback (that could wait on the thread that called it).
    Returns E, then dV/dx, dV/dphi with ``gradients`` (else no chain rule, no second
    callback), then the virial W [n, n] of :func:`pair_virial` with ``virial`` (the same
    fused pass where f is a config expression, else a third kernel after the geometry and
    f's partials): E alone when neither. ``cell``: the current cell of a box that a barostat
    deforms (an operand of the kernels: one compilation serves every box), or None."""
    _require_cutoff(pot)
    bodies, n = x.shape
    g = _HostGeometry.of(pot, space, n, moving=cell is not None)
    if cell is None:
        h, h_inv = jnp.asarray(g.h, x.dtype), jnp.asarray(g.h_inv, x.dtype)
    else:
        h, h_inv = cell, linalg.inv(cell)
    f64 = lambda shape: jax.ShapeDtypeStruct(shape, x.dtype)  # noqa: E731
    fused = _fused_source(pot, n)
    if fused is not None:  # f is a config expression: one callback does it all
        shapes = ((f64(()),) + ((f64(x.shape), f64(phi.shape)) if gradients else ())
                  + ((f64((n, n)),) if virial else ()))
        out = _host.callback(partial(_host_fused, g, fused, gradients, virial), shapes,
                             x, phi, i, j, count, h, h_inv, vmap_method="sequential",
                             fills_results=True)
        return tuple(out) if len(shapes) > 1 else out[0]
    binv, det = linalg.inv(phi), linalg.det(phi)
    capacity = i.shape[0]
    chunk = _host_chunk(capacity)
    chunks = -(-capacity // chunk)
    fill = chunks * chunk - capacity
    i_all = jnp.concatenate([i, jnp.zeros(fill, i.dtype)])
    j_all = jnp.concatenate([j, jnp.zeros(fill, j.dtype)])
    columns = g.columns(chunk)
    geometry_shapes = tuple(f64(shape) for shape in columns.values())
    sum_shapes = (f64(x.shape), f64(phi.shape), f64(phi.shape), f64((bodies,)))
    values_and_partials = _scalar_values_and_partials(pot, n)
    rows = jnp.arange(chunk)

    def step(carry, k):
        energy, w, sums = carry
        lo = k * chunk
        ii = lax.dynamic_slice(i_all, (lo,), (chunk,))
        jj = lax.dynamic_slice(j_all, (lo,), (chunk,))
        valid = jnp.clip(count - lo, 0, chunk).astype(jnp.int32)
        scalars = _host.callback(partial(_host_geometry, g), geometry_shapes, x, phi, binv,
                                    det, ii, jj, valid, h, h_inv, vmap_method="sequential")
        base = dict(zip(columns, scalars, strict=True))  # padding rows: beyond the cut-off
        inside = rows < valid
        if not (gradients or virial):
            energies = pot.energy_from_scalars(base, n)
            return energy + jnp.sum(jnp.where(inside, energies, 0.0)), w, sums
        energies, partials = values_and_partials(base)
        partials = tuple(partials[key] for key in columns)
        if virial:
            w = w + _host.callback(partial(_host_virial, g), f64((n, n)), x, binv, ii, jj,
                                   valid, partials, h, h_inv, vmap_method="sequential")
        if gradients:
            sums = _host.callback(
                partial(_host_scatter, g), sum_shapes, sums, x, phi, binv, det, ii, jj, valid,
                partials, h, h_inv, vmap_method="sequential")
        return energy + jnp.sum(jnp.where(inside, energies, 0.0)), w, sums

    init = (jnp.zeros((), x.dtype), jnp.zeros((n, n), x.dtype),
            (jnp.zeros_like(x), jnp.zeros_like(phi), jnp.zeros_like(phi),
             jnp.zeros((bodies,), x.dtype)))
    ks = jnp.arange(chunks)
    energy, w, (g_x, g_phi, g_b, g_det) = _over_chunks(step, init, ks, ks * chunk, count)
    out = (energy,)
    if gradients:
        out += (g_x, _finish(phi, binv, det, g_phi, g_b, g_det))
    if virial:
        out += (w,)
    return out if len(out) > 1 else energy


def energy_and_gradients_host(pot, space: Space, x, phi, i, j, count, cell=None):
    """The compiled-CPU twin of :func:`energy_and_gradients`: the host kernel, jitted (the
    path ``simulate.run`` takes on a CPU). Needs Numba. ``cell`` as in :func:`pair_sum`."""
    if _host.numba is None:
        raise ValueError("pair_kernels: the compiled CPU kernel needs numba (pip install numba)")
    _require_cutoff(pot)
    return _host_pair_sum_jit(pot, space, jnp.asarray(x), jnp.asarray(phi), jnp.asarray(i),
                              jnp.asarray(j), jnp.asarray(count),
                              cell=None if cell is None else jnp.asarray(cell))


_host_pair_sum_jit = jax.jit(_host_pair_sum, static_argnums=(0, 1))


def host_kernel_in_use() -> bool:
    """True when :func:`pair_sum` runs the compiled host kernel (CPU backend with Numba)."""
    return _host_in_use()


def kernel_in_use(pot, n: int) -> str:
    """Which kernel :func:`pair_sum` runs for ``pot`` in dimension n, in words (``affinebody
    run --verbose``): the host kernel, or the JAX kernel with its :func:`pair_program`."""
    if host_kernel_in_use():
        f = ("f compiled into it" if fused_on_host(pot, n)
             else "f in XLA between two callbacks")
        return f"host kernel (Numba, {_host.host_threads()} threads, {f})"
    program = pair_program(pot, n)
    if program == "triton":
        f = ("f in the first kernel" if triton_energy(pot, n, program) is not None
             else "f in XLA between the kernels")
        return f"JAX kernel, triton program ({f})"
    return f"JAX kernel, {program} program"


def pair_sum(pot, space: Space, x, phi, i, j, count, cell=None, virial: bool = False):
    """(E, dV/dx, dV/dphi) over the list's pairs, with the kernel for the backend: the
    compiled host kernel on a CPU (when Numba is installed), the JAX kernel otherwise (a GPU:
    no host round trip). Both are tested against all-pairs autodiff. ``cell``: the current
    cell of a box that a barostat deforms (``space`` its reference), or None. ``virial``:
    (E, dV/dx, dV/dphi, W), the virial of :func:`pair_virial` from the same pass (what a
    barostat's move needs after the step's force evaluation)."""
    if host_kernel_in_use():
        return _host_pair_sum(pot, space, x, phi, i, j, count, cell=cell, virial=virial)
    return energy_and_gradients(pot, space, x, phi, i, j, count, cell=cell, virial=virial)


__all__ = [
    "ACCELERATOR_PAIR_CHUNK", "PAIR_CHUNK", "PAIR_PROGRAMS", "PAIR_PROGRAM_VARIABLE",
    "energy_and_gradients", "energy_and_gradients_host", "fused_on_host", "host_kernel_in_use",
    "host_threads", "kernel_in_use", "neighbor_energy", "padding_value", "pair_chunk",
    "pair_program", "pair_sum", "pair_virial", "scalar_columns", "triton_builds",
    "triton_energy",
]
