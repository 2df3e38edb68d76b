"""The fused host pair kernel of config-expression pair terms (f and its partial derivatives
compiled with the geometry and the chain rule, affinebody._host_kernels.pair_expression):

- the generated partial derivatives equal jax.grad of the expression at random points, for
  an expression that calls every whitelisted function, and at the kinks of abs, min and max
  (JAX's conventions);
- energies and generalised forces over a neighbour list, and the energy and virial of the
  barostat's pass, equal the host path with XLA's f between two callbacks (the same f as a
  Python function; the virial also the JAX kernel's), for n = 2 and 3, f in r, D, det,
  K_a, M_a (asymmetric: both orders, M'_a and 1/det), cut-offs on r (periodic box) and on D
  (free space), and the all-pairs autodiff with the cut-off on D.

test_pair_kernels runs its expression terms (cut-offs on r, n = 2 and 3, every pair variable)
through this kernel against the all-pairs autodiff, and checks that its fixed parts give the
same bits on one thread or two."""

import math
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numba
import numpy as np
import pytest

from affinebody import _host
from affinebody import pair_kernels as pk
from affinebody.expressions import FUNCTIONS, compile_expression, derivative_source
from affinebody.potentials import Cutoff, PairPotential
from affinebody.space import free_space
from test_pair_kernels import BOX3, all_pairs, assert_same, configuration, list_for

#: Calls every whitelisted function (aliases included) on arguments inside its domain for
#: any pair: r, D > 0, det > 0 (phi with det > 0), K_a, M_a any real.
EVERY_FUNCTION = (
    "exp(-r) + 0.3*log(det) + log1p(D**2) + expm1(-0.5*D) + sqrt(1 + M1**2) + cbrt(M1 - 0.3)"
    " + 0.1*square(K1) + sin(M2) + cos(K1) + tan(0.4*tanh(M1)) + arcsin(0.5*tanh(K1))"
    " + asin(0.4*tanh(M2)) + arccos(0.5*tanh(D)) + acos(0.3*tanh(M1)) + arctan(M1)"
    " + atan(K2) + arctan2(r, D) + atan2(M1, 1 + D) + sinh(0.2*r) + cosh(0.3*D) + tanh(M2)"
    " + arcsinh(K1) + asinh(M1) + arccosh(1.5 + r) + acosh(1.2 + D**2)"
    " + arctanh(0.5*tanh(M1)) + atanh(0.4*tanh(K2)) + erf(M1) + erfc(D)"
    " + abs(M1 - 3) + min(r, D) + minimum(M1, K1) + max(D, 0.7) + maximum(M2, 1)"
    " + pi/e*exp(-(D - r)**2)*det**0.5"
)

CASES = {  # (f, n, cut-off, space)
    "r-cut-periodic-3d": ("exp(-D**2)*(M2 - 2)**2 + 0.3*log(det) + 0.02*K2*tanh(r)"
                          " + 0.1*sqrt(1 + M1**2) + abs(M1 - 3)*erf(K1) + max(r, D)", 3,
                          Cutoff(1.6, 1.2), BOX3),
    "D-cut-free-2d": ("exp(-D**2)*(M2 - 2)**2 + 0.3*det + abs(M1 - 2)*K2 + r*exp(-r)"
                      " + max(M1, K1)", 2, Cutoff(1.4, 1.0, variable="D"), free_space()),
}


def potentials(case):
    """The term as a config expression (fused kernel) and the same f as a Python function
    (XLA's f between the two callbacks)."""
    text, n, cutoff, space = CASES[case]
    fused = PairPotential.from_expression(text, n, cutoff=cutoff,
                                          box=space if space.periodic else None)
    expression = fused.expression
    plain = PairPotential(lambda **values: expression(**values), expression.used, cutoff,
                          fused.box)
    return fused, plain, n


def test_generated_partials_equal_jax_grad_at_random_points():
    """f and its partials as the fused kernel's module compiles them (``_f``), for an f that
    calls every whitelisted function."""
    term = PairPotential.from_expression(EVERY_FUNCTION, 3, cutoff=Cutoff(1.6), box=BOX3)
    f = _host.specialized("pair", extra=pk._fused_source(term, 3), N=3)._f
    expression = term.expression
    assert all(f"{name}(" in EVERY_FUNCTION for name in FUNCTIONS)  # every function called
    names = expression.used
    assert set(names) == {"r", "D", "det", "K1", "K2", "M1", "M2"}
    rng = np.random.default_rng(1)
    points = {name: rng.uniform(0.3, 2.0, 12) if name in ("r", "D", "det")
              else rng.uniform(-2.5, 2.5, 12) for name in names}
    value_and_grad = jax.jit(jax.vmap(jax.value_and_grad(
        lambda v: expression(**v))))
    values, grads = value_and_grad({k: jnp.asarray(v) for k, v in points.items()})
    for p in range(12):
        value, *partials = f(*(float(points[name][p]) for name in names))
        assert value == pytest.approx(float(values[p]), rel=1e-13, abs=1e-13)
        for name, partial in zip(names, partials, strict=True):
            assert partial == pytest.approx(float(grads[name][p]), rel=1e-12, abs=1e-12)


def test_generated_partials_follow_jax_at_the_kinks():
    # d|x|/dx = 1 at 0; min and max give half the derivative to each of two equal arguments
    text = "abs(r - 1) + 2*min(D, det) + 3*max(D, det) + r**D"
    expression = compile_expression(text, ("r", "D", "det"))
    namespace = {"np": np, "math": math}
    exec(derivative_source(expression, "_f"), namespace)
    f = numba.njit(error_model="numpy")(namespace["_f"])
    for r, d, det in [(1.0, 0.7, 0.7), (1.0, 1.3, 1.3), (0.5, 2.0, 1.0)]:
        reference = jax.grad(lambda a, b, c: expression(r=a, D=b, det=c), argnums=(0, 1, 2))(
            r, d, det)
        value, *partials = f(r, d, det)
        assert value == pytest.approx(float(expression(r=r, D=d, det=det)), rel=1e-14)
        np.testing.assert_allclose(partials, np.asarray(reference), rtol=1e-14)


@pytest.mark.parametrize("case", list(CASES))
def test_fused_kernel_equals_the_two_callback_path(case):
    fused, plain, n = potentials(case)
    assert pk._fused_source(fused, n) is not None and pk._fused_source(plain, n) is None
    x, phi = configuration(np.random.default_rng(sum(map(ord, case))), n, fused.space)
    _, nbrs = list_for(fused, x, phi)
    args = (x, phi, nbrs.i, nbrs.j, nbrs.count)
    result = pk.energy_and_gradients_host(fused, fused.space, *args)
    reference = pk.energy_and_gradients_host(plain, plain.space, *args)
    assert_same(result, tuple(np.asarray(a) for a in reference))
    # the energy alone (observables): the fused kernel without the chain rule
    alone = jax.jit(lambda a, b: fused.energy(a, b, nbrs))(x, phi)
    assert float(alone) == pytest.approx(float(reference[0]), rel=1e-12)
    # the barostat's pass, energy and virial: the fused virial kernel, the two-callback path
    # and the JAX kernel (chunked: no host kernel)
    virial = jax.jit(pk.pair_virial, static_argnums=(0, 1), static_argnames=("chunk", "energy"))
    e, w = virial(fused, fused.space, *args, energy=True)
    e_plain, w_plain = virial(plain, plain.space, *args, energy=True)
    e_jax, w_jax = virial(fused, fused.space, *args, chunk=64, energy=True)
    assert np.max(np.abs(np.asarray(w))) > 1e-2  # pairs in range: a non-trivial virial
    for energy, other in ((e_plain, w_plain), (e_jax, w_jax)):
        assert float(e) == pytest.approx(float(energy), rel=1e-12)
        np.testing.assert_allclose(np.asarray(w), np.asarray(other), rtol=1e-11, atol=1e-12)


def test_fused_kernel_with_a_cut_off_on_D_equals_all_pairs():
    """(test_pair_kernels compares expression terms cut on r, through this kernel, with the
    all-pairs autodiff in n = 2 and 3.)"""
    fused, _, n = potentials("D-cut-free-2d")
    x, phi = configuration(np.random.default_rng(5), n, fused.space)
    _, nbrs = list_for(fused, x, phi)
    assert_same(pk.energy_and_gradients_host(fused, fused.space, x, phi, nbrs.i, nbrs.j,
                                             nbrs.count), all_pairs(fused, x, phi))


#: A child process's energies, forces and virials of a 2D expression term (the pair term of a
#: run with run.pressure; with some other expressions the two copies below had agreed) at 40
#: random states, of 4 bodies over all pairs and of 40 over a list, saved to argv[1], and
#: whether its kernel was compiled there or loaded from the cache.
_KERNEL_BITS = textwrap.dedent("""
    import sys
    import jax
    import numpy as np
    jax.config.update("jax_enable_x64", True)
    from affinebody import neighbors as nb
    from affinebody import pair_kernels as pk
    from affinebody.potentials import Cutoff, PairPotential
    from affinebody.space import orthorhombic
    box = orthorhombic((4.0, 4.2))
    term = PairPotential.from_expression("exp(-D**2) + 0.5*exp(-r**2)", 2, cutoff=Cutoff(1.0),
                                         box=box)
    virial = jax.jit(pk.pair_virial, static_argnums=(0, 1), static_argnames=("energy",))
    rng = np.random.default_rng(0)
    out = []
    for bodies in [4] * 20 + [40] * 20:
        x = rng.uniform(0.0, 4.0, size=(bodies, 2))
        phi = np.eye(2) + 0.25 * rng.normal(size=(bodies, 2, 2))
        phi[np.linalg.det(phi) < 0, 0] *= -1
        if bodies == 4:
            i, j = (np.asarray(a, np.int32) for a in np.triu_indices(bodies, 1))
            pairs = (x, phi, i, j, len(i))
        else:
            lst = nb.allocate(box, x, phi, 1.0, "r", 0.3, capacity=780, cell_capacity=40)[1]
            pairs = (x, phi, lst.i, lst.j, lst.count)
        out += [np.ravel(a) for a in virial(term, box, *pairs, energy=True)]
        out += [np.ravel(a) for a in pk.energy_and_gradients_host(term, box, *pairs)]
    np.save(sys.argv[1], np.concatenate(out))
    stats = pk._fused_kernel(2, pk._fused_source(term, 2)).fused_thread.stats
    print("compiled" if stats.cache_misses else "loaded" if stats.cache_hits else "?")
""")


@pytest.mark.skipif(not _host.in_use(), reason="the host kernels run on a CPU with Numba")
def test_the_process_that_compiles_the_kernel_gives_the_bits_of_those_that_load_it(tmp_path):
    """The fused kernel's machine code is the same in the process whose Numba compiled it
    and in every later one, which loads it from the cache. Its f and pair loop (FMA
    contraction allowed) had been functions of their own that the kernel called: the process
    that compiled them called their own copies, later processes the copies linked into the
    kernel's module, which LLVM had contracted differently: a run's pressure (and, over a
    neighbour list, its forces) an ulp apart depending on whether it was the first run of the
    expression on the machine (frame 34 of 41 of a 400-step run, against a 600-step one)."""
    env = {**os.environ, "AFFINEBODY_CACHE_DIR": str(tmp_path / "kernels")}
    results = []
    for k, how in enumerate(("compiled", "loaded")):
        out = tmp_path / f"{k}.npy"
        done = subprocess.run([sys.executable, "-c", _KERNEL_BITS, str(out)], env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == [how]
        results.append(np.load(out))
    assert results[0].size == 40 * (1 + 2 * 2) + 20 * (1 + 4 * 6) + 20 * (1 + 40 * 6)
    np.testing.assert_array_equal(results[0], results[1])
