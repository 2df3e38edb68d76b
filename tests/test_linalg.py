"""Closed-form det / inv / solve / slogdet of affinebody._linalg (n <= 3): agreement with
LAPACK (jnp.linalg) on well-conditioned batches, forward error of order cond * eps against
exact rational arithmetic on ill-conditioned ones, autodiff against the closed-form derivatives
(Jacobi's formula), jit/vmap, and — the point of the module — no LAPACK custom call in the
compiled code, neither for a large batch nor in a compiled integrator step of an all-pairs
system (two concurrent batched LAPACK kernels deadlock jaxlib 0.10 on a two-thread pool)."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from affinebody import _linalg as la
from affinebody import kinetic as kin
from affinebody.integrators import get_integrator
from affinebody.potentials import Dilatation, PairPotential, total_potential
from affinebody.state import State
from affinebody.system import HamiltonianSystem

EPS = np.finfo(np.float64).eps
BATCH = 64
LAPACK_MARKERS = ("lapack", "getrf", "trsm", "getrs", "gesv")


def rel_each(x, ref) -> np.ndarray:
    """Relative Frobenius error of each matrix (vector) of a batch."""
    x, ref = np.asarray(x), np.asarray(ref)
    return (np.linalg.norm((x - ref).reshape(len(ref), -1), axis=-1)
            / np.linalg.norm(ref.reshape(len(ref), -1), axis=-1))


def rel(x, ref) -> float:
    return float(np.max(rel_each(x, ref)))


def orthogonal(rng, batch, n):
    q, r = np.linalg.qr(rng.normal(size=(batch, n, n)))
    return q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]


def with_singular_values(rng, batch, s):
    """U diag(s) V^T with Haar-random U, V and a random overall sign: cond = max s / min s."""
    n = len(s)
    a = orthogonal(rng, batch, n) @ (np.asarray(s)[:, None] * orthogonal(rng, batch, n))
    return a * rng.choice([-1.0, 1.0], size=(batch, 1, 1))


def exact_solve(a, b):
    """x = a^-1 b and det a in exact rational arithmetic (Gauss-Jordan on the float entries)."""
    n, k = b.shape
    m = [[Fraction(float(v)) for v in row] + [Fraction(float(v)) for v in brow]
         for row, brow in zip(a, b, strict=True)]
    det = Fraction(1)
    for c in range(n):
        p = next(r for r in range(c, n) if m[r][c] != 0)
        if p != c:
            m[c], m[p], det = m[p], m[c], -det
        det *= m[c][c]
        pivot = m[c][c]
        m[c] = [v / pivot for v in m[c]]
        for r in range(n):
            if r != c and m[r][c] != 0:
                f = m[r][c]
                m[r] = [v - f * w for v, w in zip(m[r], m[c], strict=True)]
    x = np.array([[float(v) for v in row[n:]] for row in m])
    return x, float(det)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_well_conditioned_batches_agree_with_lapack(n):
    rng = np.random.default_rng(n)
    a = with_singular_values(rng, BATCH, np.linspace(2.0, 0.5, n))
    b = rng.normal(size=(BATCH, n, 2))
    v = rng.normal(size=n)
    assert rel(la.det(a), jnp.linalg.det(a)) < 1e-12
    assert rel(la.inv(a), jnp.linalg.inv(a)) < 1e-12
    assert rel(la.solve(a, b), jnp.linalg.solve(a, b)) < 1e-12
    assert rel(la.solve(a, v), jnp.linalg.solve(a, v)) < 1e-12
    sign, logabs = la.slogdet(a)
    ref_sign, ref_logabs = jnp.linalg.slogdet(a)
    np.testing.assert_array_equal(sign, ref_sign)
    np.testing.assert_allclose(logabs, ref_logabs, rtol=0, atol=1e-12)
    # the defining identities
    eye = np.broadcast_to(np.eye(n), a.shape)
    np.testing.assert_allclose(np.asarray(la.inv(a)) @ a, eye, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a @ np.asarray(la.solve(a, b)), b, rtol=0, atol=1e-13)


@pytest.mark.parametrize("s", [(1.0, 1e-6), (1.0, 1.0, 1e-6), (1.0, 1e-3, 1e-6),
                               (1.0, 1e-6, 1e-6), (1.0, 1e-8), (1.0, 1e-8, 1e-8),
                               (1e4, 1e-2, 1e-2)])
def test_forward_error_on_ill_conditioned_matrices(s):
    """cond = 1e6 and 1e8, against exact rational arithmetic. inv and solve are pivoted: a few
    cond * eps, as LAPACK's pivoted LU (checked alongside), also for 3x3 with two small singular
    values (an isochoric shear, det = 1), where the adjugate reached cond^2 * eps; so is the
    determinant (the product of the pivots), where the cofactor formula was as bad."""
    n, cond = len(s), max(s) / min(s)
    rng = np.random.default_rng(len(s) + int(-np.log10(s[1])))
    a = with_singular_values(rng, 24, s)
    b = rng.normal(size=(24, n, 1))
    exact = [exact_solve(m, np.concatenate([np.eye(n), rhs], axis=1))
             for m, rhs in zip(a, b, strict=True)]
    exact_inv = np.array([x[:, :n] for x, _ in exact])
    exact_x = np.array([x[:, n:] for x, _ in exact])
    exact_det = np.array([d for _, d in exact])
    for impl in (la, jnp.linalg):
        assert np.all(rel_each(impl.inv(a), exact_inv) < 10 * cond * EPS)
        assert np.all(rel_each(impl.solve(a, b), exact_x) < 10 * cond * EPS)
    assert np.all(np.abs(np.asarray(la.det(a)) / exact_det - 1) < 10 * cond * EPS)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_gradients_match_jacobi_formula_and_lapack_versions(n):
    rng = np.random.default_rng(20 + n)
    a = jnp.asarray(with_singular_values(rng, 8, np.linspace(1.5, 0.7, n)))
    b = jnp.asarray(rng.normal(size=(8, n, 2)))
    w = jnp.asarray(rng.normal(size=(8, n, n)))
    # Jacobi: d det / d a = det(a) a^-T ;  d log|det| / d a = a^-T
    inv_t = jnp.swapaxes(jnp.linalg.inv(a), -1, -2)
    np.testing.assert_allclose(jax.grad(lambda m: jnp.sum(la.det(m)))(a),
                               jnp.linalg.det(a)[:, None, None] * inv_t, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jax.grad(lambda m: jnp.sum(la.slogdet(m)[1]))(a), inv_t,
                               rtol=1e-12, atol=1e-12)

    def scalar_of_inverse(impl):
        return lambda m: jnp.sum(w * impl.inv(m) @ impl.inv(m))

    def scalar_of_solution(impl):
        return lambda m, rhs: jnp.sum(jnp.sin(impl.solve(m, rhs)))

    np.testing.assert_allclose(jax.grad(scalar_of_inverse(la))(a),
                               jax.grad(scalar_of_inverse(jnp.linalg))(a), rtol=1e-11, atol=1e-12)
    ours = jax.grad(scalar_of_solution(la), argnums=(0, 1))(a, b)
    ref = jax.grad(scalar_of_solution(jnp.linalg), argnums=(0, 1))(a, b)
    for x, y in zip(ours, ref, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-12)
    # second order: the Hessian-vector product of log|det| is -Tr(a^-1 da a^-1 da) per matrix
    da = jnp.asarray(rng.normal(size=a.shape))
    hvp = jax.jvp(jax.grad(lambda m: jnp.sum(la.slogdet(m)[1])), (a,), (da,))[1]
    inv = jnp.linalg.inv(a)
    np.testing.assert_allclose(jnp.sum(hvp * da, axis=(-2, -1)),
                               -jnp.trace(inv @ da @ inv @ da, axis1=-2, axis2=-1),
                               rtol=1e-10, atol=1e-12)


def test_jit_vmap_and_broadcasting():
    rng = np.random.default_rng(30)
    a = with_singular_values(rng, 12, (1.3, 1.0, 0.8)).reshape(3, 4, 3, 3)
    b = rng.normal(size=(4, 3, 5))  # broadcasts against a's leading axes (3, 4)
    direct = la.solve(a, b)
    # compiled code may fuse multiply-adds differently: equal to round-off
    np.testing.assert_allclose(jax.jit(la.solve)(a, b), direct, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(jax.vmap(la.solve, in_axes=(0, None))(a, b), direct,
                               rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(direct, np.linalg.solve(a, b), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(jax.vmap(jax.vmap(la.inv))(a), la.inv(a), rtol=1e-13, atol=1e-15)
    assert la.det(a).shape == (3, 4) and la.inv(a).dtype == jnp.float64


def test_larger_matrices_fall_back_to_lapack_with_the_same_semantics():
    rng = np.random.default_rng(40)
    a = with_singular_values(rng, 6, np.linspace(2.0, 0.5, 5))
    b = rng.normal(size=(6, 5, 2))
    np.testing.assert_allclose(la.solve(a, b), np.linalg.solve(a, b), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(la.inv(a), np.linalg.inv(a), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(la.det(a), np.linalg.det(a), rtol=1e-12)
    # one matrix, many right-hand sides: solved as one system with the batch as columns
    np.testing.assert_allclose(la.solve(a[0], b), np.linalg.solve(a[0], b), rtol=1e-12,
                               atol=1e-13)


def test_bad_shapes_raise_value_error():
    with pytest.raises(ValueError, match="square"):
        la.inv(np.ones((3, 2)))
    with pytest.raises(ValueError, match="b must have shape"):
        la.solve(np.eye(3), np.ones((4, 3)))  # a stack of vectors must be b[..., None]


def lapack_calls(text: str) -> list[str]:
    return [line for line in text.lower().splitlines()
            if ("custom_call" in line or "custom-call" in line)
            and any(marker in line for marker in LAPACK_MARKERS)]


def test_large_batch_compiles_without_lapack_calls():
    """20000 3x3 matrices through det, inv, solve, slogdet and their gradients: the compiled
    module has no LAPACK custom call (the jnp.linalg version of the same function has)."""
    rng = np.random.default_rng(50)
    a = jnp.asarray(np.eye(3) + 0.1 * rng.normal(size=(20000, 3, 3)))
    b = jnp.asarray(rng.normal(size=(20000, 3, 1)))

    def work(impl):
        def f(m, rhs):
            return (jnp.sum(impl.det(m)) + jnp.sum(impl.inv(m) @ impl.solve(m, rhs))
                    + jnp.sum(impl.slogdet(m)[1]))
        return jax.jit(jax.value_and_grad(f, argnums=(0, 1)))

    compiled = work(la).lower(a, b).compile().as_text()
    assert lapack_calls(compiled) == []
    assert lapack_calls(work(jnp.linalg).lower(a, b).compile().as_text())  # the check can fail


def test_integrator_step_of_an_all_pairs_system_has_no_lu_calls():
    """A Strang step of 8 bodies with the demo's affine pair potential (r, D, det and M1 need
    phi^-1, det and psi^-1 phi over all pairs) and a d'Alembert kinetic energy (T of (6)):
    no getrf/trsm in the HLO."""
    demo = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2 + det"
    system = HamiltonianSystem(
        kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.DAlembert(0.3 * jnp.eye(3))),
        total_potential([PairPotential.from_expression(demo, 3), Dilatation(1.0)]))
    rng = np.random.default_rng(60)
    state = State(jnp.asarray(2.0 * rng.normal(size=(8, 3))),
                  jnp.asarray(np.eye(3) + 0.05 * rng.normal(size=(8, 3, 3))),
                  jnp.asarray(rng.normal(size=(8, 3))), jnp.asarray(rng.normal(size=(8, 3, 3))))
    step = jax.jit(lambda s: get_integrator("strang").step(system, s, 0.01))
    assert lapack_calls(step.lower(state).as_text()) == []


@pytest.mark.parametrize("n", [1, 2, 3])
def test_expm_agrees_with_scipy_and_is_a_group_exponential(n):
    """Pade [13/13] scaling and squaring over norms from 1e-8 to ~50 (up to 4 squarings): as
    close to scipy's expm as jax.scipy.linalg.expm is (the same algorithm with LU; exp is
    ill-conditioned for large non-normal X, so neither agrees to eps there), and below 1e-11;
    exp(X) exp(-X) = Id, det exp(X) = exp(tr X), exp of a skew matrix orthogonal; gradients
    equal those through jax.scipy.linalg.expm."""
    import scipy.linalg as sl

    rng = np.random.default_rng(70 + n)
    for scale in (1e-8, 1e-3, 0.5, 3.0, 15.0):
        a = scale * rng.normal(size=(BATCH, n, n))
        ours = np.asarray(la.expm(jnp.asarray(a)))
        ref = np.array([sl.expm(m) for m in a])
        theirs = np.asarray(jax.vmap(jax.scipy.linalg.expm)(jnp.asarray(a)))
        assert rel(ours, ref) <= max(2 * rel(theirs, ref), 4 * EPS) and rel(ours, ref) < 1e-11
        if scale > 1:  # exp(X) exp(-X) and det exp(X) cancel catastrophically for large X
            continue
        back = np.asarray(la.expm(jnp.asarray(-a)))
        size = np.linalg.norm(ours, axis=(-2, -1)) * np.linalg.norm(back, axis=(-2, -1))
        assert np.all(np.linalg.norm(ours @ back - np.eye(n), axis=(-2, -1)) < 1e-13 * size)
        trace = np.trace(a, axis1=-2, axis2=-1)
        assert np.allclose(np.linalg.det(ours), np.exp(trace), rtol=1e-11)
    w = rng.normal(size=(BATCH, n, n))
    q = np.asarray(la.expm(jnp.asarray(w - np.swapaxes(w, -1, -2))))
    assert np.allclose(q @ np.swapaxes(q, -1, -2), np.eye(n), atol=1e-13)
    x = jnp.asarray(rng.normal(size=(n, n)))
    grad_ours = jax.grad(lambda m: jnp.sum(jnp.sin(la.expm(m))))(x)
    grad_jax = jax.grad(lambda m: jnp.sum(jnp.sin(jax.scipy.linalg.expm(m))))(x)
    assert np.allclose(grad_ours, grad_jax, rtol=1e-11, atol=1e-12)


def test_expm_of_a_large_batch_compiles_without_lapack_calls():
    """jax.scipy.linalg.expm solves its Pade system with LAPACK (getrf/trsm); ours does not."""
    x = jnp.zeros((20000, 3, 3))
    assert lapack_calls(jax.jit(la.expm).lower(x).compile().as_text()) == []
    assert lapack_calls(jax.jit(jax.scipy.linalg.expm).lower(x).compile().as_text())


def test_fused_products_of_the_gpu_path_are_the_same_matrices(monkeypatch):
    """The GPU form of tiny products (elementwise, ``fused_products``) computes the same
    matrices as ``@``: products, the exponential (entry by entry, its squarings a loop: also
    its gradient) and an exact af-is drift agree to round-off with the CPU form, exercised
    here on the CPU by forcing the switch. The GPU form runs on arrays with one more leading
    axis: new shapes, so that the jitted expm is traced anew with the switch on."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(2, 40, 3, 3))
    phi = np.eye(3) + 0.2 * rng.normal(size=(40, 3, 3))
    state = State(jnp.zeros((40, 3)), jnp.asarray(phi), jnp.zeros((40, 3)),
                  jnp.asarray(rng.normal(size=(40, 3, 3))))
    model = kin.AffineIsotropic(1.0, 0.2, 0.1)
    # 3 a: norms up to ~30, so that some matrices take squarings and some none
    weights = jnp.asarray(rng.normal(size=(40, 3, 3)))

    def gradient(expm, x):
        return jax.grad(lambda y: jnp.sum(weights * expm(y)))(x)

    plain = (la.matmul(a, b), la.expm(3.0 * a), model.flow(state, 0.3),
             gradient(la.expm, 3.0 * a))
    monkeypatch.setattr(la, "fused_products", lambda: True)
    state1 = jax.tree.map(lambda v: v[None], state)
    fused = (la.matmul(a, b), la.expm(3.0 * a[None])[0],
             jax.tree.map(lambda v: v[0], model.flow(state1, 0.3)),
             gradient(lambda y: la.expm(y[None])[0], 3.0 * a))
    np.testing.assert_allclose(fused[0], np.asarray(a) @ np.asarray(b), rtol=0, atol=1e-14)
    scale = np.max(np.abs(plain[1]))
    assert np.max(np.abs(plain[1])) > 100  # squarings were taken
    np.testing.assert_allclose(fused[1], plain[1], rtol=1e-13, atol=1e-13 * scale)
    np.testing.assert_allclose(fused[1], scipy.linalg.expm(3.0 * a), rtol=1e-12,
                               atol=1e-13 * scale)
    for mine, theirs in zip(fused[2], plain[2], strict=True):
        np.testing.assert_allclose(mine, theirs, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(fused[3], plain[3], rtol=1e-11,
                               atol=1e-12 * np.max(np.abs(plain[3])))
