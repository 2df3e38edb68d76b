"""Compiled host (CPU) code: whether the product runs it, and its kernels cached on disk.

On a CPU backend with Numba installed, the pair kernel (``pair_kernels``), the neighbour list build
(``neighbors``) and the exact drift of the isotropic affine models (``kinetic.isotropic_flow``) run
compiled CPU loops reached through :func:`callback` (a ``jax.pure_callback`` without its copies of
the operands); on a GPU (or without Numba) they run their JAX versions, so nothing leaves the device
inside the time loop. Both versions of each are tested against each other (the pair sums also
against all-pairs sums). Work is split in fixed parts run on up to as many threads
(:func:`in_parts`), so results do not depend on the number of cores.

The kernels live in :mod:`affinebody._host_kernels` as modules whose dimension (and box kind)
are module constants, which Numba compiles as constants so that the small loops unroll (the
pair kernels' loops over pairs are generated source appended to their module, written out per
pair term). :func:`specialized` writes such a module once per set of constants into a cache
folder and
imports it from there; Numba's ``cache=True`` then keeps the machine code beside it, so only the
first process on a machine compiles (about 5 s for the n = 3 pair kernel), the others load.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import hashlib
import importlib.util
import inspect
import itertools
import os
import re
import sys
import threading
import types
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Primitive
from jax.interpreters import batching, mlir

try:  # optional at import: the JAX paths work without it (pyproject installs it)
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

_CONSTANTS = re.compile(r"# --- constants.*?\n(.*?)# --- end of constants", re.S)


#: Fixed parts of the work of a host kernel (pairs of a list, bodies), each run whole by one
#: thread and combined in part order, so results are the same on any number of cores; the
#: threads (at most this many) take the parts as they become free (:func:`in_parts`).
PARTS = 2


def in_use() -> bool:
    """True when compiled host code runs: a CPU backend and Numba installed."""
    return numba is not None and jax.default_backend() == "cpu"


def cores() -> int:
    """The cores this process may run on (``taskset -c 0`` gives one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def threads(parts: int) -> int:
    """Threads for work split in ``parts`` fixed parts: the :func:`cores`, at most ``parts``."""
    return max(1, min(parts, cores()))


def host_threads() -> int:
    """Threads every host kernel uses (pair sums, list builds, drifts): the :func:`cores`
    this process may run on, at most :data:`PARTS` (``taskset -c 0`` gives one)."""
    return threads(PARTS)


def thread_count(rows: int, fewest: int) -> int:
    """Threads for ``rows`` units of a host kernel's work: :func:`host_threads`, one below
    ``fewest`` (the kernel's own threshold, where a second thread costs more than it saves)."""
    return host_threads() if rows >= fewest else 1


@functools.cache
def _pool(count: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=count, thread_name_prefix="affinebody-host")


def part_ranges(rows: int, parts: int) -> list[tuple[int, int]]:
    """The ``parts`` fixed parts (lo, hi) of range(rows) that :func:`in_parts` runs, in order
    (equal sizes to within one row)."""
    bounds = [rows * k // parts for k in range(parts + 1)]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def in_parts(work, rows: int, parts: int, count: int) -> list:
    """``work(part, lo, hi)`` over ``parts`` fixed parts of range(rows) (part k is
    ``part_ranges(rows, parts)[k]``, the same whatever ``count``; a part's index picks its own
    output, e.g. its per-body sums), on ``count`` threads when ``count > 1`` (Numba kernels
    release the GIL); results in part order, so sums over them are the same on any number of
    threads. The threads take the next part as they become free (the calling thread
    included), so a core that another process slows down takes fewer parts."""
    ranges = part_ranges(rows, parts)
    if count <= 1:
        return [work(k, lo, hi) for k, (lo, hi) in enumerate(ranges)]
    results: list = [None] * parts
    taken = itertools.count()  # next() is atomic under the GIL

    def drain(_) -> None:
        while (k := next(taken)) < parts:
            results[k] = work(k, *ranges[k])

    side_by_side(drain, count)
    return results


def side_by_side(work, count: int, failed=None) -> list:
    """``work(k)`` for k in range(count), each on a thread of its own at the same time (the
    calling thread runs k = 0), results in order of k: for parts that wait on each other (a
    barrier between phases, ``_host_kernels/pair.py``), which :func:`in_parts`, where a
    thread takes the next part only once it is free, could not run. Where ``work(k)`` raises,
    ``failed(k)`` is called first (e.g. to release the others from a barrier they would
    otherwise wait at for ever); every thread has returned before the first error is
    raised (never return, or raise into XLA, which frees the buffers, while a helper
    writes)."""
    def guarded(k):
        try:
            return work(k)
        except BaseException:
            if failed is not None:
                failed(k)
            raise

    helpers = [_pool(count - 1).submit(guarded, k) for k in range(1, count)]
    try:
        first = guarded(0)
    finally:
        for helper in helpers:
            helper.exception()
    return [first] + [helper.result() for helper in helpers]


#: glibc ``mallopt`` parameters (malloc.h) and the values :func:`keep_freed_memory` sets: blocks
#: up to 32 MiB (glibc's largest heap threshold) from the heap, and a heap trimmed only when
#: 2 GiB (the largest int) lie free at its top.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 * 1024 * 1024
_TRIM_THRESHOLD = 2**31 - 1


def keep_freed_memory() -> bool:
    """Let this process's C heap keep the memory it frees (glibc ``mallopt``), so that the
    arrays a time step allocates and frees (a callback's results and sums, XLA's copies of them)
    reuse pages that are already mapped instead of faulting in fresh zeroed ones: 570 page
    faults per step of a 4096-body run without it, 2.3 with it (``run_scale.py --faults``,
    docs/performance.md). The peak memory grows little (what is kept was in use at the peak;
    1.31 -> 1.38 GiB at 10^5 bodies). What the command line and the workers do for their own
    process, like float64; importing affinebody never does it. False where the C library is not
    glibc (nothing changed)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to tune
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
                and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))


# --------------------------------------------------------------------------------------------
# the call from compiled code into a host kernel

try:  # JAX's own emitter of Python callbacks (what jax.pure_callback lowers to), if present
    from jax._src.callback import emit_python_callback as _emit_python_callback
except ImportError:  # pragma: no cover - a JAX without it: jax.pure_callback instead
    _emit_python_callback = None
if _emit_python_callback is not None and not {"has_side_effect", "returns_token"} <= set(
        inspect.signature(_emit_python_callback).parameters):  # pragma: no cover - changed
    _emit_python_callback = None


# The call on a CPU: XLA's typed FFI (xla/ffi/api/c_api.h, API 0.3) calls a C function pointer
# made by ctypes from :func:`_ffi_handler` with one XLA_FFI_CallFrame*; the handler reads the
# operand and result buffers' addresses from it and gives the host function NumPy views of
# them, with no copy. JAX's own Python callback copies every operand and result (~0.1 ms per
# MB: ~0.3 ms a step at 4096 bodies, docs/performance.md). The structs are
# read as 8-byte words at the offsets of the C header (x86-64 and aarch64 LP64 layout):
#   XLA_FFI_CallFrame: 1 extension_start, 2 api, 4 stage, 7 args.size, 9 args.args,
#                      12 rets.size, 14 rets.rets, 20 attrs.attrs (22 words);
#   XLA_FFI_Buffer:    2 dtype, 3 data, 4 rank, 5 dims;
#   XLA_FFI_Extension_Base: 1 type, then (metadata extension) 3 XLA_FFI_Metadata*.
_FFI_TARGET = "affinebody_host_callback"
_FFI_API_VERSION = (0, 3)
_FFI_EXECUTE, _FFI_METADATA, _FFI_INTERNAL = 3, 1, 13
_FFI_DTYPES = {1: np.bool_, 2: np.int8, 3: np.int16, 4: np.int32, 5: np.int64, 6: np.uint8,
               7: np.uint16, 8: np.uint32, 9: np.uint64, 11: np.float32, 12: np.float64,
               15: np.complex64, 18: np.complex128}
_FRAME_WORDS = ctypes.c_char * (22 * 8)
#: the host function of each lowered call (the call's ``index`` attribute), and the operand and
#: result layouts of each, read from its first call
_FFI_FUNCTIONS: list = []
_FFI_LAYOUTS: dict = {}
_FFI_LOCK = threading.Lock()


class _ApiVersion(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("major_version", ctypes.c_int), ("minor_version", ctypes.c_int)]


class _ErrorCreateArgs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("message", ctypes.c_char_p), ("errc", ctypes.c_int)]


_ERROR_CREATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ErrorCreateArgs))


def _words(address: int, count: int) -> np.ndarray:
    return np.frombuffer((ctypes.c_char * (8 * count)).from_address(address), np.int64)


def _buffer_layout(address: int) -> tuple:
    """(dtype, shape, the ctypes type of its bytes or None when empty) of an XLA_FFI_Buffer."""
    words = _words(address, 6)
    dtype = np.dtype(_FFI_DTYPES[int(words[2]) & 0xFFFFFFFF])
    rank = int(words[4])
    shape = tuple(int(d) for d in _words(int(words[5]), rank)) if rank else ()
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    return dtype, shape, (ctypes.c_char * size) if size else None


def _buffer_view(address: int, layout: tuple, writeable: bool) -> np.ndarray:
    dtype, shape, raw = layout
    if raw is None:
        return np.empty(shape, dtype)
    data = ctypes.c_void_p.from_address(address + 24).value
    view = np.frombuffer(raw.from_address(data), dtype).reshape(shape)
    view.flags.writeable = writeable
    return view


def _ffi_error(api: int, message: str) -> int:
    """An XLA_FFI_Error made by the API's XLA_FFI_Error_Create (its first function, after
    struct_size, extension_start, the 24-byte api_version and internal_api)."""
    create = _ERROR_CREATE(ctypes.c_void_p.from_address(api + 48).value)
    args = _ErrorCreateArgs(ctypes.sizeof(_ErrorCreateArgs), None,
                            message.encode("utf-8", "replace"), _FFI_INTERNAL)
    return create(ctypes.byref(args))


def _ffi_handler(frame: int) -> int | None:
    """The FFI handler: answers the metadata query (the API version it was written for), does
    nothing before the execute stage, and there calls the host function (a :class:`_Flat`)
    of the call's ``index`` on read-only views of the operands and writable views of XLA's
    result buffers. An exception becomes an XLA error (raised by the jitted call)."""
    words = np.frombuffer(_FRAME_WORDS.from_address(frame), np.int64)
    extension = _words(int(words[1]), 4) if words[1] else None
    if extension is not None and int(extension[1]) & 0xFFFFFFFF == _FFI_METADATA:
        metadata = int(extension[3])
        version = _ApiVersion.from_address(metadata + 8)
        version.major_version, version.minor_version = _FFI_API_VERSION
        ctypes.c_uint32.from_address(metadata + 8 + ctypes.sizeof(_ApiVersion)).value = 0
        return None
    if int(words[4]) & 0xFFFFFFFF != _FFI_EXECUTE:
        return None
    try:
        index = ctypes.c_uint64.from_address(
            ctypes.c_void_p.from_address(int(_words(int(words[20]), 1)[0]) + 8).value).value
        args, rets = _words(int(words[9]), int(words[7])), _words(int(words[14]), int(words[12]))
        layouts = _FFI_LAYOUTS.get(index)
        if layouts is None:
            layouts = _FFI_LAYOUTS[index] = ([_buffer_layout(int(a)) for a in args],
                                             [_buffer_layout(int(r)) for r in rets])
        operands = [_buffer_view(int(a), layout, False)
                    for a, layout in zip(args, layouts[0], strict=True)]
        results = tuple(_buffer_view(int(r), layout, True)
                        for r, layout in zip(rets, layouts[1], strict=True))
        _FFI_FUNCTIONS[index](*operands, results=results)
    except BaseException as error:  # noqa: BLE001 - every error goes back to XLA, which raises it
        return _ffi_error(int(words[2]), f"affinebody host callback: "
                                         f"{type(error).__name__}: {error}")
    return None


_FFI_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)(_ffi_handler)
try:
    jax.ffi.register_ffi_target(_FFI_TARGET, jax.ffi.pycapsule(_FFI_HANDLER), platform="cpu")
    _FFI_LOWERING = jax.ffi.ffi_lowering(_FFI_TARGET)
except Exception:  # pragma: no cover - a JAX without this FFI: JAX's own Python callback
    _FFI_LOWERING = None


#: The name of :func:`callback`'s primitive in a jaxpr (where a host kernel is called).
CALLBACK_NAME = "affinebody_host_callback"
_CALLBACK = Primitive(CALLBACK_NAME)
_CALLBACK.multiple_results = True


def callback(function, result_shapes, *args, vmap_method: str = "sequential",
             fills_results: bool = False):
    """``jax.pure_callback(function, result_shapes, *args, vmap_method=...)`` without its
    copies: pure_callback copies every operand into a new JAX array (``device_put``, ~20 us
    per operand plus the bytes), and JAX's Python callback under it copies each operand again
    and each result into XLA's buffer (~0.1 ms per MB: ~0.3 ms a step for a 4096-body pair
    call). Here, on a CPU, ``function`` gets read-only NumPy views of XLA's operand buffers
    (:func:`_ffi_handler`) and, with ``fills_results``, writable views of its result buffers
    as ``results=`` (a flat tuple in the order of ``result_shapes``' leaves) to fill in place,
    returning nothing; otherwise its results are copied there. The same purity (XLA may drop
    or merge calls whose results are unused or equal) and vmap methods ("sequential": one
    call per batch element; "broadcast_all": one call over the batch, every operand given
    the batch axes). No derivative (as pure_callback): wrap it in a ``custom_jvp``. On other
    platforms it is JAX's Python callback; where this JAX lacks that, jax.pure_callback."""
    if _emit_python_callback is None:  # pragma: no cover
        if fills_results:
            function = _Flat(function, None, True).returning(result_shapes)
        return jax.pure_callback(function, result_shapes, *args, vmap_method=vmap_method)
    leaves, tree = jax.tree.flatten(result_shapes)
    flat_args, args_tree = jax.tree.flatten(args)
    avals = tuple(jax.core.ShapedArray(leaf.shape, leaf.dtype) for leaf in leaves)
    out = _CALLBACK.bind(*flat_args, function=_Flat(function, args_tree, fills_results),
                         result_avals=avals, vmap_method=vmap_method)
    return jax.tree.unflatten(tree, out)


class _Flat:
    """``function`` called with its operands unflattened and its results written into the
    given ``results`` (writable arrays of the declared shapes and dtypes), by ``function``
    itself where it ``fills`` them, else copied from what it returns (hashable, so jit caches
    by it)."""

    def __init__(self, function, tree, fills: bool):
        self.function, self.tree, self.fills = function, tree, fills

    def __call__(self, *flat, results: tuple):
        args = flat if self.tree is None else jax.tree.unflatten(self.tree, flat)
        if self.fills:
            self.function(*args, results=results)
            return
        out = jax.tree.leaves(self.function(*args))
        if len(out) != len(results):
            raise TypeError(f"a host callback returned {len(out)} arrays where "
                            f"{len(results)} were declared")
        for target, value in zip(results, out, strict=True):
            value = np.asarray(value)
            if value.shape != target.shape or value.dtype != target.dtype:
                raise TypeError(f"a host callback returned {value.dtype}{list(value.shape)} "
                                f"where {target.dtype}{list(target.shape)} was declared")
            np.copyto(target, value)

    def returning(self, shapes):
        """A function of the operands that returns new arrays shaped as ``shapes``' leaves,
        filled by this one (for a caller that takes results, JAX's Python callback)."""
        leaves = [(leaf.shape, leaf.dtype) for leaf in jax.tree.leaves(shapes)]

        def call(*flat):
            results = tuple(np.empty(shape, dtype) for shape, dtype in leaves)
            self(*flat, results=results)
            return results

        return call

    def __hash__(self):
        return hash((self.function, self.tree, self.fills))

    def __eq__(self, other):
        return (isinstance(other, _Flat) and self.function == other.function
                and self.tree == other.tree and self.fills == other.fills)


def _callback_abstract(*args, function, result_avals, vmap_method):
    return result_avals


def _callback_impl(*args, function, result_avals, vmap_method):
    """Outside jit: the host function called at once on NumPy views of the operands, as the
    compiled call gives it them (compiling a one-call program instead cost a compilation per
    call: the function, a new partial each time, is part of the cache key)."""
    out = function.returning(result_avals)(*(np.asarray(a) for a in args))
    return [jnp.asarray(o) for o in out]


def _callback_lowering(ctx, *args, function, result_avals, vmap_method):
    result, _, _ = _emit_python_callback(ctx, function.returning(ctx.avals_out), None,
                                         list(args), ctx.avals_in,
                                         ctx.avals_out, has_side_effect=False,
                                         returns_token=False)
    return result


def _callback_ffi_lowering(ctx, *args, function, result_avals, vmap_method):
    """On a CPU: XLA's FFI custom call of :func:`_ffi_handler`, with the index of ``function``
    (kept for as long as the process lives, as JAX keeps its callbacks) as attribute."""
    with _FFI_LOCK:
        _FFI_FUNCTIONS.append(function)
        index = len(_FFI_FUNCTIONS) - 1
    return _FFI_LOWERING(ctx, *args, index=np.uint64(index))


def _callback_batched(args, dims, *, function, result_avals, vmap_method):
    # d is None: vmap does not map that operand (batching.not_mapped of JAX 0.10, gone in 0.12)
    size = next(a.shape[d] for a, d in zip(args, dims, strict=True)
                if d is not None)
    front = [a if d is None else jnp.moveaxis(a, d, 0)
             for a, d in zip(args, dims, strict=True)]
    if vmap_method == "broadcast_all":
        full = [jnp.broadcast_to(a, (size, *a.shape)) if d is None else a
                for a, d in zip(front, dims, strict=True)]
        batched = tuple(jax.core.ShapedArray((size, *a.shape), a.dtype) for a in result_avals)
        out = _CALLBACK.bind(*full, function=function, result_avals=batched,
                             vmap_method=vmap_method)
    elif vmap_method == "sequential":
        mapped = [k for k, d in enumerate(dims) if d is not None]

        def one(slices):
            operands = list(front)
            for k, a in zip(mapped, slices, strict=True):
                operands[k] = a
            return _CALLBACK.bind(*operands, function=function, result_avals=result_avals,
                                  vmap_method=vmap_method)

        out = lax.map(one, [front[k] for k in mapped])
    else:
        raise ValueError(f"vmap_method must be 'sequential' or 'broadcast_all' "
                         f"(got {vmap_method!r})")
    return list(out), [0] * len(result_avals)


_CALLBACK.def_impl(_callback_impl)
_CALLBACK.def_abstract_eval(_callback_abstract)
batching.primitive_batchers[_CALLBACK] = _callback_batched
if _emit_python_callback is not None:
    mlir.register_lowering(_CALLBACK, _callback_lowering)
if _FFI_LOWERING is not None:
    mlir.register_lowering(_CALLBACK, _callback_ffi_lowering, platform="cpu")


def cache_folder() -> Path:
    """Where specialized kernels and their compiled code are kept: $AFFINEBODY_CACHE_DIR, else
    $XDG_CACHE_HOME/affinebody/kernels, else ~/.cache/affinebody/kernels."""
    if os.environ.get("AFFINEBODY_CACHE_DIR"):
        return Path(os.environ["AFFINEBODY_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "affinebody" / "kernels"


def specialized(kernel: str, extra: str = "", **constants) -> types.ModuleType:
    """The module ``affinebody._host_kernels.<kernel>`` with its block of constants set to
    ``constants`` (and ``CACHE`` on) and the generated source ``extra`` appended, loaded from a
    file in :func:`cache_folder` named by a hash of its text and of the Numba and Python
    versions, so a changed kernel never meets a stale cache. Where the folder cannot be
    written, the module is compiled in memory, uncached."""
    template = resources.files("affinebody._host_kernels").joinpath(f"{kernel}.py").read_text(
        encoding="utf-8")
    if extra:
        template = f"{template}\n\n{extra}"
    block = "".join(f"{name} = {value!r}\n" for name, value in {**constants, "CACHE": True}.items())
    text, count = _CONSTANTS.subn(lambda m: m.group(0).replace(m.group(1), block), template)
    if count != 1:
        raise RuntimeError(f"_host_kernels/{kernel}.py has no block of constants")
    key = hashlib.sha256(f"{text}{numba.__version__}{sys.version}".encode()).hexdigest()[:16]
    name = f"affinebody_kernel_{kernel}_{key}"
    # one loader at a time: callbacks of one compiled function may run on several threads,
    # and a module is in sys.modules before it has finished executing
    with _LOADING:
        return _load(name, text)


_LOADING = threading.RLock()


def _load(name: str, text: str) -> types.ModuleType:
    if name in sys.modules:
        return sys.modules[name]
    path = cache_folder() / f"{name}.py"
    try:
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            partial.write_text(text, encoding="utf-8")
            os.replace(partial, path)  # concurrent processes each write the same text
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    except OSError:  # no writable cache: compile in memory (each process compiles)
        module = types.ModuleType(name)
        exec(compile(text.replace("CACHE = True", "CACHE = False"), f"<{name}>", "exec"),
             module.__dict__)
        sys.modules[name] = module
    return module
