"""Holonomic constraints: rigid, incompressible and shape-preserving bodies, every kinetic model.

The paper (section 1) places the affine body between the rigid body (phi in SO(n) or O(n), the
gyroscopic constraint (37), (39)), the incompressible body (SL(n), UL(n): det phi = +-1), the
shape-preserving body (R+SO(n), R+O(n): phi = s U) and the unconstrained one (GL(n)). On a
subgroup G with Lie algebra g (``groups.project_algebra``) the motion is the Hamiltonian system on
T*G obtained by restricting the Lagrangian to TG.

Momentum representatives. A covector on T_phi G is pi modulo the annihilator
N_phi = {Lambda phi^-1 : Lambda in g^perp} (g^perp: the Frobenius complement of g in gl(n):
R Id for sl, symmetric matrices for so, traceless symmetric ones for R+so). Two representatives
are used:

- the *Frobenius* one, Sigma_hat = pi phi in g (``system.project_momentum``): the state's pi;
- the *metric* lift (``metric_lift``): the one whose velocity (dH/dpi)^T is tangent to G. The
  restricted kinetic Hamiltonian is H_c(phi, [pi]) = H(phi, metric lift), the stationary value of
  H on the fibre pi + N_phi (its minimum for a positive definite T). This is the RATTLE velocity
  projection.

Drifts (flows of the kinetic energy on T*G), declared by each kinetic term as its
``constrained_drift`` (``kinetic.AbstractKineticTerm``; read by ``drift_mode``):

- ``"exact"``: the term's own exact flow stays on G, because its inertia maps g into g
  (isotropic af-is (74), is-af (73), af-af (72)) or because it keeps phi fixed (translational
  terms; the momentum change is then projected, which is exact);
- ``"lie-group"``: a left-invariant (l-af (70), af-J (65)) or right-invariant (r-af (71), H-af
  (67)) term restricted to G is again left- (right-) invariant on G. Its restricted inertia
  K_ab = Tr(Sigma_hat(E_a) E_b) on a Frobenius-orthonormal basis E_a of g has eigen-directions
  W_k in g; h_c = 1/2 sum_k Tr(W_k Sigma_hat)^2 / mu_k is split into rank-one pieces whose exact
  flows phi -> phi expm(t c W_k) run along one-parameter subgroups of G (McLachlan's Lie-Poisson
  splitting; NO_SQUISH for the rigid body). Explicit, symplectic on T*G, second order;
- ``"rattle"``: d'Alembert's T = 1/2 Tr(xi J xi^T) (6) is neither (its straight-line drift leaves
  G). Free RATTLE (Andersen 1983; Leimkuhler & Skeel 1994): pi_half = pi + Lambda phi^-1 with
  Lambda in g^perp, phi' = phi + h (J^-1 pi_half)^T, Lambda solved by Newton so that phi' is in G:
  one scalar per body for SL/UL (ln |det phi'| = 0), a symmetric matrix for SO/O
  (phi'^T phi' = Id), a traceless symmetric one for R+SO/R+O (phi'^T phi' = s'^2 Id). The velocity
  projection of RATTLE maps pi_half to a representative of the same covector, so the Frobenius
  projection that follows is equivalent. The map is symplectic and symmetric on T*G, so the
  compositions of ``integrators`` (Yoshida, Suzuki) raise its order.

The connected component of the initial phi is kept by continuity (det phi = -1 in UL(n), O(n),
R+O(n) stays -1).
"""

from __future__ import annotations

from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import _linalg as linalg
from affinebody._checks import transpose
from affinebody.groups import lie_algebra, project_algebra
from affinebody.kinetic import rank_one_splitting
from affinebody.state import State

#: Groups on which the momentum is a covector of a proper subgroup.
CONSTRAINED_GROUPS = ("SL", "UL", "SO", "O", "R+SO", "R+O")
#: The constrained drifts a kinetic term may declare (``constrained_drift``, module docstring).
DRIFT_MODES = ("exact", "lie-group", "rattle")

NEWTON_TOL = 1e-14
NEWTON_MAX_ITER = 30


# ------------------------------------------------------------------------------- bases
@lru_cache(maxsize=64)
def _bases(group: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Frobenius-orthonormal bases of g and of g^perp, shapes [d, n, n] and [n^2 - d, n, n]."""
    units = np.eye(n * n).reshape(n * n, n, n)
    with jax.ensure_compile_time_eval():
        projected = np.asarray(project_algebra(jnp.asarray(units), group)).reshape(n * n, n * n)
    u, s, _ = np.linalg.svd(projected.T)  # columns of u: eigenvectors of the projector
    d = int(np.sum(s > 0.5))
    return u[:, :d].T.reshape(d, n, n).copy(), u[:, d:].T.reshape(n * n - d, n, n).copy()


def algebra_basis(group: str, n: int) -> jax.Array:
    """Frobenius-orthonormal basis [d, n, n] of the Lie algebra of ``group``."""
    return jnp.asarray(_bases(group, n)[0])


def complement_basis(group: str, n: int) -> jax.Array:
    """Frobenius-orthonormal basis [n^2 - d, n, n] of g^perp (R Id, Sym or Sym_0)."""
    return jnp.asarray(_bases(group, n)[1])


# ------------------------------------------------------------------------------- residuals
def constraint_residual(phi: jax.Array, group: str) -> jax.Array:
    """The holonomic constraint c(phi) [..., m], zero on ``group``; m = dim g^perp.

    SL, UL: ln|det phi| (m = 1); SO, O: upper triangle of phi^T phi - Id (m = n(n+1)/2);
    R+SO, R+O: upper triangle of phi^T phi / s^2 - Id without its last diagonal entry,
    s^2 = Tr(phi^T phi)/n (m = n(n+1)/2 - 1). Scale-free in every case.
    """
    n = phi.shape[-1]
    algebra = lie_algebra(group)
    if algebra == "gl":
        return jnp.zeros(phi.shape[:-2] + (0,), phi.dtype)
    if algebra == "sl":
        return linalg.slogdet(phi)[1][..., None]
    g = transpose(phi) @ phi
    rows, cols = np.triu_indices(n)
    if algebra == "so":
        return (g - jnp.eye(n))[..., rows, cols]
    s2 = jnp.trace(g, axis1=-2, axis2=-1)[..., None, None] / n
    return (g / s2 - jnp.eye(n))[..., rows[:-1], cols[:-1]]


# ------------------------------------------------------------------------------- solvers
def _blockwise_jacobian(residual, z):
    """(r(z), dr/dz) for r block diagonal over the leading axes: [..., m], [..., m, m]."""
    r, linear = jax.linearize(residual, z)
    m = z.shape[-1]
    unit = jnp.eye(m, dtype=z.dtype).reshape((m,) + (1,) * (z.ndim - 1) + (m,))
    columns = jax.vmap(linear)(jnp.broadcast_to(unit, (m,) + z.shape))  # [k, ..., i]
    return r, jnp.moveaxis(columns, 0, -1)


def newton_blockwise(residual, z0, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER):
    """Solve residual(z) = 0 by Newton's method; z [..., m], one m x m block per body.

    ``residual`` must act independently on every leading index (bodies, batch), so that the
    Jacobian is block diagonal: its blocks come from m forward-mode products. Iterates
    (``lax.while_loop``) until the Newton step is below tol (1 + |z|), then takes one more step
    (so that forward-mode derivatives of the solution are exact). Returns (z, converged).
    """

    def change(z_new, z):
        return jnp.max(jnp.abs(z_new - z)) / (1.0 + jnp.max(jnp.abs(z_new)))

    def body(carry):
        z, k, err, _ = carry
        r, jac = _blockwise_jacobian(residual, z)
        z_new = z - linalg.solve(jac, r[..., None])[..., 0]
        # the step after the iteration (converged, or max_iter steps) is the loop's last: one
        # Newton step in the compiled graph instead of a second copy after the loop, which
        # halves the time to trace and compile the implicit integrators
        last = (err <= tol) | (k >= max_iter)
        return (z_new, jnp.where(last, k, k + 1), jnp.where(last, err, change(z_new, z)),
                last)

    start = (z0, 0, jnp.asarray(jnp.inf, z0.dtype), jnp.asarray(False))
    z, _, err, _ = lax.while_loop(lambda carry: ~carry[3], body, start)
    return z, err <= 100.0 * tol


def solve_linear_blockwise(residual, m: int, like: jax.Array) -> jax.Array:
    """Solution z [..., m] of the affine, block-diagonal equation residual(z) = 0."""
    z0 = jnp.zeros(like.shape[:-2] + (m,), like.dtype)
    r, jac = _blockwise_jacobian(residual, z0)
    return -linalg.solve(jac, r[..., None])[..., 0]


# ------------------------------------------------------------------------------- momenta
def _annihilator_directions(phi: jax.Array, group: str) -> jax.Array:
    """Lambda_j phi^-1 for the basis Lambda_j of g^perp: [..., m, n, n] (the fibre of pi)."""
    basis = complement_basis(group, phi.shape[-1])
    return jnp.einsum("jab,...bc->...jac", basis, linalg.inv(phi))


def metric_lift(kinetic_hamiltonian, state: State, group: str) -> State:
    """The representative of [pi] whose velocity is tangent to ``group`` (RATTLE's projection).

    ``kinetic_hamiltonian(state)`` is the kinetic energy (any leading shape, summed over bodies),
    quadratic in pi. The lift pi + sum_j c_j Lambda_j phi^-1 makes H stationary in c (a linear
    solve per body); H there is the restricted kinetic Hamiltonian H_c.
    """
    if lie_algebra(group) == "gl":
        return state
    directions = _annihilator_directions(state.phi, group)

    def gradient(c):
        def energy(c):
            pi = state.pi + jnp.einsum("...j,...jac->...ac", c, directions)
            return jnp.sum(kinetic_hamiltonian(state._replace(pi=pi)))

        return jax.grad(energy)(c)

    c = solve_linear_blockwise(gradient, directions.shape[-3], state.phi)
    return state._replace(pi=state.pi + jnp.einsum("...j,...jac->...ac", c, directions))


# ------------------------------------------------------------------------------- drifts
def drift_mode(term) -> str | None:
    """How the kinetic ``term`` drifts on a constrained group: the ``constrained_drift`` it
    declares (one of DRIFT_MODES, module docstring); None for a term that declares none
    (``HamiltonianSystem.check`` then probes whether its own flow keeps the group)."""
    mode = getattr(term, "constrained_drift", None)
    if mode is not None and mode not in DRIFT_MODES:
        raise ValueError(f"kinetic term {type(term).__name__} declares constrained_drift = "
                         f"{mode!r}; choose from {', '.join(DRIFT_MODES)}")
    return mode


def restricted_directions(term, group: str, n: int) -> tuple[jax.Array, jax.Array]:
    """Eigen-directions W_k in g [..., d, n, n] and rates 1/mu_k [..., d] of the restricted inertia.

    K_ab = Tr(S(E_a) E_b) with S the (co-moving for left-, spatial for right-invariant terms)
    affine spin of the velocity E_a, read off the Legendre map at phi = Id. Parameters with a
    body axis give one set per body.
    """
    basis = algebra_basis(group, n)
    spins = term.legendre(jnp.eye(n), basis.reshape((basis.shape[0], 1, n, n)))
    k = jnp.einsum("a...ij,bji->...ab", spins, basis)
    mu, u = jnp.linalg.eigh(0.5 * (k + jnp.swapaxes(k, -1, -2)))
    directions = jnp.einsum("...ak,aij->...kij", u, basis)
    return directions, 1.0 / mu


def lie_group_drift(term, state: State, h, group: str) -> State:
    """Second-order explicit symplectic drift of a left/right-invariant term restricted to G
    (the side is the term's declared ``invariance_side``)."""
    directions, rates = restricted_directions(term, group, state.phi.shape[-1])
    return rank_one_splitting(state, directions, rates, h, term.invariance_side)


def rattle_drift(term, state: State, h, group: str) -> State:
    """Free RATTLE step of a d'Alembert term (constant inertia) on ``group`` (module docstring).

    The returned pi is pi_half (a representative of the new covector, not yet projected); a
    step that does not converge returns NaN, which the run driver reports.
    """
    directions = _annihilator_directions(state.phi, group)
    m = directions.shape[-3]

    def moved(c):
        pi_half = state.pi + jnp.einsum("...j,...jac->...ac", c, directions)
        return state.phi + h * term.inverse_legendre(state.phi, pi_half), pi_half

    def residual(c):
        return constraint_residual(moved(c)[0], group)

    c0 = jnp.zeros(state.phi.shape[:-2] + (m,), state.phi.dtype)
    c, converged = newton_blockwise(residual, c0)
    phi, pi_half = moved(c)
    out = state._replace(phi=phi, pi=pi_half)
    return jax.tree.map(lambda a: jnp.where(converged, a, jnp.nan), out)


def constrained_flow(term, state: State, h, group: str) -> State:
    """The drift of one kinetic term on the constrained ``group`` (pi not yet projected)."""
    mode = drift_mode(term)
    if mode == "exact":
        return term.flow(state, h)
    if mode == "rattle":
        return rattle_drift(term, state, h, group)
    if mode == "lie-group":
        return lie_group_drift(term, state, h, group)
    raise ValueError(
        f"kinetic term {type(term).__name__} has no constrained drift on {group}(n): it is "
        f"neither d'Alembert nor left/right affinely invariant; use group = 'GL+'"
    )


__all__ = [
    "CONSTRAINED_GROUPS", "DRIFT_MODES", "algebra_basis", "complement_basis",
    "constrained_flow", "constraint_residual", "drift_mode",
    "lie_group_drift", "metric_lift", "newton_blockwise", "rattle_drift",
    "restricted_directions", "solve_linear_blockwise",
]
