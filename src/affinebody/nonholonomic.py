"""Non-holonomic rotationless motion (40), (41): the constraint and Lagrange-d'Alembert dynamics.

The paper (section 1) names two linear velocity constraints on the internal motion:

- spatially rotationless, purely deformative motion: Omega = xi phi^-1 symmetric (40);
- materially rotationless motion: Omega_hat = phi^-1 xi symmetric (41).

They are not equivalent (Omega = phi Omega_hat phi^-1), and neither is integrable: the admissible
velocities at phi are Sym phi resp. phi Sym, and symmetric matrices are not a Lie subalgebra
([S1, S2] is skew), so the distribution is not involutive (Frobenius) and a closed loop of
admissible motions ends in a net rotation (``rotationless_loop``).

Dynamics (Lagrange-d'Alembert). With C_phi(xi) = 0 the linear constraint (the n(n-1)/2 entries
above the diagonal of Omega - Omega^T or Omega_hat - Omega_hat^T; on SL(n) and UL(n) also the
holonomic Tr(phi^-1 xi) = 0), the constraint forces lie in the annihilator, the range of C_phi^T:

    dphi/dt = (dH/dpi)^T,   dpi/dt = -(dH/dphi)^T + (C_phi^T lambda)^T,   C_phi(dphi/dt) = 0,

(in pi's transposed placement) i.e. Sigma = phi pi gains a skew part (40), Sigma_hat = pi phi a skew
part (41). The constraints are ideal and time-independent, so the energy H is conserved.
``lagrange_dalembert_field`` evaluates this vector field (lambda from d/dt C = 0).

Integrator (``affinebody.integrators.rattle``): the discrete Lagrange-d'Alembert principle
with the trapezoidal discrete Lagrangian L_d(q0, q1) = h/2 [L(q0, v) + L(q1, v)],
v = (q1 - q0)/h, and a RATTLE-type velocity projection (McLachlan & Perlmutter, J. Nonlinear
Sci. 16 (2006) 283; Cortes & Martinez, Nonlinearity 14 (2001) 1365):

    p0 + C_{q0}^T lambda = -D1 L_d(q0, q1),     C_{(q0 + q1)/2}((q1 - q0)/h) = 0,
    p1' = D2 L_d(q0, q1),                        p1 = p1' + C_{q1}^T mu,   C_{q1}(v(q1, p1)) = 0.

For d'Alembert's T it is non-holonomic RATTLE; for the affine models (phi-dependent metrics) it
is implicit in q1 and solved by Newton per body together with lambda. It is time-reversible
(the discrete constraint is symmetric in q0, q1), second order, keeps C_{q}(v) = 0 at every step
to round-off, and on SL/UL also ln|det phi| = 0. The energy error stays bounded (no drift).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg
from affinebody._checks import sym, transpose
from affinebody.constraints import solve_linear_blockwise
from affinebody.groups import lie_algebra
from affinebody.polar import polar
from affinebody.state import State

#: The two rotationless constraints: "spatial" is (40), "material" is (41).
ROTATIONLESS = ("spatial", "material")
#: Configuration spaces on which a rotationless constraint is accepted.
ROTATIONLESS_GROUPS = ("GL+", "GL", "SL", "UL")


def check_rotationless(rotationless, group: str) -> None:
    """ValueError for an unknown constraint or a group on which it makes no sense."""
    if rotationless is None:
        return
    if rotationless not in ROTATIONLESS:
        raise ValueError(
            f"constraints.rotationless must be 'spatial' (eq. (40)) or 'material' (eq. (41)) "
            f"(got {rotationless!r})"
        )
    if group in ("SO", "O"):
        raise ValueError(
            f"constraints.rotationless = {rotationless!r} on {group}(n) leaves no motion: Omega is "
            f"skew on a rigid body (37) and symmetric by (40)/(41); use group = 'GL+' or 'SL'"
        )
    if group in ("R+SO", "R+O"):
        raise ValueError(
            f"constraints.rotationless = {rotationless!r} on {group}(n) leaves only the dilatation "
            f"phi = s(t) U0, a holonomic 1-dimensional motion; use group = 'GL+' or 'SL'"
        )
    if group not in ROTATIONLESS_GROUPS:
        raise ValueError(
            f"constraints.rotationless needs invertible phi (Omega = xi phi^-1): use group in "
            f"{', '.join(ROTATIONLESS_GROUPS)} (got {group!r})"
        )


# ------------------------------------------------------------------------------- constraints
def _upper_skew(a: jax.Array) -> jax.Array:
    """The n(n-1)/2 entries of a - a^T above the diagonal."""
    rows, cols = np.triu_indices(a.shape[-1], 1)
    return (a - transpose(a))[..., rows, cols]


def velocity_constraint(phi, xi, rotationless: str, group: str = "GL+") -> jax.Array:
    """C_phi(xi) [..., m]: Omega - Omega^T (40) or Omega_hat - Omega_hat^T (41) above the
    diagonal, and Tr(phi^-1 xi) on SL/UL. Linear in xi; zero exactly for admissible xi."""
    if rotationless == "spatial":
        omega = transpose(linalg.solve(transpose(phi), transpose(xi)))
    else:
        omega = linalg.solve(phi, xi)
    c = _upper_skew(omega)
    if lie_algebra(group) == "sl":
        c = jnp.concatenate([c, jnp.trace(linalg.solve(phi, xi), axis1=-2, axis2=-1)[
            ..., None]], axis=-1)
    return c


def constraint_count(n: int, group: str) -> int:
    """m, the number of constraint components per body."""
    return n * (n - 1) // 2 + (1 if lie_algebra(group) == "sl" else 0)


def constraint_impulse(phi, lam, rotationless: str, group: str) -> jax.Array:
    """C_phi^T lambda in pi's placement [..., n, n] (an element of the annihilator)."""
    _, adjoint = jax.vjp(lambda xi: velocity_constraint(phi, xi, rotationless, group),
                         jnp.zeros_like(phi))
    return transpose(adjoint(lam)[0])


def admissible_momentum(kinetic, state: State, rotationless: str, group: str) -> State:
    """pi + C_phi^T mu whose velocity satisfies the constraint (the kinetic-metric projection)."""
    m = constraint_count(state.phi.shape[-1], group)

    def residual(mu):
        pi = state.pi + constraint_impulse(state.phi, mu, rotationless, group)
        xi = kinetic.inverse_legendre(state._replace(pi=pi)).xi
        return velocity_constraint(state.phi, xi, rotationless, group)

    mu = solve_linear_blockwise(residual, m, state.phi)
    return state._replace(pi=state.pi + constraint_impulse(state.phi, mu, rotationless, group))


def residuals(kinetic, state: State, rotationless: str, group: str = "GL+") -> jax.Array:
    """max |C_phi(v)| per batch element: the constraint violation of the state's velocity."""
    xi = kinetic.inverse_legendre(state).xi
    return jnp.max(jnp.abs(velocity_constraint(state.phi, xi, rotationless, group)),
                   axis=(-2, -1))


# ------------------------------------------------------------------------------- dynamics
def lagrange_dalembert_field(system, state: State) -> State:
    """(dx/dt, dphi/dt, dp/dt, dpi/dt) of the constrained equations (module docstring).

    lambda solves d/dt C_phi(v(phi, pi)) = 0 (a linear m x m system per body), so the
    constraint is kept by the exact flow; a reference for tests and for scipy solvers.
    """
    kind, group = system.rotationless, system.group
    grad = jax.grad(lambda s: jnp.sum(system.hamiltonian(s)))(state)
    free = State(x=grad.p, phi=transpose(grad.pi), p=-grad.x, pi=-transpose(grad.phi))

    def field(lam):
        return free._replace(pi=free.pi + constraint_impulse(state.phi, lam, kind, group))

    def constraint(s):
        return velocity_constraint(s.phi, system.kinetic.inverse_legendre(s).xi, kind, group)

    def rate(lam):
        return jax.jvp(constraint, (state,), (field(lam),))[1]

    lam = solve_linear_blockwise(rate, constraint_count(state.phi.shape[-1], group), state.phi)
    return field(lam)




# ------------------------------------------------------------------------------- non-integrability
def admissible_field(phi, s, rotationless: str) -> jax.Array:
    """The admissible velocity with symmetric Omega = s (40) or Omega_hat = s (41)."""
    return s @ phi if rotationless == "spatial" else phi @ s


def field_bracket(phi, s1, s2, rotationless: str) -> jax.Array:
    """Lie bracket [X_1, X_2](phi) = DX_2 . X_1 - DX_1 . X_2 of two admissible fields, by jvp.

    For (40) it is [s2, s1] phi, for (41) phi [s1, s2]: the affine velocity of the bracket is
    skew, so the bracket is not admissible and the distribution is not integrable (Frobenius).
    """
    def field(s):
        return lambda q: admissible_field(q, s, rotationless)

    x1, x2 = field(s1)(phi), field(s2)(phi)
    return jax.jvp(field(s2), (phi,), (x1,))[1] - jax.jvp(field(s1), (phi,), (x2,))[1]


def _log_spd(a: jax.Array) -> jax.Array:
    w, v = jnp.linalg.eigh(sym(a))
    return (v * jnp.log(w)[..., None, :]) @ transpose(v)


def rotationless_loop(phi0, s1, s2, rotationless: str):
    """A closed loop of admissible motions that ends in a net rotation (non-integrability).

    Five legs of unit duration with constant symmetric Omega (40) or Omega_hat (41): s1, s2,
    -s1, -s2 (their velocities integrate to zero), then the symmetric -log of the stretch left
    over, so that the deformation returns: for (40) phi_end = U phi0 (the Green tensor G (11)
    is back to G[phi0]), for (41) phi_end = phi0 U (the Cauchy tensor C (11) is back).
    Returns (legs [5, n, n] symmetric generators, phi_end, U); U != Id to order |[s1, s2]|.
    For a holonomic constraint every such loop would close: phi_end = phi0.
    """
    phi0, s1, s2 = (jnp.asarray(a, jnp.float64) for a in (phi0, s1, s2))
    e = linalg.expm
    if rotationless == "spatial":
        m = e(-s2) @ e(-s1) @ e(s2) @ e(s1)
        u, a = polar(m)
        b = u @ a @ transpose(u)  # left stretch: m = b u
        last = -_log_spd(b)
    else:
        m = e(s1) @ e(s2) @ e(-s1) @ e(-s2)
        u, a = polar(m)
        last = -_log_spd(a)
    legs = jnp.stack([s1, s2, -s1, -s2, last])
    phi = phi0
    for leg in legs:
        phi = e(leg) @ phi if rotationless == "spatial" else phi @ e(leg)
    return legs, phi, u


__all__ = [
    "ROTATIONLESS", "ROTATIONLESS_GROUPS",
    "admissible_field", "admissible_momentum", "check_rotationless", "constraint_count",
    "constraint_impulse", "field_bracket", "lagrange_dalembert_field", "residuals",
    "rotationless_loop", "velocity_constraint",
]
