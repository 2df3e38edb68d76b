"""Reduction of doubly isotropic Hamiltonians to the deformation invariants (two-polar
coordinates, the paper's last section; docs/theory/two-polar.md, "Reduced Hamiltonians").

Coordinates. ``phi = L D R^T`` with ``L, R`` in SO(n) and ``D = diag(exp q)``,
``q_1 > ... > q_n`` (affine models, GL+(n), Haar measure); for d'Alembert the whole of
L(n, R) with ``D = diag(Q)``, ``Q_1 > ... > Q_{n-1} > |Q_n|`` (``Q_n < 0`` iff det phi < 0).
``K_ab = E_ba - E_ab`` (a < b) is the rotation generator in the (a, b) plane. Body-frame
generators on wave functions Psi(L, q, R):

    rho_ab Psi = (hbar/i) d/dt Psi(L exp(t K_ab), q, R),
    tau_ab Psi = (hbar/i) d/dt Psi(L, q, R exp(t K_ab)).

sum rho^2 = spin Casimir sum_{a<b} S_ab^2 (S = Sigma - Sigma^T), sum tau^2 = vorticity Casimir
sum V_ab^2 (V = Sigma_hat - Sigma_hat^T). The map (L, q, R) -> phi is |M|-to-1, M = diagonal
sign matrices in SO(n) (|M| = 2 for n = 2, 4 for n = 3); single-valued wave functions satisfy
``Psi(L m, q, R m) = Psi(L, q, R)``.

Reduced Hamiltonians (V a function of the invariants only). In a sector, Psi is a fixed
combination of matrix elements of L and R times radial functions F(x) (a vector of d of them),
and rho_ab, tau_ab act on F as matrices; then

    H F = -(hbar^2/2) (1/J) sum_ab d_a (J G^ab d_b F) + U_sector(x) F + V(x) F,
    U_sector = sum_{a<b} [ c_+ (rho_ab + tau_ab)^2 + c_- (rho_ab - tau_ab)^2
                           + c_rho rho_ab^2 + c_tau tau_ab^2 ].

Settled sign (numerically, tests/test_quantum_reduction.py): with rho and tau *both* defined by
right multiplication by exp(t K_ab), the singular 1/sinh^2 (1/(Q_a - Q_b)^2) term carries
rho + tau -- the joint rotation L -> L e^{tK}, R -> R e^{tK} that leaves phi = L D R^T fixed
when q_a = q_b. Swapping the sign fails the check.

- af-is (85), x = q, L^2(Haar): M = I + A, 1/I~ = I/(I^2 - A^2) of (86),
  J = prod_{a<b} sinh(q_a - q_b), G^ab = delta^ab / M - B / (M (M + n B)),
  c_+ = 1/(16 M sinh^2((q_a - q_b)/2)), c_- = -1/(16 M cosh^2((q_a - q_b)/2)),
  c_rho = 0, c_tau = 1/(2 I~).
- is-af (84a): the same with rho <-> tau (c_rho = 1/(2 I~), c_tau = 0).
- af-af (72): I = 0: M = A, c_rho = c_tau = 0 (the classical metric is indefinite).
- d'Alembert (76a) with J = I Id, x = Q, L^2(Lebesgue): J = prod_{a<b} |Q_a^2 - Q_b^2|,
  G^ab = delta^ab / I, c_+ = 1/(4 I (Q_a - Q_b)^2), c_- = 1/(4 I (Q_a + Q_b)^2),
  c_rho = c_tau = 0.

The Haar measure is (up to the constant 2^{n(n-1)/2}, and |M|) J dq dmu(L) dmu(R); the Lebesgue
measure is J dQ dmu(L) dmu(R); so H is symmetric in L^2(J dx) on each sector.

The potential V is passed as a function of x (q or Q); V(phi) invariant under
phi -> U phi V (U, V in SO(n)) is a function of the invariants only.

Sectors provided:

- n = 2, ``so2_character_channel(m, k)``: Psi = exp(i m alpha) exp(i k beta) f(q), with
  L = L(alpha) = [[cos, -sin], [sin, cos]](alpha), R = R(beta). Then rho_12 = hbar m,
  tau_12 = hbar k, and for af-is
      U = hbar^2 (m + k)^2 / (16 M sinh^2((q_1 - q_2)/2))
          - hbar^2 (m - k)^2 / (16 M cosh^2((q_1 - q_2)/2)) + hbar^2 k^2 / (2 I~).
  Physical labels: spin S_12 = Sigma^1_2 - Sigma^2_1 has eigenvalue hbar m; vorticity
  V_12 = Sigma_hat^1_2 - Sigma_hat^2_1 has eigenvalue -hbar k (phi -> phi R(t) maps
  beta -> beta - t). So the 1/sinh^2 term is (spin - vorticity)^2. Identification: M = {Id, -Id}
  and (-L, q, -R) gives the same phi, so single-valuedness requires m + k even (equivalently
  m - k even): :func:`so2_sector_allowed`. d'Alembert: U = hbar^2 (m + k)^2/(4 I (Q_1 - Q_2)^2)
  + hbar^2 (m - k)^2 / (4 I (Q_1 + Q_2)^2), domain Q_1 > |Q_2|.
- any n, ``cartesian_channel(n, s, v)``: Psi = < c, (L^{(x)s} (x) R^{(x)v}) F(x) > for a constant
  tensor c, F a tensor with s spin (L) slots and v vorticity (R) slots, d = n^(s+v) radial
  functions. rho_ab acts as K_ab on every L slot, tau_ab as K_ab on every R slot. Rank 1 is the
  spin / vorticity 1 representation (the real form of the Wigner functions D^1), rank 0 the
  scalar. n = 3:
  * (s, v) = (0, 0), spin = vorticity = 0: U = 0, purely radial (one function f(q)):
    H f = -(hbar^2/2) (1/J) sum_ab d_a (J G^ab d_b f) + V f (any model; d'Alembert in Q).
  * (1, 0), (0, 1): no M-invariant states (the identification projector vanishes).
  * (1, 1), spin = vorticity = 1: M-invariance forces F diagonal, Psi = sum_a f_a(q) (L^T u)_a
    (R^T w)_a; three coupled radial functions with (af-is)
        (U f)_a = sum_{b != a} [ 2 hbar^2 c_+^{ab} (f_a - f_b) + 2 hbar^2 c_-^{ab} (f_a + f_b)
                                 + hbar^2 c_tau f_a ],
    (c^{ab} = c^{ba}), i.e. hbar^2/(8M) sum_{b!=a} [(f_a - f_b)/sinh^2((q_a - q_b)/2)
    - (f_a + f_b)/cosh^2((q_a - q_b)/2)] + hbar^2 f_a / I~ (the last term is the vorticity
    Casimir 2 hbar^2 / (2 I~)); is-af: c_tau -> c_rho (same numbers); af-af: no last term;
    d'Alembert: the Q-coefficients and no last term.
  Higher ranks (e.g. (2, 2)) are valid channels too (reducible; project with
  :func:`identification_projector` and by symmetry type as needed).

Verification: tests/test_quantum_reduction.py builds Psi(phi) from F through an SVD section
(:func:`two_polar_section`), applies the full operator of hamiltonians.py on R^{n^2} by
autodiff and compares with :meth:`TwoPolarReduction.apply` (asserted to 1e-8 relative; the
observed agreement is ~1e-13).

Role: this module is part of the independent reference (autodiff on Cartesian wave functions,
no reduction) that the reduced solvers of :mod:`affinebody.quantum.spectra` are tested
against (tests/test_quantum_operators.py, tests/test_quantum_reduction.py); no solver
imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations, product

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _pytree
from affinebody.polar import two_polar, two_polar_haar_density, two_polar_lebesgue_density

MODELS = ("af-is", "is-af", "af-af", "dalembert")


def pairs(n: int) -> list[tuple[int, int]]:
    """The index pairs (a, b), a < b, in the order used by every pair-indexed array here."""
    return list(combinations(range(n), 2))


def rotation_generator(n: int, a: int, b: int) -> np.ndarray:
    """K_ab = E_ba - E_ab: exp(t K_12) is the counter-clockwise rotation by t in the (a,b) plane."""
    k = np.zeros((n, n))
    k[b, a] = 1.0
    k[a, b] = -1.0
    return k


# ----------------------------------------------------------------------------------------
# channels: how rho_ab, tau_ab act on the vector F of radial functions


@_pytree.dataclass
class Channel:
    """Matrices r_ab, t_ab [pairs, d, d] with rho_ab = (hbar/i) r_ab, tau_ab = (hbar/i) t_ab
    acting on the radial vector F (see the module docstring)."""

    rho: jax.Array
    tau: jax.Array

    @property
    def dimension(self) -> int:
        return self.rho.shape[-1]


def so2_character_channel(m: int, k: int) -> Channel:
    """n = 2, Psi = exp(i m alpha) exp(i k beta) f(q): rho_12 = hbar m, tau_12 = hbar k."""
    return Channel(
        rho=jnp.asarray([[[1j * m]]], dtype=jnp.complex128),
        tau=jnp.asarray([[[1j * k]]], dtype=jnp.complex128),
    )


def so2_sector_allowed(m: int, k: int) -> bool:
    """Single-valuedness on GL+(2): Psi(-L, q, -R) = Psi(L, q, R) iff m + k is even."""
    return (m + k) % 2 == 0


def _slot_sum(gen: np.ndarray, slots: range, rank: int) -> np.ndarray:
    n = gen.shape[0]
    out = np.zeros((n**rank, n**rank))
    for slot in slots:
        factors = [np.eye(n)] * rank
        factors[slot] = gen
        term = factors[0]
        for f in factors[1:]:
            term = np.kron(term, f)
        out += term
    return out


def cartesian_channel(n: int, spin_rank: int, vorticity_rank: int) -> Channel:
    """Cartesian-tensor channel: F has ``spin_rank`` L slots then ``vorticity_rank`` R slots
    (row-major flattening); rho_ab = (hbar/i) sum over L slots of K_ab, tau likewise on R slots."""
    if spin_rank < 0 or vorticity_rank < 0:
        raise ValueError("spin_rank and vorticity_rank must be >= 0")
    rank = spin_rank + vorticity_rank
    rho, tau = [], []
    for a, b in pairs(n):
        gen = rotation_generator(n, a, b)
        rho.append(_slot_sum(gen, range(spin_rank), rank))
        tau.append(_slot_sum(gen, range(spin_rank, rank), rank))
    return Channel(rho=jnp.asarray(np.array(rho)), tau=jnp.asarray(np.array(tau)))


def identification_group(n: int) -> list[np.ndarray]:
    """M: the diagonal sign matrices with det +1 (the kernel of (L, q, R) -> L D R^T)."""
    out = []
    for signs in product((1.0, -1.0), repeat=n):
        if np.prod(signs) > 0:
            out.append(np.diag(signs))
    return out


def identification_projector(n: int, spin_rank: int, vorticity_rank: int) -> jax.Array:
    """Projector onto channel vectors F with Psi(L m, q, R m) = Psi(L, q, R) for all m in M:
    the average of m^{(x)(s+v)} over M."""
    rank = spin_rank + vorticity_rank
    acc = np.zeros((n**rank, n**rank))
    group = identification_group(n)
    for m in group:
        term = np.ones((1, 1))
        for _ in range(rank):
            term = np.kron(term, m)
        acc += term
    return jnp.asarray(acc / len(group))


def cartesian_wave_function(L, R, F, outer, spin_rank: int, vorticity_rank: int):
    """Psi = < outer, (L^{(x)s} (x) R^{(x)v}) F > for F flattened [d] (complex or real)."""
    n = L.shape[-1]
    rank = spin_rank + vorticity_rank
    t = jnp.reshape(F, (n,) * rank)
    mats = [L] * spin_rank + [R] * vorticity_rank
    for slot, mat in enumerate(mats):
        t = jnp.moveaxis(jnp.tensordot(mat, t, axes=([1], [slot])), 0, slot)
    return jnp.sum(jnp.reshape(outer, (n,) * rank) * t)


def so2_angle(rotation: jax.Array) -> jax.Array:
    """alpha with rotation = [[cos, -sin], [sin, cos]](alpha)."""
    return jnp.arctan2(rotation[1, 0], rotation[0, 0])


# ----------------------------------------------------------------------------------------
# a smooth local section of the two-polar map


def two_polar_section(phi: jax.Array):
    """(L, Q, R) with phi = L diag(Q) R^T, L, R in SO(n), |Q| descending, Q_n < 0 iff det < 0.

    :func:`affinebody.polar.two_polar` (SVD with the signs fixed by determinants) with the sign
    moved into Q; differentiable to any order where the singular values are distinct. For the
    affine models q = log Q (det phi > 0).
    """
    tp = two_polar(phi)
    n = tp.q.shape[-1]
    last = jnp.arange(n) == n - 1
    Q = jnp.exp(tp.q) * jnp.where(last, tp.sign[..., None], 1.0)
    return tp.L, Q, tp.R


# ----------------------------------------------------------------------------------------
# the reduced operators


@dataclass(frozen=True)
class TwoPolarReduction:
    """Reduced Hamiltonian of a doubly isotropic model (see the module docstring).

    ``model`` in MODELS; ``I, A, B`` the inertial constants of (72)-(74) (af-af ignores I);
    for "dalembert" ``I`` is the scalar inertia of J = I Id. ``x`` below is q (affine models)
    or Q (d'Alembert), shape [n].
    """

    model: str
    n: int
    I: float = 1.0  # noqa: E741
    A: float = 0.0
    B: float = 0.0
    hbar: float = 1.0

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS} (got {self.model!r})")
        if self.n < 1:
            raise ValueError(f"n must be >= 1 (got {self.n})")
        if self.model == "dalembert":
            if not self.I > 0:
                raise ValueError(f"I must be > 0 for d'Alembert J = I Id (got I={self.I})")
            return
        mass = self.radial_mass
        if mass == 0 or mass + self.n * self.B == 0:
            raise ValueError(
                f"I + A and I + A + n B must be nonzero for {self.model} "
                f"(got I={self.I}, A={self.A}, B={self.B})"
            )
        if self.model != "af-af" and self.I**2 == self.A**2:
            raise ValueError(f"I != |A| required for {self.model} (got I={self.I}, A={self.A})")

    @property
    def radial_mass(self) -> float:
        """M = I + A (A for af-af; I for d'Alembert)."""
        if self.model == "af-af":
            return float(self.A)
        if self.model == "dalembert":
            return float(self.I)
        return float(self.I + self.A)

    def radial_weight(self, x: jax.Array) -> jax.Array:
        """J(x): prod_{a<b} sinh(q_a - q_b) (Haar) or prod_{a<b} |Q_a^2 - Q_b^2| (Lebesgue)."""
        if self.model == "dalembert":
            return two_polar_lebesgue_density(x)
        return two_polar_haar_density(x)

    def radial_inverse_metric(self) -> jax.Array:
        """G^{ab}: delta/M - B/(M (M + n B)) (affine models), delta/I (d'Alembert)."""
        mass = self.radial_mass
        eye = jnp.eye(self.n)
        if self.model == "dalembert":
            return eye / mass
        return eye / mass - self.B / (mass * (mass + self.n * self.B)) * jnp.ones((self.n, self.n))

    def pair_coefficients(self, x: jax.Array) -> jax.Array:
        """[..., pairs, 4]: (c_+, c_-, c_rho, c_tau) of U_sector for every pair a < b."""
        x = jnp.asarray(x)
        mass = self.radial_mass
        out = []
        for a, b in pairs(self.n):
            if self.model == "dalembert":
                c_plus = 1.0 / (4 * mass * (x[..., a] - x[..., b]) ** 2)
                c_minus = 1.0 / (4 * mass * (x[..., a] + x[..., b]) ** 2)
                c_rho = c_tau = jnp.zeros_like(c_plus)
            else:
                half = 0.5 * (x[..., a] - x[..., b])
                c_plus = 1.0 / (16 * mass * jnp.sinh(half) ** 2)
                c_minus = -1.0 / (16 * mass * jnp.cosh(half) ** 2)
                quad = 0.0
                if self.model != "af-af":
                    quad = self.I / (2 * (self.I**2 - self.A**2))  # 1/(2 I~)
                zero = jnp.zeros_like(c_plus)
                c_rho = zero + (quad if self.model == "is-af" else 0.0)
                c_tau = zero + (quad if self.model == "af-is" else 0.0)
            out.append(jnp.stack([c_plus, c_minus, c_rho, c_tau], axis=-1))
        return jnp.stack(out, axis=-2)

    def sector_potential(self, x: jax.Array, channel: Channel) -> jax.Array:
        """U_sector(x) [..., d, d] (with rho = (hbar/i) r: (rho + tau)^2 = -hbar^2 (r + t)^2)."""
        coeff = self.pair_coefficients(x)
        r, t = channel.rho, channel.tau
        sq = lambda m: m @ m
        blocks = jnp.stack([sq(r + t), sq(r - t), sq(r), sq(t)], axis=1)  # [pairs, 4, d, d]
        return -(self.hbar**2) * jnp.einsum("...pk,pkde->...de", coeff.astype(blocks.dtype), blocks)

    def apply(
        self,
        F: Callable[[jax.Array], jax.Array],
        x: jax.Array,
        channel: Channel,
        potential: Callable[[jax.Array], jax.Array] | None = None,
    ) -> jax.Array:
        """(H F)(x) [d] for a radial vector function ``F: x [n] -> [d]`` (autodiff in x)."""
        G = self.radial_inverse_metric()

        def flux(y):
            grad = jax.jacfwd(F)(y)  # [d, n]
            return self.radial_weight(y) * grad @ G.T

        div = jnp.trace(jax.jacfwd(flux)(x), axis1=-2, axis2=-1)
        out = -(self.hbar**2) / 2 * div / self.radial_weight(x)
        out = out + self.sector_potential(x, channel) @ F(x)
        if potential is not None:
            out = out + potential(x) * F(x)
        return out


__all__ = [
    "MODELS", "pairs", "rotation_generator", "Channel", "so2_character_channel",
    "so2_sector_allowed", "cartesian_channel", "identification_group", "identification_projector",
    "cartesian_wave_function", "so2_angle", "two_polar_section", "TwoPolarReduction"
]
