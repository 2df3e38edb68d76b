"""Input validation (affinebody._checks) and the batching/tracing contract of the foundation.

Every public function takes float64 arrays with leading batch axes [..., n, n], broadcasts
them, refuses float32 and x64-disabled JAX, names the offending argument in its ValueError,
and is jit-traceable and vmap-able.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import _checks, actions, deformation, groups, momenta, mutual, polar, velocities
from affinebody.state import State
from strategies import assert_close, element_from_log_singular_values

RNG = np.random.default_rng(20240611)
N = 3
BATCH = (2, 3)


def _gl(batch=BATCH, n=N, group="GL"):
    log_s = RNG.uniform(-1.0, 1.0, size=tuple(batch) + (n,))
    return element_from_log_singular_values(group, log_s, RNG)


# ------------------------------------------------------------------------------- float64


def test_float32_and_float16_are_refused_naming_float64():
    for dtype in (np.float32, np.float16):
        with pytest.raises(ValueError, match="phi has dtype .*float64"):
            _checks.as_matrix(np.eye(2, dtype=dtype), "phi")
    with pytest.raises(ValueError, match="phi has dtype float32.*float64"):
        deformation.green_tensor(jnp.eye(2, dtype=jnp.float32))
    with pytest.raises(ValueError, match="float64"):
        polar.two_polar(np.eye(3, dtype=np.float32))
    with pytest.raises(ValueError, match="psi has dtype float32"):
        mutual.mutual_gamma(np.eye(2, dtype=np.float32), np.eye(2))
    with pytest.raises(ValueError, match="must be real"):
        _checks.as_float64(np.eye(2, dtype=np.complex128), "phi")


def test_integer_and_list_input_become_float64():
    assert _checks.as_matrix([[1, 2], [3, 4]]).dtype == jnp.float64
    assert deformation.green_tensor(np.eye(2, dtype=np.int64)).dtype == jnp.float64


def test_x64_disabled_is_refused():
    with jax.enable_x64(False):
        assert not jax.config.read("jax_enable_x64")
        with pytest.raises(ValueError, match="float64.*jax_enable_x64"):
            _checks.require_x64()
        with pytest.raises(ValueError, match="float64"):
            deformation.green_tensor(np.eye(2))
        with pytest.raises(ValueError, match="float64"):
            polar.polar(np.eye(2))
    assert jax.config.read("jax_enable_x64")  # the context restored the session's setting


def test_importing_the_library_leaves_x64_off():
    code = (
        "import jax, numpy as np\n"
        "import affinebody._checks, affinebody.state, affinebody.groups, affinebody.polar\n"
        "import affinebody.deformation, affinebody.mutual, affinebody.velocities\n"
        "import affinebody.momenta, affinebody.actions, affinebody.inertia\n"
        "assert not jax.config.read('jax_enable_x64')\n"
        "try:\n"
        "    affinebody.deformation.green_tensor(np.eye(2))\n"
        "except ValueError as err:\n"
        "    print('refused:', err)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "refused:" in out.stdout and "float64" in out.stdout


# ------------------------------------------------------------------------------- shapes


def test_wrong_shapes_name_the_argument():
    with pytest.raises(ValueError, match=r"phi must have shape \[\.\.\., n, n\] \(got \(2, 3\)\)"):
        _checks.as_matrix(np.ones((2, 3)), "phi")
    with pytest.raises(ValueError, match=r"J must have shape \[\.\.\., n, n\]"):
        _checks.as_matrix(np.ones(3), "J")
    with pytest.raises(ValueError, match="phi must be 3x3"):
        _checks.as_matrix(np.eye(2), "phi", n=3)
    with pytest.raises(ValueError, match="x must have shape .*scalar"):
        _checks.as_vector(1.0, "x")
    with pytest.raises(ValueError, match="q must have last dimension 3"):
        polar.from_two_polar(np.eye(3), np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="v has dimension 3 but phi is 2x2"):
        velocities.comoving_velocity(np.eye(2), np.ones(3))
    with pytest.raises(ValueError, match="xi has dimension 2 but phi is 3x3"):
        velocities.spatial_affine_velocity(np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="pi has dimension 2"):
        momenta.affine_spin(np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="p has dimension 2"):
        momenta.comoving_momentum(np.eye(3), np.ones(2))
    with pytest.raises(ValueError, match="Sigma_hat must have shape"):
        momenta.vorticity(np.ones(4))


# ---------------------------------------------------------------- singular and non-SPD


def test_singular_or_non_finite_phi_is_refused():
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    with pytest.raises(ValueError, match="phi is singular"):
        _checks.check_invertible(singular)
    with pytest.raises(ValueError, match="phi is singular"):
        _checks.check_invertible(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not finite"):
        _checks.check_invertible(np.array([[1.0, np.nan], [0.0, 1.0]]))
    batch = np.stack([np.eye(2), singular, np.eye(2)])
    # the determinant said is that of the matrix at fault (it was the batch's first one's)
    at_fault = r"phi is singular or not finite at batch index \(1,\) \(det phi = 0\)"
    with pytest.raises(ValueError, match=at_fault):
        velocities.comoving_affine_velocity(batch, batch)
    with pytest.raises(ValueError, match="A is singular"):
        actions.transform_state(
            State(np.zeros(2), np.eye(2), np.zeros(2), np.eye(2)), A=singular
        )
    # nearly singular but invertible in float64 is accepted
    _checks.check_invertible(np.array([[1.0, 1.0], [1.0, 1.0 + 1e-9]]))


@pytest.mark.parametrize("scale", [1e-30, 1e30, 1e-110, 1e110])
def test_invertibility_check_is_scale_free(scale):
    """|det phi| / prod |phi e_j| is invariant under phi -> s phi; a rotation scaled by any
    representable s is invertible. (Fails at 1e+-110 while det underflows/overflows: see the
    report; computing the ratio as det of the column-normalised phi avoids that.)"""
    rotation = np.asarray(groups.expm(np.array([[0.0, 1, 2], [-1, 0, 3], [-2, -3, 0]]) / 4))
    _checks.check_invertible(scale * rotation)
    assert bool(groups.is_member(scale * rotation, "GL"))


def test_symmetric_positive_definite_check_names_the_problem():
    _checks.check_symmetric_positive_definite(np.diag([1.0, 2.0]), "J")
    with pytest.raises(ValueError, match="J must be symmetric"):
        _checks.check_symmetric_positive_definite(np.array([[1.0, 1.0], [0.0, 1.0]]), "J")
    with pytest.raises(ValueError, match="J must be positive definite"):
        _checks.check_symmetric_positive_definite(np.array([[1.0, 2.0], [2.0, 1.0]]), "J")
    with pytest.raises(ValueError, match="J must be finite"):
        _checks.check_symmetric_positive_definite(np.array([[1.0, np.inf], [np.inf, 1.0]]), "J")
    with pytest.raises(ValueError, match="H must be positive definite"):
        _checks.check_symmetric_positive_definite(np.stack([np.eye(2), -np.eye(2)]), "H")


def test_matrix_helpers():
    a = RNG.standard_normal(BATCH + (N, N))
    sym, skew = np.asarray(_checks.sym(a)), np.asarray(_checks.skew(a))
    assert_close(sym + skew, a, 1e-15)
    assert_close(sym, np.swapaxes(sym, -1, -2), 0.0)
    assert_close(skew, -np.swapaxes(skew, -1, -2), 0.0)
    assert_close(_checks.transpose(a), np.swapaxes(a, -1, -2), 0.0)
    assert_close(_checks.trace(a), np.trace(a, axis1=-2, axis2=-1), 1e-15)
    assert_close(_checks.eye_like(a) @ a, a, 0.0)
    assert _checks.is_concrete(jnp.ones(2))
    assert jax.jit(lambda x: jnp.asarray(_checks.is_concrete(x)))(jnp.ones(2)) == False  # noqa: E712


# ------------------------------------------------------------------ batching and tracing

PHI, PSI = _gl(), _gl()
X_K, X_L = RNG.standard_normal(BATCH + (N,)), RNG.standard_normal(BATCH + (N,))
MAT = RNG.standard_normal(BATCH + (N, N))
SMALL = 0.3 * MAT

UNARY = {
    "green_tensor": deformation.green_tensor,
    "cauchy_tensor": deformation.cauchy_tensor,
    "inverse_green_tensor": deformation.inverse_green_tensor,
    "inverse_cauchy_tensor": deformation.inverse_cauchy_tensor,
    "lagrange_strain": deformation.lagrange_strain,
    "euler_strain": deformation.euler_strain,
    "trace_invariants": deformation.trace_invariants,
    "green_eigenvalues": deformation.green_eigenvalues,
    "characteristic_invariants": deformation.characteristic_invariants,
    "eigenvalues_from_traces": lambda phi: deformation.eigenvalues_from_traces(
        deformation.trace_invariants(phi)
    ),
    "polar": polar.polar,
    "left_polar": polar.left_polar,
    "two_polar": polar.two_polar,
    "from_two_polar": lambda phi: polar.from_two_polar(*polar.two_polar(phi)),
    "signed_singular_values": polar.signed_singular_values,
    "haar_density": polar.haar_density,
    "haar_density_with_translations": polar.haar_density_with_translations,
    "two_polar_haar_density": lambda phi: polar.two_polar_haar_density(polar.two_polar(phi).q),
    "project_SO": partial(groups.project, group="SO"),
    "project_R+O": partial(groups.project, group="R+O"),
    "project_SL": partial(groups.project, group="SL"),
    "is_member_GL+": partial(groups.is_member, group="GL+"),
    "project_algebra_R+so": partial(groups.project_algebra, group="R+SO"),
    "expm": lambda phi: groups.expm(0.3 * phi),
    "spin": lambda phi: momenta.spin(phi),
}

BINARY = {
    "mutual_green": mutual.mutual_green,
    "mutual_cauchy": mutual.mutual_cauchy,
    "mutual_gamma": mutual.mutual_gamma,
    "mutual_sigma": mutual.mutual_sigma,
    "mutual_lagrange_strain": mutual.mutual_lagrange_strain,
    "mutual_euler_strain": mutual.mutual_euler_strain,
    "mutual_gamma_strain": mutual.mutual_gamma_strain,
    "mutual_sigma_strain": mutual.mutual_sigma_strain,
    "mutual_trace_invariants": mutual.mutual_trace_invariants,
    "affine_invariants": mutual.affine_invariants,
    "mean_cauchy_tensor": mutual.mean_cauchy_tensor,
    "relative_volume": mutual.relative_volume,
    "spatial_affine_velocity": velocities.spatial_affine_velocity,
    "comoving_affine_velocity": velocities.comoving_affine_velocity,
    "gyroscopic_residual": velocities.gyroscopic_residual,
    "material_rotationless_residual": velocities.material_rotationless_residual,
    "affine_spin": momenta.affine_spin,
    "comoving_affine_spin": momenta.comoving_affine_spin,
    "momentum_from_affine_spin": momenta.momentum_from_affine_spin,
    "momentum_from_comoving_affine_spin": momenta.momentum_from_comoving_affine_spin,
    "internal_pairing": momenta.internal_pairing,
}

VECTOR = {
    "comoving_velocity": velocities.comoving_velocity,
    "comoving_momentum": momenta.comoving_momentum,
}


def _close_trees(got, expected, rtol=1e-11):
    for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
        assert g.shape == e.shape
        assert_close(g, e, rtol)


#: Two elements of the [2, 3] batch, checked one at a time against the batched result.
PROBES = ((0, 2), (1, 0))


def _check_elementwise(f, expected, *arrays):
    """f on single elements (no batch axes) agrees with the batched evaluation."""
    for i, j in PROBES:
        single = f(*(a[i, j] for a in arrays))
        _close_trees(single, jax.tree.map(lambda leaf, i=i, j=j: leaf[i, j], expected))


def _jit_vmap(f):
    """jit of vmap over the first batch axis: one compilation checks both transformations."""
    return jax.jit(jax.vmap(f))


#: Which inputs each function takes: configurations (PHI, PSI) or general matrices (MAT).
ARGUMENTS = {"phi": PHI, "psi": PSI, "mat": MAT}
_GENERAL_FIRST = ("internal_pairing",)
_GENERAL_SECOND = ("spatial_affine_velocity", "comoving_affine_velocity", "gyroscopic_residual",
                   "material_rotationless_residual", "affine_spin", "comoving_affine_spin",
                   "momentum_from_affine_spin", "momentum_from_comoving_affine_spin")


def _unary_argument(name):
    return "mat" if name.startswith("project_algebra") or name in ("expm", "spin") else "phi"


def _binary_arguments(name):
    return ("mat" if name in _GENERAL_FIRST else "phi",
            "mat" if name in _GENERAL_SECOND else "psi")


@functools.cache
def _all_under_jit_vmap():
    """Every unary and binary function under one jit(vmap(...)): one compilation for all."""

    def everything(args):
        out = {name: f(args[_unary_argument(name)]) for name, f in UNARY.items()}
        for name, f in BINARY.items():
            first, second = _binary_arguments(name)
            out[name] = f(args[first], args[second])
        return out

    return _jit_vmap(everything)(ARGUMENTS)


@pytest.mark.parametrize("name", sorted(UNARY))
def test_unary_functions_batch_jit_and_vmap(name):
    f = UNARY[name]
    arg = ARGUMENTS[_unary_argument(name)]
    expected = f(arg)  # 2 leading batch axes
    _check_elementwise(f, expected, arg)
    _close_trees(_all_under_jit_vmap()[name], expected)


@pytest.mark.parametrize("name", sorted(BINARY))
def test_binary_functions_broadcast_jit_and_vmap(name):
    f = BINARY[name]
    first, second = (ARGUMENTS[key] for key in _binary_arguments(name))
    expected = f(first, second)
    _check_elementwise(f, expected, first, second)
    # broadcasting: [2, 1, n, n] against [1, 3, n, n] gives [2, 3, ...]
    a = first[:, :1]
    b = second[:1, :]
    broadcast = f(a, b)
    _close_trees(broadcast, f(np.broadcast_to(a, first.shape), np.broadcast_to(b, second.shape)))
    _close_trees(_all_under_jit_vmap()[name], expected)


@pytest.mark.parametrize("name", sorted(VECTOR))
def test_vector_functions_broadcast_jit_and_vmap(name):
    f = VECTOR[name]
    expected = f(PHI, X_K)
    _check_elementwise(f, expected, PHI, X_K)
    _close_trees(f(PHI, X_K[0, 0]), f(PHI, np.broadcast_to(X_K[0, 0], X_K.shape)))
    _close_trees(_jit_vmap(f)(PHI, X_K), expected)


def test_affine_distance_broadcasts_and_traces():
    f = mutual.affine_distance
    expected = f(X_K, PHI, X_L, PSI)
    _check_elementwise(f, expected, X_K, PHI, X_L, PSI)
    _close_trees(_jit_vmap(f)(X_K, PHI, X_L, PSI), expected)
    _close_trees(f(X_K[:, :1], PHI[:, :1], X_L[:1], PSI[:1]),
                 f(*(np.broadcast_to(a, b.shape) for a, b in
                     ((X_K[:, :1], X_K), (PHI[:, :1], PHI), (X_L[:1], X_L), (PSI[:1], PSI)))))
    # its gradient is finite (zero) at coincident centres
    grad = jax.grad(lambda x: f(x, PHI[0, 0], X_K[0, 0], PSI[0, 0]))(X_K[0, 0])
    assert np.all(np.isfinite(grad))


def test_transform_state_traces():
    state = State(X_K, PHI, X_L, MAT)
    a, b, shift = _gl(()), _gl(()), RNG.standard_normal(N)
    expected = actions.transform_state(state, a, b, shift)
    vmapped = jax.vmap(actions.transform_state, in_axes=(0, None, None, None))
    _close_trees(jax.jit(vmapped)(state, a, b, shift), expected)
