"""Pair kernels over a neighbour list: energies and generalised forces equal the all-pairs
autodiff of affinebody.potentials (to 1e-12) on random periodic systems, for every pair
variable r, D, det, K_a, M_a and every built-in pair family, cut-offs on r and on D, n = 2 and
3, for both kernels (the compiled host kernel that runs on a CPU and the JAX kernel that runs
on a GPU); also inside compiled code (the path ``simulate.run`` takes), after strong
deformation, after a capacity overflow, through jax.grad, and along a trajectory."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from affinebody import kinetic as kin
from affinebody import neighbors as nb
from affinebody import pair_kernels as pk
from affinebody.potentials import (
    Cutoff,
    Dilatation,
    Gaussian,
    HarmonicInvariants,
    LennardJones,
    Morse,
    PairPotential,
    StVenantKirchhoff,
    generalized_forces,
    total_potential,
)
from affinebody.space import free_space, orthorhombic, triclinic
from affinebody.state import State
from affinebody.system import HamiltonianSystem

BODIES = 40
BOX3 = triclinic([[5.0, 0.8, -0.5], [0.0, 5.2, 0.6], [0.0, 0.0, 5.1]])
BOX2 = orthorhombic((5.0, 5.4))
CUBE = orthorhombic((5.0, 5.0, 5.0))  # the box kind of `affinebody run`'s lattices
DEMO = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"
EVERYTHING3 = "exp(-D**2)*(M2 - 2)**2 + 0.3*det + 0.01*M3 + 0.02*K2 + K1*exp(-r) + 0.001*K3"

CASES = {
    "demo-3d": (PairPotential.from_expression(DEMO, 3, cutoff=Cutoff(1.5), box=BOX3), 3),
    "demo-cubic-3d": (PairPotential.from_expression(DEMO, 3, cutoff=Cutoff(1.5), box=CUBE), 3),
    "all-variables-3d": (
        PairPotential.from_expression(EVERYTHING3, 3, cutoff=Cutoff(1.5, 1.2), box=BOX3), 3),
    "material-affine-arrays-3d": (PairPotential(
        lambda M, det: 0.01 * jnp.sum(M**2, axis=-1) + jnp.exp(-0.1 * M[..., 1]) * det,
        ("M", "det"), cutoff=Cutoff(1.5), box=BOX3), 3),
    "lennard-jones-in-D-free-3d": (
        LennardJones(0.3, 0.45, argument="D", cutoff=Cutoff(1.2, variable="D")), 3),
    "all-variables-2d": (PairPotential.from_expression(
        "exp(-D**2)*(M1 - 1.5)**2 + det + 0.1*K2 + 0.2*M2 + r", 2, cutoff=Cutoff(1.5),
        box=BOX2), 2),
    "morse-r-2d": (Morse(1.0, 3.0, 1.0, cutoff=Cutoff(1.5, 1.2), box=BOX2), 2),
    "gaussian-in-D-free-2d": (
        Gaussian(-0.7, 0.5, argument="D", cutoff=Cutoff(1.3, variable="D")), 2),
    "harmonic-M-3d": (HarmonicInvariants(0.8, "M", cutoff=Cutoff(1.5), box=BOX3), 3),
    "harmonic-K-2d": (HarmonicInvariants(0.8, "K", cutoff=Cutoff(1.5), box=BOX2), 2),
}


def configuration(rng, n: int, space, stretch: float = 0.25):
    if space.periodic:
        x = rng.uniform(-0.5, 1.5, size=(BODIES, n)) @ space.matrix.T
    else:
        x = rng.uniform(-2.0, 2.0, size=(BODIES, n))
    phi = np.eye(n) + stretch * rng.normal(size=(BODIES, n, n))
    phi[np.linalg.det(phi) < 0, 0] *= -1
    return jnp.asarray(x), jnp.asarray(phi)


@jax.jit(static_argnums=0)
def _all_pairs(potential, x, phi):
    return potential.energy(x, phi), generalized_forces(potential, x, phi)


def all_pairs(potential, x, phi):
    """The reference: sum over all N(N-1)/2 pairs, gradients by autodiff (potentials.py)."""
    energy, (fx, fphi) = _all_pairs(potential, x, phi)
    return float(energy), -np.asarray(fx), -np.asarray(fphi)


def assert_same(result, reference, rtol=1e-12):
    e, gx, gphi = (np.asarray(a) for a in result)
    e_ref, gx_ref, gphi_ref = reference
    scale = max(np.max(np.abs(gx_ref)), np.max(np.abs(gphi_ref)))
    assert scale > 1e-3  # the forces are not trivially zero
    assert abs(float(e) - e_ref) <= rtol * max(1.0, abs(e_ref)) * 10
    np.testing.assert_allclose(gx, gx_ref, rtol=0, atol=rtol * scale)
    np.testing.assert_allclose(gphi, gphi_ref, rtol=0, atol=rtol * scale)


def list_for(potential, x, phi, skin=0.3):
    """A list with fixed capacities, so that equal cut-offs share one compiled build."""
    return nb.allocate(potential.space, x, phi, potential.cutoff.r_cut,
                       potential.cutoff.variable, skin, capacity=BODIES * (BODIES - 1) // 2,
                       cell_capacity=BODIES)


@jax.jit(static_argnums=0)
def _in_loop(potential, x, phi, nbrs):
    """What a kick in ``simulate.run`` computes: jax.grad of the list energy, jitted."""
    energy = lambda x, phi: potential.energy(x, phi, nbrs)  # noqa: E731
    return energy(x, phi), *jax.grad(energy, argnums=(0, 1))(x, phi)


@pytest.mark.parametrize("case", list(CASES))
def test_list_forces_equal_all_pairs_forces_host_and_jax(case):
    potential, n = CASES[case]
    rng = np.random.default_rng(sum(map(ord, case)))
    x, phi = configuration(rng, n, potential.space)
    spec, nbrs = list_for(potential, x, phi)
    reference = all_pairs(potential, x, phi)
    assert np.sum(np.abs(reference[1]) > 0) > BODIES  # many bodies interact
    jax_result = pk.energy_and_gradients_jit(
        potential, potential.space, x, phi, nbrs.i, nbrs.j, nbrs.count, 64)  # several chunks
    assert_same(jax_result, reference)
    host_result = pk.energy_and_gradients_host(
        potential, potential.space, x, phi, nbrs.i, nbrs.j, nbrs.count)
    assert_same(host_result, reference)
    # inside compiled code the backend's kernel runs: on a CPU the host kernel (through
    # _host.callback), on a GPU the JAX one with its large passes (no host round trip)
    assert pk.host_kernel_in_use() == (jax.default_backend() == "cpu")
    assert_same(_in_loop(potential, x, phi, nbrs), reference)
    # translation invariance: the pair forces on the centres sum to zero
    np.testing.assert_allclose(np.sum(host_result[1], axis=0), 0.0,
                               atol=1e-12 * np.max(np.abs(reference[1])))
    if "material-affine" in potential.symmetry:  # Noether (31): sum_K phi_K^T dV/dphi_K = 0
        charge = np.einsum("kia,kib->ab", np.asarray(phi), host_result[2])
        assert np.max(np.abs(charge)) <= 1e-11 * np.max(np.abs(reference[2]))


@pytest.mark.parametrize("case", ["all-variables-3d", "all-variables-2d"])
def test_jax_kernel_in_its_gpu_form_equals_all_pairs(monkeypatch, case):
    """On a GPU the JAX kernel's 3x3 products are written elementwise (_linalg.fused_products),
    with the per-pair chain rule through phi^-1 and det phi; forced here on the CPU, it must
    give the all-pairs autodiff forces like the batched-dot form above (every scalar: r, D,
    det, K_a, M_a in both orders)."""
    from affinebody import _linalg

    monkeypatch.setattr(_linalg, "fused_products", lambda: True)
    potential, n = CASES[case]
    x, phi = configuration(np.random.default_rng(11), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    # a new function object: traced now, with the elementwise products
    kernel = jax.jit(lambda x, phi, i, j, count: pk.energy_and_gradients(
        potential, potential.space, x, phi, i, j, count, 64))
    assert_same(kernel(x, phi, nbrs.i, nbrs.j, nbrs.count), all_pairs(potential, x, phi))


@pytest.mark.parametrize("case", ["all-variables-3d", "all-variables-2d",
                                  "lennard-jones-in-D-free-3d"])
def test_triton_kernels_of_the_gpu_equal_all_pairs_in_the_pallas_interpreter(case):
    """On a GPU the JAX kernel's passes over pairs are the Pallas (Triton) kernels of
    affinebody._pair_triton (pair_program "triton"); the same kernels in Pallas' interpreter
    must give the all-pairs autodiff energy and forces, and from the same pass the virial of
    the XLA program (every scalar in both orders; a cut-off on D in free space; chunks of 64
    pairs, each padded to the kernels' block of 128)."""
    potential, n = CASES[case]
    x, phi = configuration(np.random.default_rng(11), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    args = (potential, potential.space, x, phi, nbrs.i, nbrs.j, nbrs.count, 64)
    assert int(nbrs.count) > 2 * 64 and 64 % pk._pair_triton.BLOCK
    *result, virial = pk.energy_and_gradients_jit(*args, virial=True,
                                                  program="triton-interpret")
    assert_same(result, all_pairs(potential, x, phi))
    reference = pk.pair_virial(*args[:7], chunk=64)  # the XLA program's
    np.testing.assert_allclose(virial, reference, rtol=0,
                               atol=1e-12 * float(jnp.max(jnp.abs(reference))))


def test_triton_run_sums_hold_for_pairs_in_any_order(monkeypatch):
    """The rows kernel sums body K's rows over runs of pairs of one K (_pair_triton._run_sums):
    a list in the order of neighbors.build has one run per K, but the sums must not depend on
    it. The same pairs reversed, interleaved (K in many short runs, one-pair runs, runs across
    blocks) and shuffled give the all-pairs forces too. With f and its partials in XLA
    between the kernels (the way for an f that Triton cannot run; the test above runs f in
    the first kernel)."""
    monkeypatch.setattr(pk, "F_IN_TRITON", False)
    potential, n = CASES["all-variables-3d"]
    x, phi = configuration(np.random.default_rng(11), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    count = int(nbrs.count)
    i, j = np.asarray(nbrs.i[:count]), np.asarray(nbrs.j[:count])
    rng = np.random.default_rng(3)
    reference = all_pairs(potential, x, phi)
    for order in (np.arange(count)[::-1], np.argsort(np.arange(count) % 7, kind="stable"),
                  rng.permutation(count)):
        result = pk.energy_and_gradients_jit(potential, potential.space, x, phi, i[order],
                                             j[order], count, 256, program="triton-interpret")
        assert_same(result, reference)


#: The custom call through which XLA runs a Pallas Triton kernel on a GPU.
TRITON_CALL = "__gpu$xla.gpu.triton"


def export_chunk_for_cuda(potential, n: int, pairs: int = 1024, bodies: int = 50,
                          batch: int | None = None, f_in_kernel: bool = False):
    """jax.export of one chunk of the Triton program of ``potential`` for the "cuda"
    platform, an H100 named as the target device (JAX 0.12 asks for one where no GPU is
    present); with ``batch``, vmapped over that many systems (the samples of a sweep); with
    ``f_in_kernel`` f and its partials in the first kernel (the partials kernel) instead of
    in XLA between the two; also what tools/triton_offline.py compiles."""
    from jax import export
    from jax.sharding import AbstractDevice, AbstractMesh, use_abstract_mesh

    layout, padding = pk._triton_layout(potential, n)
    energy = pk._pair_triton.ColumnEnergy(potential, layout) if f_in_kernel else None

    def chunk(u, i, j, valid, table):
        return pk._pair_triton.chunk_rows(layout, pk._scalar_values_and_partials(potential, n),
                                          padding, u, i, j, valid, table, energy=energy)

    lead = () if batch is None else (batch,)
    shapes = [jax.ShapeDtypeStruct(lead + shape, dtype) for shape, dtype in (
        ((pairs, n), jnp.float64), ((pairs,), jnp.int32), ((pairs,), jnp.int32),
        ((pairs,), bool), ((bodies * layout.columns,), jnp.float64))]
    h100 = AbstractDevice(device_kind="NVIDIA H100", num_cores=None, platform="gpu")
    with use_abstract_mesh(AbstractMesh((1,), ("bodies",), abstract_device=h100)):
        return export.export(jax.jit(chunk if batch is None else jax.vmap(chunk)),
                             platforms=["cuda"], disabled_checks=[
            export.DisabledSafetyCheck.custom_call(TRITON_CALL)])(*shapes)


def test_triton_kernels_lower_to_triton_for_a_cuda_gpu():
    """Without a GPU, the kernels still go through Pallas' Triton lowering for CUDA
    (:func:`export_chunk_for_cuda`): every operation they use has a Triton form, and a chunk
    of the JAX kernel is XLA around two Triton calls (scalars, or with f inside the partials,
    then rows). Vmapped, as the
    samples of a sweep run them, each call gets a second grid axis over the batch."""
    import re

    potential, n = CASES["all-variables-3d"]  # every scalar: the kernels' every operation
    for f_in_kernel, first in ((False, "scalars"), (True, "partials")):
        module = export_chunk_for_cuda(potential, n, f_in_kernel=f_in_kernel).mlir_module()
        assert module.count(f"custom_call @{TRITON_CALL}(") == 2
        assert f"affinebody_pair_{first}" in module and "affinebody_pair_rows" in module
    # the demo's f (exp, a power, negated literals) inside a kernel
    demo, n3 = CASES["demo-3d"]
    assert "affinebody_pair_partials" in export_chunk_for_cuda(
        demo, n3, f_in_kernel=True).mlir_module()
    batched = export_chunk_for_cuda(potential, n, batch=3).mlir_module()
    grids = re.findall(r"grid_x = (\d+) : i32, grid_y = (\d+) : i32", batched)
    assert grids == [(str(1024 // pk._pair_triton.BLOCK), "3")] * 2
    x, phi = configuration(np.random.default_rng(5), n, potential.space)
    with pytest.raises(ValueError, match="pair program 'cuda': expected one of xla, triton"):
        pk.energy_and_gradients(potential, potential.space, x, phi, jnp.zeros(1, int),
                                jnp.ones(1, int), 1, program="cuda")


def test_a_gpu_where_the_triton_kernels_do_not_build_runs_the_xla_program(monkeypatch):
    """On a GPU the default program is "triton" only where its kernels build
    (pk.triton_builds, once per process and layout). Here the backend claims to be a GPU
    while JAX's is the CPU, where Pallas' Triton kernels cannot be compiled: the forces must
    still come, from the XLA program (bit for bit), with one warning that says so; the
    probe itself passes for kernels that do run (the interpreter's, inside a trace as a run
    calls it)."""
    potential, n = CASES["morse-r-2d"]
    x, phi = configuration(np.random.default_rng(3), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    args = (potential, potential.space, x, phi, nbrs.i, nbrs.j, nbrs.count, 64)
    xla = pk.energy_and_gradients(*args, program="xla")
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.delenv(pk.PAIR_PROGRAM_VARIABLE, raising=False)
    pk.triton_builds.cache_clear()
    with pytest.warns(RuntimeWarning, match="Triton pair kernels do not build here .*XLA"):
        result = pk.energy_and_gradients(*args)
    for a, b in zip(result, xla, strict=True):
        np.testing.assert_array_equal(a, b)
    assert_same(result, all_pairs(potential, x, phi))
    assert pk.pair_program(potential, n) == "xla"  # decided once: no second probe
    assert pk.kernel_in_use(potential, n) == "JAX kernel, xla program"  # --verbose says so
    layout, padding = pk._triton_layout(potential, n)
    traced = jax.jit(lambda: jnp.asarray(pk.triton_builds(layout, padding,
                                                          "triton-interpret")))
    assert bool(traced())
    pk.triton_builds.cache_clear()  # no CPU verdict left for a later test


def test_f_runs_in_the_triton_kernel_only_where_it_builds_there(monkeypatch):
    """The Triton program computes f and its partials in its first kernel (pk.triton_energy)
    for an f of scalars only; an f of a whole array K or M gets XLA's f between the kernels,
    and so does an f that does not build inside a kernel on the GPU (checked once, with one
    warning that says so; here the backend claims to be a GPU, where a compiled Pallas kernel
    cannot build). $AFFINEBODY_PAIR_PROGRAM skips the check."""
    morse, n = CASES["morse-r-2d"]
    assert morse.columnwise and not CASES["harmonic-M-3d"][0].columnwise
    assert pk.triton_energy(*CASES["harmonic-M-3d"], "triton-interpret") is None
    energy = pk.triton_energy(morse, n, "triton-interpret")
    assert isinstance(energy, pk._pair_triton.ColumnEnergy)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.delenv(pk.PAIR_PROGRAM_VARIABLE, raising=False)
    pk.triton_builds.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="f in the Triton pair kernel does not build "
                                                "here .*f in XLA between them"):
            assert pk.triton_energy(morse, n, "triton") is None
        monkeypatch.setenv(pk.PAIR_PROGRAM_VARIABLE, "triton")
        assert pk.triton_energy(morse, n, "triton") == energy
        # what `affinebody run --verbose` prints
        assert pk.kernel_in_use(morse, n) == "JAX kernel, triton program (f in the first kernel)"
        assert (pk.kernel_in_use(*CASES["harmonic-M-3d"])
                == "JAX kernel, triton program (f in XLA between the kernels)")
    finally:
        pk.triton_builds.cache_clear()  # no verdict of the pretended GPU left for later tests


def test_the_pair_program_variable_chooses_the_program_or_says_what_is_wrong(monkeypatch):
    potential, n = CASES["morse-r-2d"]
    monkeypatch.setenv(pk.PAIR_PROGRAM_VARIABLE, "cuda")
    with pytest.raises(ValueError, match="AFFINEBODY_PAIR_PROGRAM=cuda: expected xla or"):
        pk.pair_program(potential, n)
    monkeypatch.setenv(pk.PAIR_PROGRAM_VARIABLE, "triton")
    with pytest.raises(ValueError, match="=triton needs a GPU .*here is cpu"):
        pk.pair_program(potential, n)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert pk.pair_program(potential, n) == "triton"  # chosen: no probe
    monkeypatch.setenv(pk.PAIR_PROGRAM_VARIABLE, "xla")
    assert pk.pair_program(potential, n) == "xla"
    assert pk.triton_builds.cache_info().currsize == 0


@pytest.mark.parametrize("case", ["material-affine-arrays-3d", "demo-3d", "demo-cubic-3d"])
def test_host_kernel_over_several_chunks_and_threads_is_the_same_sum(monkeypatch, case):
    """Chunks of pairs (per-body sums carried between callbacks) give the all-pairs forces,
    and the threads' fixed parts give the same bits on one thread or two: with a Python f
    (XLA evaluates it between two callbacks) and a config expression (the fused kernel)."""
    potential, n = CASES[case]
    x, phi = configuration(np.random.default_rng(3), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    args = (potential, potential.space, x, phi, nbrs.i, nbrs.j, nbrs.count)
    monkeypatch.setattr(pk, "HOST_CHUNK_PAIRS", 97)  # several chunks, the last one partial
    monkeypatch.setattr(pk, "HOST_THREAD_MIN_ROWS", 0)
    chunked = jax.jit(pk._host_pair_sum, static_argnums=(0, 1),
                      static_argnames=("gradients", "virial"))
    assert nbrs.i.shape[0] > 3 * 97
    kinds = ({}, {"virial": True}, {"gradients": False, "virial": True})
    fused = pk.fused_on_host(potential, n)
    calls = []
    if fused:  # one thread and two run the same compiled function (FMA contraction, hence
        # the last bit, depends on where LLVM inlines a loop: a second function for one
        # thread had given dV/dx an ulp apart in a 4096-body run)
        kernels = pk._fused_kernel(n, pk._fused_source(potential, n))
        thread = kernels.fused_thread
        monkeypatch.setattr(kernels, "fused_thread",
                            lambda *a: calls.append(pk._host.host_threads()) or thread(*a))
    monkeypatch.setattr(pk._host, "threads", lambda parts: 1)
    one = [chunked(*args, **kind) for kind in kinds]
    monkeypatch.setattr(pk._host, "threads", lambda parts: 2)
    two = [chunked(*args, **kind) for kind in kinds]
    if fused:
        assert calls.count(1) == 3 * 3 + 3 * 3 and calls.count(2) == 3 * 2
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(two), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # bit for bit
    assert_same(one[0], all_pairs(potential, x, phi))
    # the virial of the same pass with and without gradients (the fused kernel: two threads
    # with barriers between their phases, or one after the other)
    np.testing.assert_array_equal(np.asarray(one[1][-1]), np.asarray(one[2][-1]))
    assert float(one[2][0]) == float(one[0][0])


def _with_timeout(call, seconds=120.0):
    """call() on a thread of its own; its outcome, or a failure where it does not return in
    time (a thread that waits for ever on a barrier would otherwise hang the suite)."""
    import threading

    outcome = {}

    def target():
        try:
            outcome["value"] = call()
        except Exception as error:  # noqa: BLE001 - handed to the test
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "the host kernel did not return (a thread waits for ever)"
    return outcome


def test_two_host_threads_neither_hang_nor_raise_on_a_singular_body_or_a_failing_part(
        monkeypatch):
    """The fused kernel's two threads wait for each other between phases: a singular phi
    gives a non-finite energy and forces (as the JAX path, for the run's finiteness check),
    the same bits on one thread and two; where one thread's part raises, the other is
    released from the barrier and the error comes back with its message."""
    potential, n = CASES["demo-cubic-3d"]
    x, phi = configuration(np.random.default_rng(3), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    singular = phi.at[0].set(0.0)
    call = jax.jit(pk._host_pair_sum, static_argnums=(0, 1))
    args = (potential, potential.space, x, singular, nbrs.i, nbrs.j, nbrs.count)
    monkeypatch.setattr(pk, "HOST_THREAD_MIN_ROWS", 0)
    results = {}
    for threads in (1, 2):
        monkeypatch.setattr(pk._host, "threads", lambda parts, threads=threads: threads)
        outcome = _with_timeout(lambda: jax.tree.map(np.asarray, call(*args)))
        assert "error" not in outcome, outcome.get("error")
        results[threads] = outcome["value"]
    assert not np.isfinite(results[1][0]) and not np.isfinite(results[1][2][0]).all()
    for a, b in zip(results[1], results[2], strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    reference = _all_pairs(potential, x, singular)
    assert not np.isfinite(float(reference[0]))

    kernels = pk._fused_kernel(n, pk._fused_source(potential, n))
    thread = kernels.fused_thread
    for failing in (0, 1):
        def part(k, *rest, failing=failing):
            if k == failing:
                raise RuntimeError(f"part {k} failed")
            return thread(k, *rest)

        monkeypatch.setattr(kernels, "fused_thread", part)
        outcome = _with_timeout(lambda: call(potential, potential.space, x, phi, nbrs.i,
                                             nbrs.j, nbrs.count)[0].block_until_ready())
        assert f"part {failing} failed" in str(outcome.get("error"))


def test_forces_after_strong_deformation_and_after_a_capacity_overflow():
    # affine cut-off in free space: stretching by up to 2.2 widens every body's reach
    potential, n = CASES["lennard-jones-in-D-free-3d"]
    rng = np.random.default_rng(11)
    x, phi = configuration(rng, n, free_space(), stretch=0.1)
    spec, nbrs = nb.allocate(free_space(), x, phi, 1.2, "D", 0.2)  # capacities measured here
    rotations = np.linalg.qr(rng.normal(size=(BODIES, 3, 3)))[0]
    deformed = jnp.asarray(rotations * np.array([2.2, 1.0, 0.45])) @ phi
    assert bool(nb.needs_rebuild(spec, nbrs, x, deformed))
    rebuilt = nb.build_jit(spec, x, deformed)
    # the reach outgrew the cells and the pairs the capacity
    assert int(rebuilt.overflow) & nb.REACH_OVERFLOW and int(rebuilt.overflow) & nb.PAIR_OVERFLOW
    with pytest.raises(nb.NeighborListOverflow):
        nb.check(rebuilt)
    spec, nbrs = list_for(potential, x, deformed, skin=0.2)
    reference = all_pairs(potential, x, deformed)
    assert_same(pk.energy_and_gradients_host(potential, free_space(), x, deformed, nbrs.i,
                                             nbrs.j, nbrs.count), reference)
    assert_same(pk.energy_and_gradients_jit(potential, free_space(), x, deformed, nbrs.i,
                                            nbrs.j, nbrs.count, 64), reference)


def test_jax_grad_of_the_list_energy_is_the_closed_form_gradient():
    potential, n = CASES["all-variables-3d"]
    x, phi = configuration(np.random.default_rng(5), n, BOX3)
    _, nbrs = list_for(potential, x, phi)
    energy = jax.jit(lambda a, b, l: potential.energy(a, b, l))
    grad = jax.jit(jax.grad(lambda a, b, l: potential.energy(a, b, l), argnums=(0, 1)))
    gx, gphi = grad(x, phi, nbrs)
    assert_same((energy(x, phi, nbrs), gx, gphi), all_pairs(potential, x, phi))
    total = total_potential([potential, Dilatation(2.0)])
    assert float(total.energy(x, phi, nbrs)) == pytest.approx(
        float(total.energy(x, phi)), rel=1e-12)


def test_energy_conservation_is_unchanged_with_the_list():
    # 27 bodies on a lattice in a periodic box; d'Alembert kinetic energy (a cheap exact drift),
    # the demo pair potential plus one-body confinement of phi; 120 Strang steps with the list
    # (updated every step inside the compiled loop) and with all pairs
    side, spacing = 3, 1.3
    box = orthorhombic((side * spacing,) * 3)
    pair = PairPotential.from_expression(DEMO, 3, cutoff=Cutoff(1.6), box=box)
    potential = total_potential([pair, Dilatation(5.0), StVenantKirchhoff(0.5, 1.0)])
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(0.3 * jnp.eye(3)))
    system = HamiltonianSystem(kinetic, potential)
    rng = np.random.default_rng(9)
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = jnp.asarray(spacing * grid + 0.05 * rng.normal(size=grid.shape))
    phi = jnp.asarray(np.eye(3) + 0.05 * rng.normal(size=(len(grid), 3, 3)))
    state = State(x, phi, jnp.asarray(0.4 * rng.normal(size=x.shape)),
                  jnp.asarray(0.05 * rng.normal(size=phi.shape)))
    spec, nbrs = nb.allocate(box, x, phi, 1.6, "r", 0.25)
    dt, steps = 0.01, 120

    def kick(s, h, neighbors):
        gx, gphi = jax.grad(lambda a, b: potential.energy(a, b, neighbors), argnums=(0, 1))(
            s.x, s.phi)
        return s._replace(p=s.p - h * gx, pi=s.pi - h * jnp.swapaxes(gphi, -1, -2))

    def step(carry, _):
        s, lst, rebuilds = carry
        s = system.drift(kick(s, 0.5 * dt, lst), dt)
        if lst is not None:
            new = nb.update(spec, lst, s.x, s.phi)
            rebuilds = rebuilds + jnp.any(new.reference_x != lst.reference_x)
            lst = new
        s = kick(s, 0.5 * dt, lst)
        return (s, lst, rebuilds), system.hamiltonian(s)

    run = jax.jit(lambda s, lst: lax.scan(step, (s, lst, 0), None, length=steps))
    (final, last, rebuilds), energies = run(state, nbrs)
    (final_ref, _, _), energies_ref = run(state, None)
    assert int(last.overflow) == 0 and int(rebuilds) >= 1  # the list was rebuilt en route
    e0 = float(system.hamiltonian(state))
    drift = np.max(np.abs(np.asarray(energies) - e0)) / abs(e0)
    drift_ref = np.max(np.abs(np.asarray(energies_ref) - e0)) / abs(e0)
    assert drift < 1e-3  # Strang at dt = 0.01 keeps the energy bounded
    assert drift == pytest.approx(drift_ref, rel=1e-6)
    for a, b in zip(final, final_ref, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-10)


def test_a_neighbour_list_needs_a_cut_off():
    potential = PairPotential.from_expression("exp(-r)", 3)
    x, phi = configuration(np.random.default_rng(0), 3, free_space())
    with pytest.raises(ValueError, match="needs a cut-off"):
        pk.energy_and_gradients_host(potential, free_space(), x, phi, np.zeros(1, int),
                                     np.ones(1, int), 1)


def test_list_energy_alone_equals_the_energy_of_the_gradient_pass():
    """The energy-only host pass (observables, set-up checks) sums the same pairs as the pass
    with gradients, and both equal the all-pairs energy."""
    potential, n = CASES["all-variables-2d"]
    x, phi = configuration(np.random.default_rng(8), n, potential.space)
    _, nbrs = list_for(potential, x, phi)
    alone = float(jax.jit(lambda x, phi: potential.energy(x, phi, nbrs))(x, phi))
    with_gradients = float(_in_loop(potential, x, phi, nbrs)[0])
    assert alone == pytest.approx(with_gradients, rel=1e-14)
    assert alone == pytest.approx(all_pairs(potential, x, phi)[0], rel=1e-12)


def test_built_in_families_reach_the_fused_kernel_as_their_own_formula():
    """Lennard-Jones, Morse and Gaussian give the host kernel their f as a config expression
    (so the fused kernel computes them, as the list-vs-all-pairs cases above check): the
    expression is the family's term at random arguments, r and D alike (to round-off), and
    harmonic-invariants (f of the vector of M_a) stays with the two-call kernel."""
    rng = np.random.default_rng(11)
    s = jnp.asarray(rng.uniform(0.6, 3.0, size=64))
    cut = Cutoff(2.5)
    families = [LennardJones(0.3, 0.45, cutoff=cut), LennardJones(1.7, 1.1, argument="D"),
                Morse(1.3, 2.5, 1.05, cutoff=cut), Morse(0.4, 1.5, 0.9, argument="D"),
                Gaussian(-0.7, 0.5, cutoff=cut), Gaussian(2.5, 1.3, argument="D")]
    for family in families:
        assert pk.fused_on_host(family, 3) == (family.cutoff is not None)  # no cut-off: no list
        expression = family.expression
        assert set(expression.used) == {family.argument}
        np.testing.assert_allclose(expression(**{family.argument: s}),
                                   family.term({family.argument: s}), rtol=1e-13, atol=1e-300)
    assert not pk.fused_on_host(HarmonicInvariants(0.8, "M", cutoff=Cutoff(1.5)), 3)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_host_inverse_and_determinant_are_those_of_linalg(n):
    """The fused host kernel computes B = phi^-1 and det phi per body itself (``_inverse_det``,
    the elimination of ``_linalg.inv`` and ``det`` with its pivoting): equal to them to a few
    cond(phi) eps, for random matrices and for permutations and near-singular ones, where
    the pivoting decides (n = 1 exactly)."""
    from affinebody import _host, _linalg

    rng = np.random.default_rng(n)  # Numba is a dependency: compiled on any backend
    phi = rng.normal(size=(300, n, n))
    phi[:6] = np.eye(n)[::-1] if n > 1 else -1.0
    phi[6:12] = np.eye(n) + 1e-9 * rng.normal(size=(6, n, n))
    phi[12:18, 0] = phi[12:18, -1] + 1e-7 * rng.normal(size=(6, n))  # nearly equal rows
    kernels = _host.specialized("pair", N=n)
    binv, det = np.empty_like(phi), np.empty(len(phi))
    kernels._inverse_det(0, len(phi), phi, binv, det)
    expected_inv, expected_det = np.asarray(_linalg.inv(phi)), np.asarray(_linalg.det(phi))
    cond = np.linalg.cond(phi)
    eps = np.finfo(float).eps
    assert np.all(np.abs(binv - expected_inv).max(axis=(1, 2))
                  <= 16 * eps * cond * np.abs(expected_inv).max(axis=(1, 2)))
    assert np.all(np.abs(det - expected_det) <= 16 * eps * cond * np.abs(expected_det))
    # and they are phi^-1 and det phi: B phi = Id to cond eps, det against NumPy's LU
    assert np.all(np.abs(binv @ phi - np.eye(n)).max(axis=(1, 2)) <= 16 * eps * cond)
    np.testing.assert_allclose(det, np.linalg.det(phi), rtol=1e-6)
    if n == 1:
        assert np.array_equal(binv, expected_inv) and np.array_equal(det, expected_det)
    # a singular phi gives what _linalg gives (inf or nan), not an exception in a callback
    singular = np.zeros((2, n, n))
    singular[1] = np.eye(n)
    singular[1, :, 0] = 0.0
    binv, det = np.empty_like(singular), np.empty(2)
    kernels._inverse_det(0, 2, singular, binv, det)
    assert not np.isfinite(binv).any()
    assert np.array_equal(binv, np.asarray(_linalg.inv(singular)), equal_nan=True)
    assert np.array_equal(det, np.asarray(_linalg.det(singular)), equal_nan=True)
