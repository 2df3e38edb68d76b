"""Potential energies of N affine bodies: one-body (57), (58), (80), (81) and binary (59)-(62),
(77), (78) terms, with forces and torques by automatic differentiation.

Every potential is a small frozen (hashable) dataclass with

- ``pot.energy(x [..., N, n], phi [..., N, n, n]) -> [...]`` the total energy, summed over
  bodies and over unordered pairs;
- ``pot.symmetry``: a frozenset of the symmetries it has (see below), inferred from the
  variables it depends on, so a declaration cannot be wrong;

and :func:`total_potential` adds several. Generalised forces are ``-jax.grad`` of the energy
(:func:`generalized_forces`); note ``dV/dphi`` has the shape of ``phi``
(docs/theory/conventions.md: Hamilton's equation is ``dpi/dt = -(dV/dphi)^T``).

One-body potentials (57) are sums over bodies of ``f(variables)`` where the variables are
(``n`` the dimension, ``a = 1..n``):

==========  ================================================================================
``x1..xn``  components of the centre x (an external field breaks translations)
``det``     det phi (volume ratio; the dilatation potentials (80), (81))
``trG``     Tr G[phi] = K1
``K1..Kn``  K_a[phi] = Tr(G^a), G = phi^T phi, eq. (17)
``I1..In``  characteristic invariants of G, eq. (19)
``E1..En``  Tr(E^a) of the Lagrange strain E = (G - Id)/2, eq. (32)
==========  ================================================================================

and, for Python callables only, the arrays ``x`` [n], ``phi`` [n, n], ``K``, ``I`` [n] and
``E`` [n, n]. The separable form (58) is the sum of a term in ``x`` and a term in ``phi``.

Pair potentials are ``V = sum_{K<L} V_KL``, which is the paper's ``1/2 sum_{K != L}`` (59) when
``V_KL`` is symmetric in (K, L); variables that are not symmetric (``M_a`` and ``det``, since
``Gamma[phi_L, phi_K] = Gamma[phi_K, phi_L]^-1``) are handled by averaging ``f`` over both orders,
which is exactly (59) with one function ``f`` for all pairs. The variables of (61), (62), (77),
(78) are

==========  ================================================================================
``r``       |x_K - x_L| (minimum image in a periodic box)
``D``       the affine distance of (75), sqrt(u^T (C[phi_K] + C[phi_L])/2 u), u = x_K - x_L
``det``     relative volume det Gamma[phi_K, phi_L] = det phi_L / det phi_K, eq. (79)
``K1..Kn``  K_a[phi_K, phi_L] = Tr((phi_K^T phi_L)^a), eq. (28)
``M1..Mn``  M_a[phi_K, phi_L] = Tr((phi_K^-1 phi_L)^a), eq. (30)
==========  ================================================================================

(callables may also take the arrays ``K`` and ``M`` [n]). The separable form (60) is the sum of a
pair potential in ``r`` and one in ``K``/``M``/``det``.

Symmetries (the strings shared with :mod:`affinebody.kinetic`). Each names a group acting on all
bodies at once; Euclidean means proper rotations R in SO(n) (a potential of ``det`` is not
invariant under reflections):

=======================  =====================================================================
``translation``          x_K -> x_K + b
``spatial-euclidean``    (x_K, phi_K) -> (R x_K, R phi_K)
``spatial-affine``       (x_K, phi_K) -> (A x_K, A phi_K), A in GL(n)  (76)
``material-euclidean``   phi_K -> phi_K R
``material-affine``      phi_K -> phi_K B, B in GL(n)  (27), (31)
=======================  =====================================================================

``r`` and ``K_a`` break spatial affine symmetry, ``D`` and ``K_a`` break material affine
symmetry, ``M_a`` and ``det Gamma`` keep all of them (31), (79): functions of ``D`` and ``M_a``
only are the purely affine binary models (78). By Noether's theorem a spatially affine potential
has ``sum_K [x_K (dV/dx_K)^T + phi_K (dV/dphi_K)^T] = 0``, a materially affine one
``sum_K phi_K^T dV/dphi_K = 0``, a translation-invariant one ``sum_K dV/dx_K = 0``.

Cut-off: a pair potential may carry a :class:`Cutoff` on ``r`` or ``D``: the pair energy is
multiplied by the C^2 quintic switch ``S`` (1 below ``r_on``, 0 from ``r_cut`` on) and is exactly
zero, with exactly zero gradient, at and beyond ``r_cut``. A periodic ``box`` (n edges of an
orthorhombic box, an n x n cell matrix of a triclinic one, or an :class:`affinebody.space.Space`)
uses the minimum image and requires a cut-off on ``r`` of at most half the smallest perpendicular
width (the shortest edge if orthorhombic), so that the minimum image is the only image in range;
a box breaks the spatial rotations.

Large N: ``energy(x, phi, neighbors)`` sums over the pairs of a neighbour list
(:mod:`affinebody.neighbors`) with the closed-form force kernel of :mod:`affinebody.pair_kernels`;
without a list the sum runs over all N(N-1)/2 pairs.

NaN-free gradients: ``r`` and ``D`` use the double-``where`` square root (gradient 0 at 0), pairs
beyond the cut-off are evaluated at a harmless reference point (identity configurations at the
cut-off distance) before masking, and the diagonal K = L is never formed (pairs K < L only).

Layout: :mod:`~affinebody.potentials.variables` (variable names, values and the symmetry they
imply), :mod:`~affinebody.potentials.terms` (``AbstractPotentialTerm``, ``OneBodyTerm``,
``PairTerm`` and its contract with ``pair_kernels``, the cut-off, sums and forces),
:mod:`~affinebody.potentials.library` (the built-in models) and
:mod:`~affinebody.potentials.registry` (the kinds a config file names, ``POTENTIALS``).
"""

from affinebody.potentials.library import (
    Dilatation,
    ExternalHarmonic,
    ExternalLinear,
    Gaussian,
    HarmonicInvariants,
    LennardJones,
    Morse,
    OneBodyPotential,
    PairPotential,
    StVenantKirchhoff,
)
from affinebody.potentials.registry import POTENTIALS, PotentialFamily, build_potential
from affinebody.potentials.terms import (
    AbstractPotentialTerm,
    Cutoff,
    NoNeighborRange,
    OneBodyTerm,
    PairTerm,
    TotalPotential,
    generalized_forces,
    neighbor_range,
    switching,
    terms_of,
    total_potential,
)
from affinebody.potentials.variables import (
    SYMMETRIES,
    one_body_symmetry,
    one_body_variable_names,
    one_body_variables,
    pair_symmetry,
    pair_variable_names,
    pair_variables,
)

__all__ = [
    "POTENTIALS",
    "SYMMETRIES",
    "AbstractPotentialTerm",
    "Cutoff",
    "Dilatation",
    "ExternalHarmonic",
    "ExternalLinear",
    "Gaussian",
    "HarmonicInvariants",
    "LennardJones",
    "Morse",
    "NoNeighborRange",
    "OneBodyPotential",
    "OneBodyTerm",
    "PairPotential",
    "PairTerm",
    "PotentialFamily",
    "StVenantKirchhoff",
    "TotalPotential",
    "build_potential",
    "neighbor_range",
    "generalized_forces",
    "one_body_symmetry",
    "one_body_variable_names",
    "one_body_variables",
    "pair_symmetry",
    "pair_variable_names",
    "pair_variables",
    "switching",
    "terms_of",
    "total_potential",
]
