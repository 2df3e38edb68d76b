"""Hamilton operators H = T + V (114), (115) of the kinetic models (76a)-(85).

Every classical kinetic Hamiltonian of the paper is a constant quadratic form in one family of
momentum-like quantities X (the canonical pi, the affine spins Sigma or Sigma_hat, or the
linear momenta p, p_hat):

    T = 1/2 sum K[alpha, beta] X_alpha X_beta,   K symmetric under alpha <-> beta.

The quantum kinetic operator substitutes the operators of :mod:`.operators` for X ("Simply one
should algebraically substitute ...", end of the paper): ``T Psi = 1/2 K[alpha, beta]
X_alpha (X_beta Psi)``, applied by nested forward-mode autodiff. As X are generators of
transformation groups and K is symmetric, there is no ordering ambiguity. With N bodies the
form is summed over bodies (same K for every body).

Checked in tests/test_quantum_operators.py: d'Alembert (76a) equals -hbar^2/2 times the
J^-1-weighted Laplacian on R^{n^2}; the affine models (af-is (85), is-af (84a), af-af (72),
af-J (79a), H-af (81a)) equal -hbar^2/2 times the Laplace-Beltrami operator of their classical
metric (74), (73), (72), (65), (67) computed independently from g(phi): no ordering
corrections (docs/theory/two-polar.md); af-is = Casimir combination + vorticity term (see
:func:`affine_isotropic_kinetic`).

Models (generators and coefficient tensors; indices as in operators.py):

- ``dalembert_kinetic(J)``           (76a) internal: X = pi, K[a,j,b,k] = (J^-1)[a,b] delta[j,k]
- ``dalembert_translational_kinetic(M)`` (76a),(77a): X = p,      K = Id / M
- ``affine_translational_kinetic(M)``    (78a):       X = p_hat,  K = Id / M
- ``affine_J_kinetic(J)``            (79a): X = Sigma_hat, K[a,b,c,d] = (J^-1)[a,c] delta[b,d]
- ``H_affine_kinetic(H)``            (81a): X = Sigma,     K[a,b,c,d] = (H^-1)[a,c] delta[b,d]
- ``left_invariant_kinetic(Lt)``     (82a): X = Sigma_hat, K = Lt (coefficient of X[A,B] X[C,D])
- ``right_invariant_kinetic(Rt)``    (83a): X = Sigma,     K = Rt
- ``isotropic_affine_kinetic(I,A,B,n)`` (84a) and ``affine_isotropic_kinetic(I,A,B,n)`` (85):
  K[a,b,c,d] = delta_ac delta_bd / I~ + delta_ad delta_bc / A~ + delta_ab delta_cd / B~ with
  I~, A~, B~ of (86); ``affine_affine_kinetic(A,B,n)`` (72) is the case I = 0 (1/I~ = 0).

``measure`` (see operators.py) selects which Hermitian versions are substituted: ``None``
(default) the paper's bare operators -- Hermitian in the Haar measure for the affine models and
in the Lebesgue measure for d'Alembert; ``"lebesgue"`` for the affine models substitutes (107),
``"haar"`` for d'Alembert the Haar-Hermitian pi. The results are unitarily equivalent via
multiplication by |det phi|^(n/2).

Role: this module is part of the independent reference (autodiff on Cartesian wave functions,
no reduction) that the reduced solvers of :mod:`affinebody.quantum.spectra` are tested
against (tests/test_quantum_operators.py, tests/test_quantum_reduction.py); no solver
imports it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _pytree
from affinebody._checks import as_float64, as_matrix, check_symmetric_positive_definite
from affinebody.quantum import operators as ops

GENERATORS: dict[str, Callable] = {
    "canonical": ops.canonical_momentum_op,
    "affine_spin": ops.affine_spin_op,
    "comoving_affine_spin": ops.comoving_affine_spin_op,
    "linear_momentum": ops.linear_momentum_op,
    "comoving_linear_momentum": ops.comoving_linear_momentum_op,
}
TRANSLATIONAL = ("linear_momentum", "comoving_linear_momentum")


@_pytree.dataclass
class QuadraticKineticOperator:
    """T = 1/2 K[alpha, beta] X_alpha X_beta with X = GENERATORS[generator] (see module doc).

    ``coefficients`` has shape [n, n, n, n] for the internal generators and [n, n] for the
    translational ones. Translational operators act on psi(x, phi), internal ones on psi(phi).
    """

    coefficients: jax.Array
    generator: str = _pytree.static_field(default="comoving_affine_spin")

    @property
    def translational(self) -> bool:
        return self.generator in TRANSLATIONAL

    def __call__(self, psi: Callable, hbar: float = 1.0, measure: str | None = None) -> Callable:
        """The callable ``T psi`` (same arguments as ``psi``)."""
        if self.generator not in GENERATORS:
            raise ValueError(
                f"generator must be one of {tuple(GENERATORS)} (got {self.generator!r})"
            )
        make = GENERATORS[self.generator]
        kwargs = {"hbar": hbar}
        if not self.translational:
            kwargs["measure"] = measure
        inner = make(psi, **kwargs)
        outer = make(inner, **kwargs)
        coeff = self.coefficients
        rank = coeff.ndim // 2

        def apply(*args):
            second = outer(*args)  # [(N,) X, (N,) X] with X of rank `rank`
            bodies = second.ndim > 2 * rank
            letters = "abcd"[: 2 * rank]
            first, last = letters[:rank], letters[rank:]
            if bodies:
                spec = f"k{first}k{last},{letters}->"
            else:
                spec = f"{first}{last},{letters}->"
            return 0.5 * jnp.einsum(spec, second, coeff)

        return apply


# ----------------------------------------------------------------------------------------
# model constructors


def _inverse_spd(a, name: str) -> jax.Array:
    a = as_matrix(a, name)
    check_symmetric_positive_definite(a, name)
    return jnp.linalg.inv(a)


def _positive(value, name: str) -> float:
    value = float(value)
    if not value > 0:
        raise ValueError(f"{name} must be > 0 (got {value})")
    return value


def dalembert_kinetic(J) -> QuadraticKineticOperator:
    """(76a) internal part: T = 1/2 Tr(pi^T J^-1 pi), pi = (hbar/i) d/dphi (113); J SPD."""
    jinv = _inverse_spd(J, "kinetic.J")
    n = jinv.shape[-1]
    coeff = jnp.einsum("ab,jk->ajbk", jinv, jnp.eye(n))
    return QuadraticKineticOperator(coeff, "canonical")


def dalembert_translational_kinetic(mass, n: int) -> QuadraticKineticOperator:
    """(76a), (77a): T_tr = 1/(2M) p^T p with p = (hbar/i) d/dx (92)."""
    m = _positive(mass, "kinetic.mass")
    return QuadraticKineticOperator(jnp.eye(n) / m, "linear_momentum")


def affine_translational_kinetic(mass, n: int) -> QuadraticKineticOperator:
    """(78a): T_tr^{af-is} = 1/(2M) p_hat^T p_hat with p_hat = phi^T p (92)."""
    m = _positive(mass, "kinetic.mass")
    return QuadraticKineticOperator(jnp.eye(n) / m, "comoving_linear_momentum")


def affine_J_kinetic(J) -> QuadraticKineticOperator:
    """(79a): T^{af-J} = 1/2 Tr(Sigma_hat^T J^-1 Sigma_hat); (80a) is J = I Id."""
    jinv = _inverse_spd(J, "kinetic.J")
    n = jinv.shape[-1]
    coeff = jnp.einsum("ac,bd->abcd", jinv, jnp.eye(n))
    return QuadraticKineticOperator(coeff, "comoving_affine_spin")


def H_affine_kinetic(H) -> QuadraticKineticOperator:  # noqa: N802 (the paper's name H-af)
    """(81a): T^{H-af} = 1/2 Tr(Sigma^T H^-1 Sigma)."""
    hinv = _inverse_spd(H, "kinetic.H")
    n = hinv.shape[-1]
    coeff = jnp.einsum("ac,bd->abcd", hinv, jnp.eye(n))
    return QuadraticKineticOperator(coeff, "affine_spin")


def _pair_symmetric(t, name: str) -> jax.Array:
    t = as_float64(t, name)
    if t.ndim != 4 or len(set(t.shape)) != 1:
        raise ValueError(f"{name} must have shape [n, n, n, n] (got {tuple(t.shape)})")
    return 0.5 * (t + jnp.transpose(t, (2, 3, 0, 1)))


def left_invariant_kinetic(inverse_inertia) -> QuadraticKineticOperator:
    """(82a): T^{l-af} = 1/2 Lt[A, B, C, D] Sigma_hat^A_B Sigma_hat^C_D (Lt symmetrised over
    (AB) <-> (CD)); ``inverse_inertia[A, B, C, D]`` multiplies Sigma_hat[A, B] Sigma_hat[C, D]."""
    return QuadraticKineticOperator(
        _pair_symmetric(inverse_inertia, "kinetic.inverse_inertia"), "comoving_affine_spin"
    )


def right_invariant_kinetic(inverse_inertia) -> QuadraticKineticOperator:
    """(83a): T^{r-af} = 1/2 Rt[i, j, k, l] Sigma^i_j Sigma^k_l."""
    return QuadraticKineticOperator(
        _pair_symmetric(inverse_inertia, "kinetic.inverse_inertia"), "affine_spin"
    )


def tilde_constants(I, A, B, n: int) -> tuple[float, float, float]:  # noqa: E741
    """(1/I~, 1/A~, 1/B~) of (86): I~ = (I^2 - A^2)/I, A~ = (A^2 - I^2)/A,
    B~ = -(I + A)(I + A + n B)/B (reciprocals, so that I = 0, A = 0 or B = 0 are allowed)."""
    I, A, B = float(I), float(A), float(B)  # noqa: E741
    if I * I == A * A:
        raise ValueError(
            f"kinetic.I and kinetic.A must satisfy I != |A| (got I={I}, A={A}): "
            "the kinetic form (73)/(74) is degenerate"
        )
    if (I + A) * (I + A + n * B) == 0:
        raise ValueError(
            f"kinetic.I + kinetic.A + n*kinetic.B must be nonzero (got I={I}, A={A}, B={B}, "
            f"n={n}): the dilatational inertia vanishes"
        )
    inv_i = I / (I * I - A * A)
    inv_a = A / (A * A - I * I)
    inv_b = -B / ((I + A) * (I + A + n * B))
    return inv_i, inv_a, inv_b


def _isotropic_coefficients(I, A, B, n: int) -> jax.Array:  # noqa: E741
    inv_i, inv_a, inv_b = tilde_constants(I, A, B, n)
    e = np.eye(n)
    coeff = (
        inv_i * np.einsum("ac,bd->abcd", e, e)
        + inv_a * np.einsum("ad,bc->abcd", e, e)
        + inv_b * np.einsum("ab,cd->abcd", e, e)
    )
    return jnp.asarray(coeff)


def affine_isotropic_kinetic(I, A, B, n: int) -> QuadraticKineticOperator:  # noqa: E741
    """(85): T^{af-is} = Tr(S^T S)/(2 I~) + Tr(S^2)/(2 A~) + (Tr S)^2/(2 B~), S = Sigma_hat.

    Equivalently ``Tr(Sigma^2)/(2(I+A)) + (Tr Sigma)^2/(2 B~) + sum_{a<b} V_ab^2/(2 I~)``:
    the GL(n) Casimirs plus the squared vorticity V = Sigma_hat - Sigma_hat^T (checked)."""
    return QuadraticKineticOperator(_isotropic_coefficients(I, A, B, n), "comoving_affine_spin")


def isotropic_affine_kinetic(I, A, B, n: int) -> QuadraticKineticOperator:  # noqa: E741
    """(84a): T^{is-af}, the form (85) in S = Sigma; the quadratic term is the squared spin."""
    return QuadraticKineticOperator(_isotropic_coefficients(I, A, B, n), "affine_spin")


def affine_affine_kinetic(A, B, n: int, generator: str = "comoving_affine_spin"):
    """(72): T^{af-af} = Tr(S^2)/(2 A~) + (Tr S)^2/(2 B~), the case I = 0 of (85)/(84a).

    Bi-invariant: ``generator`` "comoving_affine_spin" and "affine_spin" give the same
    operator (a combination of the GL(n) Casimirs Tr(Sigma^2), (Tr Sigma)^2; checked)."""
    return QuadraticKineticOperator(_isotropic_coefficients(0.0, A, B, n), generator)


def kinetic_operator_from_hamiltonian(
    hamiltonian: Callable, n: int, generator: str
) -> QuadraticKineticOperator:
    """Quantise a classical kinetic Hamiltonian ``h(phi, pi)`` (one body, [n, n] arrays).

    ``generator`` says which quantity h is a constant quadratic form of: "comoving_affine_spin"
    (left-invariant models: h depends on pi only through Sigma_hat = pi phi), "affine_spin"
    (right-invariant: Sigma = phi pi) or "canonical" (phi-independent form in pi, d'Alembert).
    At phi = Id all three coincide with pi, so K = Hessian of S -> h(Id, S).
    Use e.g. with the kinetic module: ``lambda phi, pi: term.hamiltonian(phi[None], pi[None])[0]``.
    """
    if generator not in ("comoving_affine_spin", "affine_spin", "canonical"):
        raise ValueError(
            "generator must be 'comoving_affine_spin', 'affine_spin' or 'canonical' "
            f"(got {generator!r})"
        )
    eye = jnp.eye(n)
    coeff = jax.jit(jax.hessian(lambda s: hamiltonian(eye, s)))(jnp.zeros((n, n)))
    return QuadraticKineticOperator(_pair_symmetric(coeff, "hessian"), generator)


# ----------------------------------------------------------------------------------------
# the Hamilton operator (114), (115)


def hamiltonian_op(
    psi: Callable,
    internal: QuadraticKineticOperator | None = None,
    translational: QuadraticKineticOperator | None = None,
    potential: Callable | None = None,
    hbar: float = 1.0,
    measure: str | None = None,
) -> Callable:
    """``H Psi = T_tr Psi + T_int Psi + V Psi`` (114), (115).

    With a ``translational`` term, ``psi`` and ``potential`` take (x, phi); otherwise they take
    phi. ``measure`` is passed to the internal term (see the module docstring).
    """
    if translational is not None and not translational.translational:
        raise ValueError("translational must be built on p or p_hat (got an internal term)")
    if internal is not None and internal.translational:
        raise ValueError("internal must be built on pi, Sigma or Sigma_hat (got a translational)")
    if translational is None:
        t_int = internal(psi, hbar, measure) if internal is not None else None

        def apply(phi):
            out = psi(phi) * (potential(phi) if potential is not None else 0.0)
            return out + (t_int(phi) if t_int is not None else 0.0)

        return apply

    t_tr = translational(psi, hbar)

    def apply_full(x, phi):
        out = t_tr(x, phi)
        if internal is not None:
            out = out + internal(lambda ph: psi(x, ph), hbar, measure)(phi)
        if potential is not None:
            out = out + potential(x, phi) * psi(x, phi)
        return out

    return apply_full


__all__ = [
    "GENERATORS", "TRANSLATIONAL", "QuadraticKineticOperator", "dalembert_kinetic",
    "dalembert_translational_kinetic", "affine_translational_kinetic", "affine_J_kinetic",
    "H_affine_kinetic", "left_invariant_kinetic", "right_invariant_kinetic", "tilde_constants",
    "affine_isotropic_kinetic", "isotropic_affine_kinetic", "affine_affine_kinetic",
    "kinetic_operator_from_hamiltonian", "hamiltonian_op"
]
