"""Quantum operators of affine bodies: Hilbert-space measures, momenta, affine spins and the
one-parameter unitary groups of the paper's section "General quantization ideas", (88)-(113).

Wave functions are JAX callables returning a complex (or real) scalar:

- internal wave functions ``psi(phi)`` with ``phi`` of shape [n, n] (one body) or [N, n, n]
  (N bodies, the configuration (5) without translations);
- full wave functions ``psi(x, phi)`` with ``x`` of shape [n] / [N, n].

Every operator maps a wave function to a new callable of the same arguments; derivatives are
taken by forward-mode autodiff, so operators compose (nest) freely and work on tensor-valued
callables too: if ``f`` returns an array of shape S, ``affine_spin_op(f)`` returns an array of
shape [n, n, *S] (one body) or [N, n, n, *S] (the operator's own indices first, per body).
Use float64 (``jax.config.update("jax_enable_x64", True)``).

Index placement (docs/theory/conventions.md): ``phi[i, a]`` = phi^i_a. The operator arrays are

- ``Sigma[a, b]``     = Sigma^a_b     = (hbar/i) phi^a_c d/dphi^b_c          (93) spatial
- ``Sigma_hat[a, b]`` = Sigma_hat^a_b = (hbar/i) phi^c_b d/dphi^c_a          (93) co-moving
- ``pi[a, j]``        = p^a_j         = (hbar/i) d/dphi^j_a                  (113) canonical
- ``p[a]``            = p_a           = (hbar/i) d/dx^a                      (92)
- ``p_hat[a]``        = p_hat_a       = (hbar/i) phi^b_a d/dx^b              (92)
- ``Lambda[a, b]``    = Lambda^a_b    = x^a p_b                              (108) orbital
- ``J[a, b]``         = Lambda^a_b + Sigma^a_b                               (108), (109)

so the classical correspondences Sigma = phi @ pi, Sigma_hat = pi @ phi of state.py hold.

Measures (88)-(91). Every L^2 measure used here is ``w(phi) dx dphi`` with
``w = prod_K |det phi_K|^(-k)``: ``"lebesgue"`` (k = 0; the measures a, l), ``"haar"``
(k = n; the Haar measure lambda on GL(n), and lambda x dx on R^n x GL(n)) and
``"affine-haar"`` (k = n + 1; the measure alpha of (89), left Haar measure of the affine group).
A first-order operator X = (hbar/i) v^k d_k is formally Hermitian in w dphi iff
div_w v = (1/w) d_k(w v^k) = 0, and X + (hbar/2i) div_w v always is. Hence:

- Sigma, Sigma_hat: div_w = (n - k) delta^a_b: Hermitian in "haar"; the Lebesgue versions are
  (107): Sigma' = Sigma + (hbar n / 2i) Id, and (111) for the totals.
- pi: div_w = -k (phi^-1)^a_j: Hermitian in "lebesgue" (as stated after (113)); in "haar",
  pi_haar = pi - (hbar n / 2i) phi^-T (transposed placement).
- p, p_hat: always Hermitian. Lambda: div = delta^a_b in every measure: (110).
- Paper inconsistency (checked in the tests; docs/theory/paper-typos.md): in L^2(alpha) of
  (89), Sigma and Sigma_hat are *not* formally Hermitian (div = -delta); only
  J = Lambda + Sigma is, with no correction at all. (93) is Hermitian in L^2(lambda) and in
  L^2(lambda x dx).

Each operator takes ``measure``: ``None`` gives the paper's bare differential operator; a name
gives its formally Hermitian version in that measure (the correction above).

Unitary groups (94)-(102): ``translation_group``, ``left_translation_group``,
``right_translation_group``, ``spatial_affine_group`` return the transformed wave function
(96), (97), (99) (with the fix of (99) in docs/theory/paper-typos.md:
``(R(z) Psi)(phi) = Psi(phi exp z)``), times
the multiplier ``exp((n - k) Tr z / 2)`` per body that makes them unitary in the chosen measure
(none for "haar"). They are exp((i/hbar) z^b_a X^a_b) for the corresponding generator X.

Role: this module is part of the independent reference (autodiff on Cartesian wave functions,
no reduction) that the reduced solvers of :mod:`affinebody.quantum.spectra` are tested
against (tests/test_quantum_operators.py, tests/test_quantum_reduction.py); no solver
imports it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from affinebody import polar
from affinebody._checks import as_matrix
from affinebody.groups import expm

MEASURES = ("haar", "lebesgue", "affine-haar")

WaveFunction = Callable[..., jax.Array]


def density_exponent(measure: str, n: int) -> int:
    """k of the density ``|det phi|^(-k)`` per body: haar n, lebesgue 0, affine-haar n + 1."""
    if measure == "haar":
        return n
    if measure == "lebesgue":
        return 0
    if measure == "affine-haar":
        return n + 1
    raise ValueError(f"measure must be one of {MEASURES} (got {measure!r})")


def configuration_density(phi: jax.Array, measure: str) -> jax.Array:
    """Density |det phi|^(-k) of the measure w dx dphi per body, (88)-(91).

    ``phi`` [..., n, n] is one body (batched over leading axes) -- for N bodies multiply the
    per-body densities (the measures of the paper are N-fold products).
    """
    phi = as_matrix(phi, "phi")
    if measure == "haar":
        return polar.haar_density(phi)
    if measure == "affine-haar":
        return polar.haar_density_with_translations(phi)
    density_exponent(measure, phi.shape[-1])
    return jnp.ones(phi.shape[:-2])


# ----------------------------------------------------------------------------------------
# helpers: gradients with the differentiated argument's axes first, bodies as a leading axis


def _first_axes_jacobian(fn: Callable, argnum: int, *args) -> jax.Array:
    """Jacobian of ``fn(*args)`` (any output shape S, real or complex) w.r.t. ``args[argnum]``,
    with the argument's axes first: shape arg.shape + S."""
    jac = jax.jacfwd(fn, argnums=argnum)(*args)
    arg_ndim = jnp.ndim(args[argnum])
    out_ndim = jac.ndim - arg_ndim
    return jnp.moveaxis(jac, tuple(range(out_ndim, jac.ndim)), tuple(range(arg_ndim)))


def _bodies(a: jax.Array, trailing: int) -> tuple[jax.Array, tuple[int, ...]]:
    """Reshape [*B, *core] (len(core) == trailing, len(B) <= 1) to [K, *core]; return B too."""
    lead = a.shape[: a.ndim - trailing]
    if len(lead) > 1:
        raise ValueError(
            f"configuration must have shape [n, n] or [N, n, n] per wave-function call "
            f"(got leading axes {lead}); vmap over evaluation points instead"
        )
    return a.reshape((-1,) + a.shape[a.ndim - trailing :]), lead


def _identity_term(value: jax.Array, lead: tuple[int, ...], n: int) -> jax.Array:
    """delta^a_b * value, shaped [*lead, n, n, *value.shape]."""
    eye = jnp.eye(n).reshape((1,) * len(lead) + (n, n) + (1,) * jnp.ndim(value))
    return jnp.broadcast_to(eye, lead + (n, n) + jnp.shape(value)) * value


def _check_measure(measure: str | None, n: int) -> int | None:
    return None if measure is None else density_exponent(measure, n)


def _phi_gradient(psi: Callable, phi: jax.Array):
    """(grad [K, n, n, s], value, lead, S) of psi at phi, grad[k, i, a] = d psi / d phi_k^i_a."""
    grad = _first_axes_jacobian(psi, 0, phi)
    value = psi(phi)
    shape = jnp.shape(value)
    n = phi.shape[-1]
    phik, lead = _bodies(phi, 2)
    return grad.reshape((phik.shape[0], n, n, -1)), phik, value, lead, shape


# ----------------------------------------------------------------------------------------
# internal operators on psi(phi)


def affine_spin_op(psi: WaveFunction, hbar: float = 1.0, measure: str | None = None):
    """Spatial affine spin (93): ``Sigma^a_b = (hbar/i) phi^a_c d/dphi^b_c``.

    Generates the left regular translations phi -> exp(z) phi (95), (97). ``measure="lebesgue"``
    gives the Hermitian version (107), ``Sigma + (hbar n / 2i) delta``; ``None`` or ``"haar"``
    the bare operator (Hermitian in the Haar measure (91)). Returns ``phi -> [(N,) n, n, *S]``.
    """

    def op(phi):
        grad, phik, value, lead, shape = _phi_gradient(psi, phi)
        n = phi.shape[-1]
        out = (hbar / 1j) * jnp.einsum("kac,kbcs->kabs", phik, grad)
        out = out.reshape(lead + (n, n) + shape)
        k = _check_measure(measure, n)
        if k is not None and k != n:
            out = out + (hbar * (n - k) / 2j) * _identity_term(value, lead, n)
        return out

    return op


def comoving_affine_spin_op(psi: WaveFunction, hbar: float = 1.0, measure: str | None = None):
    """Co-moving affine spin (93): ``Sigma_hat^a_b = (hbar/i) phi^c_b d/dphi^c_a``.

    Generates the right regular translations phi -> phi exp(z) (98), (99). ``measure`` as in
    :func:`affine_spin_op` ((107) for "lebesgue"). Returns ``phi -> [(N,) n, n, *S]``.
    """

    def op(phi):
        grad, phik, value, lead, shape = _phi_gradient(psi, phi)
        n = phi.shape[-1]
        out = (hbar / 1j) * jnp.einsum("kcb,kcas->kabs", phik, grad)
        out = out.reshape(lead + (n, n) + shape)
        k = _check_measure(measure, n)
        if k is not None and k != n:
            out = out + (hbar * (n - k) / 2j) * _identity_term(value, lead, n)
        return out

    return op


def canonical_momentum_op(psi: WaveFunction, hbar: float = 1.0, measure: str | None = None):
    """Canonical momentum (113): ``pi[a, j] = p^a_j = (hbar/i) d/dphi^j_a`` (transposed placement).

    Bare (``None`` or ``"lebesgue"``): Hermitian in the Lebesgue measure. ``measure="haar"``
    (or "affine-haar") adds ``-(hbar k / 2i) (phi^-1)^a_j``, the Hermitian correction for
    ``|det phi|^-k``. Returns ``phi -> [(N,) n, n, *S]``.
    """

    def op(phi):
        grad, phik, value, lead, shape = _phi_gradient(psi, phi)
        n = phi.shape[-1]
        out = (hbar / 1j) * jnp.swapaxes(grad, 1, 2)
        k = _check_measure(measure, n)
        if k:
            inv = jnp.linalg.inv(phik)  # inv[k, a, j] = (phi^-1)^a_j
            out = out - (hbar * k / 2j) * inv[..., None] * value.reshape(1, 1, 1, -1)
        return out.reshape(lead + (n, n) + shape)

    return op


def spin_op(psi: WaveFunction, hbar: float = 1.0):
    """Spin S = Sigma - Sigma^T (49) as an operator: generator of spatial rotations.

    ``S[a, b] Psi = (hbar/i) d/dt Psi(exp(t K_ab) phi)`` with ``K_ab = E_ba - E_ab``."""
    sigma = affine_spin_op(psi, hbar)

    def op(phi):
        s = sigma(phi)
        nb = phi.ndim - 2
        return s - jnp.swapaxes(s, nb, nb + 1)

    return op


def vorticity_op(psi: WaveFunction, hbar: float = 1.0):
    """Vorticity V = Sigma_hat - Sigma_hat^T (49): generator of material rotations.

    ``V[a, b] Psi = (hbar/i) d/dt Psi(phi exp(t K_ab))`` with ``K_ab = E_ba - E_ab``."""
    sigma_hat = comoving_affine_spin_op(psi, hbar)

    def op(phi):
        s = sigma_hat(phi)
        nb = phi.ndim - 2
        return s - jnp.swapaxes(s, nb, nb + 1)

    return op


# ----------------------------------------------------------------------------------------
# translational operators on psi(x, phi)


def _x_gradient(psi: Callable, x: jax.Array, phi: jax.Array):
    grad = _first_axes_jacobian(psi, 0, x, phi)
    value = psi(x, phi)
    shape = jnp.shape(value)
    xk, lead = _bodies(x, 1)
    return grad.reshape((xk.shape[0], x.shape[-1], -1)), xk, value, lead, shape


def linear_momentum_op(psi: WaveFunction, hbar: float = 1.0):
    """Linear momentum (92): ``p_a = (hbar/i) d/dx^a`` on psi(x, phi); Hermitian in every
    measure of this module. Returns ``(x, phi) -> [(N,) n, *S]``."""

    def op(x, phi):
        grad, _, _, lead, shape = _x_gradient(psi, x, phi)
        return ((hbar / 1j) * grad).reshape(lead + (x.shape[-1],) + shape)

    return op


def comoving_linear_momentum_op(psi: WaveFunction, hbar: float = 1.0):
    """Co-moving linear momentum (92): ``p_hat_a = (hbar/i) phi^b_a d/dx^b`` (= phi^T p)."""

    def op(x, phi):
        grad, _, _, lead, shape = _x_gradient(psi, x, phi)
        phik, _ = _bodies(phi, 2)
        out = (hbar / 1j) * jnp.einsum("kba,kbs->kas", phik, grad)
        return out.reshape(lead + (x.shape[-1],) + shape)

    return op


def orbital_affine_momentum_op(psi: WaveFunction, hbar: float = 1.0, measure: str | None = None):
    """Orbital affine momentum (108): ``Lambda^a_b = x^a p_b``; with any ``measure`` the
    Hermitian version (110) ``Lambda + (hbar / 2i) delta`` (x always carries Lebesgue measure)."""

    def op(x, phi):
        grad, xk, value, lead, shape = _x_gradient(psi, x, phi)
        n = x.shape[-1]
        out = (hbar / 1j) * jnp.einsum("ka,kbs->kabs", xk, grad)
        out = out.reshape(lead + (n, n) + shape)
        if measure is not None:
            density_exponent(measure, n)
            out = out + (hbar / 2j) * _identity_term(value, lead, n)
        return out

    return op


def on_internal(internal_op: Callable[..., Callable], psi: WaveFunction, **kwargs):
    """Apply an internal operator (acting on psi(phi)) to a full wave function psi(x, phi)."""

    def op(x, phi):
        return internal_op(lambda ph: psi(x, ph), **kwargs)(phi)

    return op


def total_affine_momentum_op(psi: WaveFunction, hbar: float = 1.0, measure: str | None = None):
    """``J^a_b = Lambda^a_b + Sigma^a_b`` (108), per body; its sum over bodies is (109).

    Generates (x, phi) -> (exp(z) x, exp(z) phi). ``None`` or ``"affine-haar"``: the bare
    operator, formally Hermitian in alpha (89). ``"haar"``: Lambda' + Sigma; ``"lebesgue"``:
    Lambda' + Sigma' ((110) + (107)).
    """
    orbital_measure = None if measure in (None, "affine-haar") else measure
    spin_measure = None if measure in (None, "affine-haar") else measure
    lam = orbital_affine_momentum_op(psi, hbar, orbital_measure)
    sig = on_internal(affine_spin_op, psi, hbar=hbar, measure=spin_measure)
    return lambda x, phi: lam(x, phi) + sig(x, phi)


# ----------------------------------------------------------------------------------------
# one-parameter unitary groups (94)-(102)


def _multiplier(z: jax.Array, phi: jax.Array, measure: str | None) -> jax.Array:
    n = phi.shape[-1]
    k = _check_measure(measure, n)
    if k is None or k == n:
        return jnp.asarray(1.0)
    zb = jnp.broadcast_to(z, phi.shape)
    return jnp.exp(0.5 * (n - k) * jnp.sum(jnp.trace(zb, axis1=-2, axis2=-1)))


def translation_group(psi: WaveFunction, y: jax.Array) -> WaveFunction:
    """(94), (96), (100): ``(V(y) Psi)(x, phi) = Psi(x + y, phi)`` = exp((i/hbar) y^a p_a) Psi.

    ``y`` [n] translates every body (100), [N, n] each body separately (96)."""
    return lambda x, phi: psi(x + y, phi)


def left_translation_group(psi: WaveFunction, z: jax.Array, measure: str | None = None):
    """(95), (97), (101): ``(L(z) Psi)(phi) = Psi(exp(z) phi)`` = exp((i/hbar) z^b_a Sigma^a_b) Psi.

    ``z`` [n, n] acts on every body (101), [N, n, n] per body. With ``measure`` the generator is
    the Hermitian Sigma of that measure and the result carries ``exp((n - k) Tr z / 2)`` per body
    (unitary in that measure; e.g. exp(n Tr z / 2) for "lebesgue", generated by (107))."""

    def out(phi):
        return _multiplier(z, phi, measure) * psi(expm(z) @ phi)

    return out


def right_translation_group(psi: WaveFunction, z: jax.Array, measure: str | None = None):
    """(98), (99), (102): ``(R(z) Psi)(phi) = Psi(phi exp(z))`` = exp((i/hbar) z^b_a Sigma_hat^a_b)
    Psi (the corrected (99) of docs/theory/paper-typos.md); ``measure`` as in
    :func:`left_translation_group`."""

    def out(phi):
        return _multiplier(z, phi, measure) * psi(phi @ expm(z))

    return out


def spatial_affine_group(psi: WaveFunction, z: jax.Array) -> WaveFunction:
    """``Psi(x, phi) -> Psi(exp(z) x, exp(z) phi)`` = exp((i/hbar) z^b_a J^a_b) Psi, J of (108);
    unitary in alpha (89)."""

    def out(x, phi):
        ez = expm(z)
        return psi(jnp.einsum("...ab,...b->...a", ez, x), ez @ phi)

    return out


def generator_pairing(z: jax.Array, op_value: jax.Array, bodies: bool) -> jax.Array:
    """``(i/hbar)``-free pairing ``z^b_a X^a_b`` = sum_ab z[b, a] X[a, b] of an operator array
    ``X`` [(N,) n, n, *S] with ``z`` [n, n] (summed over bodies when ``bodies``)."""
    lead = 1 if bodies else 0
    x = op_value.reshape(op_value.shape[: lead + 2] + (-1,))
    zt = jnp.broadcast_to(jnp.swapaxes(z, -1, -2), x.shape[: lead + 2])
    summed = jnp.einsum("...ab,...abs->...s", zt, x)
    if bodies:
        summed = summed.sum(axis=0)
    return summed.reshape(op_value.shape[lead + 2 :])


__all__ = [
    "MEASURES", "density_exponent", "configuration_density", "affine_spin_op",
    "comoving_affine_spin_op", "canonical_momentum_op", "spin_op", "vorticity_op",
    "linear_momentum_op", "comoving_linear_momentum_op", "orbital_affine_momentum_op",
    "on_internal", "total_affine_momentum_op", "translation_group", "left_translation_group",
    "right_translation_group", "spatial_affine_group", "generator_pairing"
]
