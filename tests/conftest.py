"""Test-session set-up: float64 JAX for every test, and the hypothesis profiles.

The library itself never flips the x64 flag (tests/test_checks.py checks that it refuses
float32); the suite enables it once here, as the CLI does for its own process.
"""

import os

# One BLAS thread per process: on the 2-core CI machine, threaded BLAS on small matrices is
# 16-60x slower than serial (measured), and pytest-xdist already uses both cores.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# Cheaper XLA compilation for the suite (and the CLI subprocesses it starts, which inherit the
# environment): most of its time is compiling many small functions once each, not running them.
# LLVM's expensive passes off and backend optimisation level 0 cut the CPU time of the heaviest
# files by about 14 % (test_constraints + test_nonholonomic: 266 s against more than 309 s of
# CPU, measured side by side). Results may differ from optimised code in the last bits only
# (float64 either way); the whole suite passes with it. XLA:CPU's MLIR fusion emitters off
# (the elemental IR emitter fuses instead) halves the compile time again: the tracker of
# test_constraints (RATTLE on R+SO) 2.43 -> 1.08 s, H-af on UL 2.43 -> 0.98 s, exact drifts
# on SL 1.09 -> 0.56 s, with the same energy errors; test_constraints 53.5 -> 36.2 s,
# test_nonholonomic 84 -> 48 s, test_kinetic 64 -> 28 s (one process each, back to back).
# Local Dask workers get sweep.WORKER_ENV instead of this environment: the fixture
# _cheap_compilation_in_dask_workers gives them these flags too.
# Each worker is pinned to one core (below), so XLA's parallel LLVM code generation (the
# module split into parts compiled on its thread pool) only adds the cost of splitting and
# linking: one part is 10 % faster for the suite (test_nonholonomic + test_kinetic +
# test_cli_sim on one core each, side by side and swapped: 175 s against 196 s, twice).
# The command line keeps XLA's default, which its two cores use (the demo is no faster
# with one part).
# The fusion-emitter flag is the product's FAST_COMPILATION, which jaxlib >= 0.11 no longer
# knows (XLA aborts the process on an unknown flag): it is added only where flags_known().
from affinebody._xla import (  # noqa: E402  (imports no JAX)
    FAST_COMPILATION,
    flags_known,
    pin_to_one_cpu,
    with_flags,
)

SUITE_XLA_FLAGS = ("--xla_backend_optimization_level=0",
                   "--xla_llvm_disable_expensive_passes=true",
                   *(FAST_COMPILATION if flags_known() else ()),
                   "--xla_cpu_parallel_codegen_split_count=1")

os.environ["XLA_FLAGS"] = with_flags(os.environ.get("XLA_FLAGS", ""), SUITE_XLA_FLAGS)

# One compilation cache on disk for the whole run, new and empty each time (as on CI): both
# workers and every command-line process the tests start (they inherit the environment)
# reuse what another compiled (the same small programs, a CLI run's set-up) instead of
# compiling it again. Four CLI-heavy files: 92-111 s against 103-118 s (side by side, two
# pairs). Executables with host callbacks are not cached by JAX; nothing else changes. JAX
# writes an entry without a lock (its locking cache scans the folder at every write): a read
# racing the write of the same entry fails its decompression, which JAX turns into a warning
# and a compilation. On Intel CPUs whose LLVM tuning has prefer-no-gather, jaxlib 0.10.1 logs
# two false-alarm lines on stderr per program loaded from the cache (openxla/xla#44565): a
# test that reads a child process's stderr runs that child without JAX_COMPILATION_CACHE_DIR.
_CACHE = "JAX_COMPILATION_CACHE_DIR"
if "PYTEST_XDIST_WORKER" not in os.environ and _CACHE not in os.environ:
    import tempfile

    os.environ[_CACHE] = _OWN_CACHE = tempfile.mkdtemp(prefix="affinebody-test-jit-")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
else:
    _OWN_CACHE = None


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        import shutil

        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


# One core per xdist worker (gw0 -> first CPU, gw1 -> second, ...): see pin_to_one_cpu for the
# jaxlib LAPACK thread-pool deadlock this avoids.
# Only inside workers: the xdist controller imports this file too, and workers inherit its mask.
if "PYTEST_XDIST_WORKER" in os.environ:
    pin_to_one_cpu(int(os.environ["PYTEST_XDIST_WORKER"].removeprefix("gw") or 0))

import gc  # noqa: E402

# Tracing creates and drops many small Python objects; the collector's default first
# threshold (700 allocations) runs it so often that a larger one saves about 3 % of the
# suite's time (the same three files: 159-167 s against 165-172 s, side by side and swapped).
gc.set_threshold(20_000, 20, 50)

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

jax.config.update("jax_enable_x64", True)

settings.register_profile(
    "default",
    max_examples=20,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile("ci", parent=settings.get_profile("default"), derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")

#: Test files that take longest (seconds in ``make test``, largest first; measured per worker
#: on the 2-core machine, 2026-11-28: nonholonomic 60, integrators 51, constraints 51, kinetic
#: 49, pair_kernels 47, neighbor_runs 44, sweep 43, quantum_evolution3 42,
#: quantum_orientations3 40, barostat 38, crash_safety 38, potentials 37, quantum_operators 36,
#: quantum_transitions 36, quantum_limits 36, quantum_densities 32, cli_neighbor_list 30,
#: thermostats 30, groups 28, quantum_n3 27, quantum_evolution 24, cli_sim 24, brackets 24,
#: linalg 23, quantum_completeness 22, pressure 21, quantum_n3_certified 20, phonons 20;
#: every other file 18 s or less). ``make test`` distributes whole files over two workers
#: (--dist loadfile) in collection order (--no-loadscope-reorder: pytest-xdist would otherwise
#: order the files by their number of tests, which started test_nonholonomic at 334 s of 591);
#: starting with the longest files keeps a long file from starting last while the other worker
#: idles (longest-processing-time-first). Files not listed keep their order.
LONGEST_FIRST = ("test_nonholonomic", "test_integrators", "test_constraints", "test_kinetic",
                 "test_pair_kernels", "test_neighbor_runs", "test_sweep",
                 "test_quantum_evolution3", "test_quantum_orientations3", "test_barostat",
                 "test_crash_safety", "test_potentials", "test_quantum_operators",
                 "test_quantum_transitions", "test_quantum_limits", "test_quantum_densities",
                 "test_cli_neighbor_list", "test_thermostats", "test_groups", "test_quantum_n3",
                 "test_quantum_evolution", "test_cli_sim", "test_brackets", "test_linalg",
                 "test_quantum_completeness", "test_pressure", "test_quantum_n3_certified",
                 "test_phonons")


@pytest.fixture(autouse=True, scope="session")
def _cheap_compilation_in_dask_workers():
    """The suite's XLA flags for the local Dask clusters the tests start (their workers get
    sweep.WORKER_ENV, not this environment), with the product's flags, which the workers
    keep (one thread). A thermal sweep task compiles in 1.2 s instead of 5.2 s (one fresh
    worker process, measured with the product's flags of before, which lacked
    --xla_cpu_use_fusion_emitters=false)."""
    from affinebody import sweep

    flags = with_flags(sweep.WORKER_ENV["XLA_FLAGS"], SUITE_XLA_FLAGS)
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sweep.WORKER_ENV, "XLA_FLAGS", flags)
        yield


def pytest_collection_modifyitems(config, items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: order kept


#: Memory mappings a worker may hold before its compiled executables are dropped. Every XLA:CPU
#: executable maps about six regions (code, read-only data, data; measured with jax 0.10) and
#: keeps them while JAX's caches hold it; Linux refuses a process more than vm.max_map_count
#: mappings (65530 by default), and XLA then crashes with a segmentation fault inside LLVM. One
#: worker of ``make test`` reached 53,704 mappings (a CI run crossed the limit and died at 98 %).
MAPPINGS_BEFORE_CLEARING = 20_000


def _mappings():
    """Number of this process's memory mappings (Linux); 0 where /proc is not there."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_executables_when_many():
    """After each test file, drop JAX's compiled executables if the mappings grow large.

    Recompiling costs a file that reuses another file's functions a little time; holding every
    executable of the whole suite in one process costs the process (see MAPPINGS_BEFORE_CLEARING).
    """
    yield
    if _mappings() > MAPPINGS_BEFORE_CLEARING:
        jax.clear_caches()
        gc.collect()
