"""The host side of the product (``affinebody._host``): the call from compiled code into a host
kernel (``callback``, against ``jax.pure_callback``), and the C heap that ``keep_freed_memory``
tunes for the command line and the workers."""

from __future__ import annotations

import functools
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import _host, _xla


def python(code: str, *args: str, env=None) -> subprocess.CompletedProcess:
    """``code`` run by this interpreter in a fresh process (JAX not yet started there)."""
    return subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True,
                          text=True, timeout=120)


def _kernel(a, b):
    """A host function of a batch: a [..., 3, 4], b [..., 4]; it checks its operands are
    NumPy arrays it may not write."""
    a, b = np.asarray(a), np.asarray(b)
    assert not a.flags.writeable and not b.flags.writeable
    return a * 2.0 + b[..., None, :], a.sum(-1)


def _shapes(a):
    return (jax.ShapeDtypeStruct(a.shape, a.dtype), jax.ShapeDtypeStruct(a.shape[:-1], a.dtype))


@pytest.mark.parametrize("vmap_method", ["sequential", "broadcast_all"])
def test_callback_is_pure_callback_under_jit_and_vmap(vmap_method):
    """_host.callback gives jax.pure_callback's results, bit for bit, called once, under jit,
    and under vmap and nested vmap (one batched operand, then two), for both vmap methods."""
    def ours(a, b):
        return _host.callback(_kernel, _shapes(a), a, b, vmap_method=vmap_method)

    def theirs(a, b):
        return jax.pure_callback(_kernel, _shapes(a), a, b, vmap_method=vmap_method)

    rng = np.random.default_rng(3)
    a, b = jnp.asarray(rng.standard_normal((3, 4))), jnp.asarray(rng.standard_normal(4))
    batch_a = jnp.asarray(rng.standard_normal((2, 3, 4)))
    batch_b = jnp.asarray(rng.standard_normal((5, 4)))
    cases = (
        (lambda f: f, (a, b)),
        (jax.jit, (a, b)),
        (lambda f: jax.jit(jax.vmap(f, (0, None))), (batch_a, b)),
        (lambda f: jax.vmap(jax.vmap(f, (0, None)), (None, 0)), (batch_a, batch_b)),
    )
    for transform, args in cases:
        got, want = transform(ours)(*args), transform(theirs)(*args)
        for x, y in zip(got, want, strict=True):
            assert x.shape == y.shape and np.array_equal(x, y)
    assert _host.CALLBACK_NAME in str(jax.make_jaxpr(ours)(a, b))


def test_callback_outside_jit_calls_the_function_and_compiles_nothing():
    """Outside jit, _host.callback calls the host function at once (read-only NumPy operands,
    the results of the compiled call bit for bit) and compiles nothing: compiling a one-call
    program each time never hit the cache, the function being a new partial at every call."""
    from jax._src import monitoring

    rng = np.random.default_rng(4)
    a, b = jnp.asarray(rng.standard_normal((3, 4))), jnp.asarray(rng.standard_normal(4))

    def call(a, b):
        return _host.callback(functools.partial(_kernel), _shapes(a), a, b)

    compiled = jax.jit(call)(a, b)
    call(a, b)  # the first call may compile the results' conversion, once
    compiles = []

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    monitoring.register_event_duration_secs_listener(listen)
    try:
        for _ in range(3):
            eager = call(a, b)
    finally:
        monitoring.unregister_event_duration_listener(listen)
    assert compiles == []
    for x, y in zip(eager, compiled, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)



def _filling(a, b, *, results):
    """_kernel's results written into the given arrays (``fills_results``)."""
    twice, sums = _kernel(a, b)
    assert all(r.flags.writeable for r in results)
    results[0][...], results[1][...] = twice, sums


@pytest.mark.parametrize("vmap_method", ["sequential", "broadcast_all"])
def test_a_callback_that_fills_its_results_gives_those_it_would_return(vmap_method):
    """With fills_results, the host function writes its results into the buffers it is
    given (XLA's own under jit): the same arrays, bit for bit, as the function returning
    them, outside jit, under jit and under vmap (each vmap method)."""
    def filled(a, b):
        return _host.callback(_filling, _shapes(a), a, b, vmap_method=vmap_method,
                              fills_results=True)

    def returned(a, b):
        return _host.callback(_kernel, _shapes(a), a, b, vmap_method=vmap_method)

    rng = np.random.default_rng(5)
    a, b = jnp.asarray(rng.standard_normal((3, 4))), jnp.asarray(rng.standard_normal(4))
    batch_a = jnp.asarray(rng.standard_normal((2, 3, 4)))
    for transform, args in ((lambda f: f, (a, b)), (jax.jit, (a, b)),
                            (lambda f: jax.jit(jax.vmap(f, (0, None))), (batch_a, b))):
        got, want = transform(filled)(*args), transform(returned)(*args)
        for x, y in zip(got, want, strict=True):
            assert x.shape == y.shape and np.array_equal(x, y)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA's CPU buffers, read in place")
def test_a_compiled_callback_reads_xlas_buffers_in_place():
    """Under jit on a CPU the host function gets views of XLA's operand buffers, not copies
    (JAX's own Python callback copies each operand, ~0.1 ms per MB): the 2 MB operand
    that the jitted function was called with has the address the host function sees."""
    seen = []

    def address(a):
        seen.append((a.ctypes.data, a.flags.writeable))
        return np.float64(a[-1])

    big = jnp.arange(2**18, dtype=jnp.float64)
    out = jax.jit(lambda a: _host.callback(address, jax.ShapeDtypeStruct((), jnp.float64), a))(
        big)
    assert float(out) == 2**18 - 1
    assert seen == [(big.unsafe_buffer_pointer(), False)]


def test_an_error_in_a_compiled_callback_is_raised_with_its_message():
    """An exception in the host function, or results of other shapes than declared, stop the
    jitted call with an error that says what happened (never a crash or silent garbage)."""
    shape = jax.ShapeDtypeStruct((2,), jnp.float64)

    def broken(a):
        raise ValueError("no such body")

    with pytest.raises(Exception, match="ValueError: no such body"):
        jax.jit(lambda a: _host.callback(broken, shape, a))(jnp.ones(2)).block_until_ready()
    with pytest.raises(Exception, match=r"returned float64\[3\] where float64\[2\]"):
        jax.jit(lambda a: _host.callback(lambda a: np.ones(3), shape, a))(
            jnp.ones(2)).block_until_ready()

# 16 arrays of 2 MiB allocated, touched and freed, four times over: the page faults of each round
REFILL = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from affinebody import _host
    assert _host.keep_freed_memory()
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    start = faults()
    arrays = [np.ones(2**18) for _ in range(16)]
    del arrays
    print(faults() - start)
"""


def refill_faults(mode: str) -> list[int]:
    out = python(REFILL, mode)
    assert out.returncode == 0, out.stderr
    return [int(line) for line in out.stdout.split()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt (Linux)")
def test_freed_memory_is_refilled_without_page_faults():
    """32 MiB freed and allocated again: with glibc's defaults the heap gives the pages back
    and every round faults them in afresh (8192 pages of 4 KiB); after keep_freed_memory the
    rounds after the first reuse the mapped pages (no fault per MiB)."""
    default, kept = refill_faults("default"), refill_faults("keep")
    pages = 16 * 2 * 2**20 // 4096
    assert min(default[1:]) > pages // 2, default  # the pattern does fault by default
    assert kept[0] > pages // 2, kept  # the first round maps the pages
    assert max(kept[1:]) < pages // 100, kept  # later rounds reuse them


def test_xla_flags_go_in_front_keep_the_users_and_are_known_to_this_xla():
    """compile_faster's flags go before the first word that is not a flag (XLA stops reading
    there), a flag the user set keeps the user's value, and flags_known() says truly whether
    this jaxlib accepts them: XLA aborts a process on a flag it does not know, so a JAX
    computation in a process with them finishes exactly when flags_known() (jaxlib 0.10: yes;
    0.12: no, and compile_faster then sets none). A flag XLA does not know stops the process:
    the check can fail."""
    assert _xla.with_flags("--xla_a=1 words", ("--xla_b=2", "--xla_a=3")) == \
        "--xla_b=2 --xla_a=1 words"
    run = "import jax.numpy as jnp; print(float(jnp.arange(4.0).sum()))"

    def finishes(flags: str) -> bool:
        out = python(run, env={**os.environ, "XLA_FLAGS": flags})
        return out.returncode == 0 and out.stdout.strip() == "6.0"

    assert finishes(_xla.with_flags("", _xla.FAST_COMPILATION)) == _xla.flags_known()
    assert not finishes("--xla_cpu_no_such_flag_of_affinebody=true")


POOL = """
import os, sys
import jax.numpy as jnp
from jax._src import xla_bridge
from affinebody import _xla
set_here = _xla.single_xla_thread()
started = xla_bridge.backends_are_initialized()
jnp.arange(4.0).sum().block_until_ready()
names = [open(f"/proc/self/task/{t}/comm").read() for t in os.listdir("/proc/self/task")]
pool = sum(n.startswith("tf_XLAEigen") for n in names)
print(set_here, started, os.environ.get("PJRT_NPROC"), pool)
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="threads counted in /proc")
def test_single_xla_thread_sizes_xla_pool_and_keeps_the_users_size():
    """single_xla_thread sets PJRT_NPROC=1 before JAX starts its backend and XLA's CPU client
    then has one pool thread; a size the user gave (here 3, which XLA honours: 3 threads) is
    kept."""
    def pool(**sizes):
        env = {k: v for k, v in os.environ.items() if k not in _xla.POOL_SIZE_VARIABLES}
        out = python(POOL, env={**env, **sizes})
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    assert pool() == ["True", "False", "1", "1"]
    assert pool(PJRT_NPROC="3") == ["False", "False", "3", "3"]
    assert pool(NPROC="3") == ["False", "False", "None", "3"]
