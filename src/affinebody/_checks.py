"""Input validation shared by every module: float64, shapes, invertibility, positivity.

The library never flips JAX's global x64 flag on import; it refuses to compute in float32
instead (:func:`enable_x64` is for the command line and the workers it starts).
Checks that need *values* (singular phi, positive-definite J) run only on concrete arrays:
inside ``jax.jit`` the arguments are tracers and these checks are skipped, so validate
eagerly once (as the config layer does) and then run the compiled code.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg

X64_FIX = (
    "affinebody computes in float64 only: call "
    "jax.config.update('jax_enable_x64', True) (or set JAX_ENABLE_X64=1) before using it"
)

#: The reciprocal condition number sigma_min / sigma_max below which phi counts as singular:
#: what float64 can resolve. A relative perturbation of size eps (one rounding) cannot make a
#: matrix above it singular, and the pivoted determinant (``affinebody._linalg``), accurate to
#: a few cond * eps, has the right sign, hence membership in GL+ is certain. Sheared states that
#: isochoric motion reaches (det phi = 1, cond 1e8 and more) are physical and pass.
SINGULAR_RTOL = 64 * float(np.finfo(np.float64).eps)


def enable_x64() -> None:
    """Switch JAX to float64 for this process: what the command line and the workers do for
    themselves (importing affinebody never does it; computing in float32 is refused)."""
    jax.config.update("jax_enable_x64", True)


def require_x64() -> None:
    """Raise a one-line ValueError unless JAX's float64 mode is enabled."""
    if not jax.config.read("jax_enable_x64"):
        raise ValueError(X64_FIX)


def is_concrete(a) -> bool:
    """True when ``a`` holds values (not a tracer inside jit/vmap/grad)."""
    return not isinstance(a, jax.core.Tracer)


def as_float64(a, name: str = "array") -> jax.Array:
    """``a`` as a float64 JAX array; refuses float32/float16 input and x64-disabled JAX."""
    require_x64()
    dtype = getattr(a, "dtype", None)
    if dtype is not None and jnp.issubdtype(dtype, jnp.floating) and jnp.finfo(dtype).bits < 64:
        raise ValueError(
            f"{name} has dtype {dtype}: affinebody computes in float64 only "
            f"(convert with .astype('float64'))"
        )
    if dtype is not None and jnp.issubdtype(dtype, jnp.complexfloating):
        raise ValueError(f"{name} must be real (got dtype {dtype})")
    return jnp.asarray(a, dtype=jnp.float64)


def as_matrix(a, name: str = "phi", n: int | None = None) -> jax.Array:
    """``a`` as a float64 array of shape [..., n, n]; ValueError naming ``name`` otherwise."""
    a = as_float64(a, name)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"{name} must have shape [..., n, n] (got {tuple(a.shape)})")
    if n is not None and a.shape[-1] != n:
        raise ValueError(f"{name} must be {n}x{n} (got {a.shape[-2]}x{a.shape[-1]})")
    return a


def as_vector(a, name: str = "x", n: int | None = None) -> jax.Array:
    """``a`` as a float64 array of shape [..., n]; ValueError naming ``name`` otherwise."""
    a = as_float64(a, name)
    if a.ndim < 1:
        raise ValueError(f"{name} must have shape [..., n] (got a scalar)")
    if n is not None and a.shape[-1] != n:
        raise ValueError(f"{name} must have last dimension {n} (got shape {tuple(a.shape)})")
    return a


def same_n(matrix: jax.Array, other: jax.Array, names: tuple[str, str]) -> None:
    """Check that ``other`` ([..., n] or [..., n, n]) has the ``n`` of ``matrix``."""
    if other.shape[-1] != matrix.shape[-1]:
        raise ValueError(
            f"{names[1]} has dimension {other.shape[-1]} but {names[0]} is "
            f"{matrix.shape[-1]}x{matrix.shape[-1]}"
        )


def reciprocal_condition(phi):
    """sigma_min / sigma_max [...] of phi [..., n, n] (0 for singular or zero matrices), from the
    singular values; NumPy arrays stay in NumPy, JAX arrays (traceable) in JAX."""
    xp = np if isinstance(phi, np.ndarray) else jnp
    finite = xp.all(xp.isfinite(phi), axis=(-2, -1))
    sigma = xp.linalg.svd(xp.where(finite[..., None, None], phi, 0.0), compute_uv=False)
    top = sigma[..., 0]
    return xp.where(finite & (top > 0), sigma[..., -1] / xp.where(top > 0, top, 1.0), 0.0)


#: A lower bound of sigma_min / sigma_max above which :func:`is_invertible` needs no singular
#: values: far above SINGULAR_RTOL, so that the rounding error of the bound (the pivoted
#: determinant's, relative cond * eps at most) cannot carry a matrix across SINGULAR_RTOL.
SCREEN_RTOL = 1e-8


def is_invertible(phi):
    """Boolean [...]: phi is invertible as far as float64 resolves (:data:`SINGULAR_RTOL`).

    JAX arrays: first the bound |det phi| / |phi|_F^n <= sigma_min / sigma_max (|det phi| is
    the product of the singular values, at most sigma_min sigma_max^(n-1), and sigma_max <=
    |phi|_F), with the pivoted determinant of ``affinebody._linalg``. Only when some matrix of
    the batch is not clearly invertible by it (bound <= :data:`SCREEN_RTOL`: a strongly sheared
    or nearly singular body, or one not finite) are the singular values computed, for the
    whole batch, and decide as before. A batch of clearly invertible bodies thus costs no SVD
    (README, "Benchmarks": the set-up's state checks at 10^6 bodies 1.0 s against 3.2 s).
    Under ``vmap`` both branches run (a select); the result is the same.
    """
    if isinstance(phi, np.ndarray):
        return reciprocal_condition(phi) > SINGULAR_RTOL
    phi = jnp.asarray(phi)
    scale = jnp.sum(phi**2, axis=(-2, -1)) ** (0.5 * phi.shape[-1])
    clearly = jnp.abs(linalg.det(phi)) > SCREEN_RTOL * scale  # False where not finite
    finite = jnp.all(jnp.isfinite(phi), axis=(-2, -1))
    return jax.lax.cond(jnp.all(clearly | ~finite), lambda: clearly,
                        lambda: reciprocal_condition(phi) > SINGULAR_RTOL)


def check_invertible(phi: jax.Array, name: str = "phi") -> None:
    """ValueError if any concrete matrix in the batch is (numerically) singular: its condition
    number is beyond what float64 resolves (:func:`is_invertible`)."""
    if not is_concrete(phi):
        return
    a = np.asarray(phi)
    with np.errstate(all="ignore"):
        det = np.abs(np.linalg.det(a))
    bad = ~np.asarray(is_invertible(a))
    if np.any(bad):
        where = tuple(int(i) for i in np.argwhere(bad)[0]) if np.ndim(bad) else ()
        at = f" at batch index {where}" if np.ndim(bad) else ""
        raise ValueError(
            f"{name} is singular or not finite{at} (det {name} = {float(det[where]):.3g}): "
            f"an internal configuration must be an invertible matrix"
        )


def check_symmetric_positive_definite(a: jax.Array, name: str = "J") -> None:
    """ValueError unless every concrete matrix in ``a`` is symmetric positive definite."""
    if not is_concrete(a):
        return
    m = np.asarray(a)
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} must be finite")
    scale = np.maximum(np.max(np.abs(m), axis=(-2, -1)), 1e-300)  # per matrix of a batch
    if np.any(np.max(np.abs(m - np.swapaxes(m, -1, -2)), axis=(-2, -1)) > 1e-12 * scale):
        raise ValueError(f"{name} must be symmetric (got {name} != {name}^T)")
    eig = np.linalg.eigvalsh(m)
    if np.any(eig[..., 0] <= 1e-14 * scale):
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {np.min(eig):.3g})"
        )


def sym(a: jax.Array) -> jax.Array:
    """Symmetric part (a + a^T)/2 over the last two axes."""
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


def skew(a: jax.Array) -> jax.Array:
    """Skew-symmetric part (a - a^T)/2 over the last two axes."""
    return 0.5 * (a - jnp.swapaxes(a, -1, -2))


def transpose(a: jax.Array) -> jax.Array:
    """Matrix transpose over the last two axes (batched)."""
    return jnp.swapaxes(a, -1, -2)


def trace(a: jax.Array) -> jax.Array:
    """Matrix trace over the last two axes (batched)."""
    return jnp.trace(a, axis1=-2, axis2=-1)


def eye_like(a: jax.Array) -> jax.Array:
    """Identity with the trailing n x n shape of ``a`` (broadcasts over the batch)."""
    return jnp.eye(a.shape[-1], dtype=a.dtype)
