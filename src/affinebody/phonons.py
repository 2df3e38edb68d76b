"""Lattice dynamics of crystals of affine bodies: dispersion relations, densities of states,
sound speeds and elastic constants (docs/phonons.md).

A crystal is the content of a periodic box (the system's pair terms carry it, with a cut-off on
r of at most half the box's perpendicular width, so that every pair in range is a minimum
image), repeated by the box's lattice. The box is orthorhombic (``system.box``: n edges) or, in
the library, triclinic (an n x n cell matrix or a triclinic :class:`affinebody.space.Space`);
it is ``cells[j]`` primitive cells along its vector h_j (found by :func:`find_cells`: the
largest translations h_j / m_j that map bodies onto bodies with the same phi and the same
inertia), so the primitive vectors a_j = h_j / cells_j may be oblique. A lattice whose
primitive vectors are not fractions of the box vectors (a triangular lattice in a rectangular
box, bcc or fcc in a cubic box) is described by the conventional cell that the box vectors
give, with several bodies: the spectrum is exact, folded into the smaller Brillouin zone.

Each body K has n translational and dim g internal degrees of freedom, in
the chart (spatial affine velocity of the paper's (34))

    x_K = x0_K + dx_K,        phi_K = (Id + X_K + X_K^2 / 2) phi0_K,   X_K = sum_a theta_K^a E_a,

with E_a a Frobenius-orthonormal basis of the Lie algebra g of the configuration group (gl(n) on
GL+, GL, L; sl, so, R Id + so on the subgroups), i.e. the tangent space T_phi0 G = g phi0. The
chart agrees with phi = expm(X) phi0 to second order, which is all a Hessian at phi0 sees, so
constrained bodies (SL, SO, R+SO, ...) move in the tangent space of their group and the
constraint forces enter through the curvature term of the chart.

Harmonic Hamiltonian at an equilibrium q0 (p0 = 0; eq. (75a) to second order):

    H = 1/2 dq_dot^T M dq_dot + 1/2 dq^T K dq,

M the kinetic metric, T = 1/2 q_dot^T M q_dot at q0 (block diagonal per body: the Hessian of the
model's kinetic energy (63)-(74) in the velocities; T has no x-phi cross terms), K the Hessian
of V. With Bloch waves dq_{R, s} = u_s exp(i k.R) (R a lattice vector, s a body of the
primitive cell) the frequencies solve the generalized Hermitian eigenproblem

    D(k) u = omega^2 M u,      D(k) = sum_R K_{0 s, R s'} exp(i k.R).

The force constants K_{0 s, R s'} come from the pair terms' second derivatives: for every body s
of the primitive cell and every neighbour (s', R) within the cut-off (the minimum image in the
box) the Hessian of the pair energy V_{s, (s', R)} (59) in the chart coordinates of both bodies
(autodiff; "bonds"), plus the Hessian of the one-body terms (57). Each unordered pair of the
infinite crystal is met once from each end, so every bond enters with weight 1/2 in the blocks
(s, s), (s, s') e^{i k.R}, (s', s) e^{-i k.R}, (s', s'), which makes D(k) exactly Hermitian.
This is exact for every k (no supercell of the wave is needed) and costs one small Hessian per
bond.

Frequencies: omega = sqrt(omega^2), and for an unstable mode (omega^2 < 0) the imaginary
frequency is reported as -sqrt(-omega^2) (never hidden; ``imaginary`` marks them); only
round-off zeros, |omega^2| <= 1e-12 max_k |omega^2|, are set to 0.

Long waves (``christoffel``): eliminating every degree of freedom but the n uniform
translations T statically, S(k) = T^H D T - T^H D Q (Q^H D Q)^-1 Q^H D T (Q the M-orthogonal
complement of T) gives omega^2 = eig(S(k), T^T M T) + O(k^4); Re S(k) = Gamma(k) + O(k^4) with
the Christoffel (acoustic) matrix Gamma_ik(k) = V_cell A_ijkl k_j k_l, A = d^2 W / d beta d beta
the energy density's second derivative in the displacement gradient (with internal relaxation).
Sound speeds are sqrt(eig(Gamma(k_hat), T^T M T)); the elastic constants C (Voigt) are fitted to
A with the minor and major symmetries (exact when the crystal is stress-free).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from affinebody.groups import expm, lie_algebra, project_algebra
from affinebody.pair_kernels import energy_and_gradients
from affinebody.potentials import OneBodyTerm, PairTerm, terms_of
from affinebody.space import Space, as_space
from affinebody.state import VelocityState

#: Names of the characters of a mode: shares of its kinetic energy.
CHARACTERS = ("translational", "dilatational", "shear", "rotational")
#: The one-body Hessians and the kinetic metric are small and run once: compile them fast.
_QUICK = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
#: High-symmetry points of the orthorhombic Brillouin zone, in units of the reciprocal vectors.
POINTS = {
    "G": (0.0, 0.0, 0.0), "X": (0.5, 0.0, 0.0), "Y": (0.0, 0.5, 0.0), "Z": (0.0, 0.0, 0.5),
    "M": (0.5, 0.5, 0.0), "S": (0.5, 0.5, 0.0), "U": (0.5, 0.0, 0.5), "T": (0.0, 0.5, 0.5),
    "R": (0.5, 0.5, 0.5),
}
#: Default high-symmetry path per dimension.
DEFAULT_PATHS = {1: ("G", "X"), 2: ("G", "X", "M", "G"), 3: ("G", "X", "M", "G", "R", "X")}


# --------------------------------------------------------------------------------------------
# The crystal


def algebra_basis(group: str, n: int) -> np.ndarray:
    """A Frobenius-orthonormal basis [g, n, n] of the Lie algebra of ``group`` (gl, sl, so or
    R Id + so, :func:`affinebody.groups.project_algebra`)."""
    units = np.eye(n * n).reshape(n * n, n, n)
    projected = np.asarray(project_algebra(jnp.asarray(units), group)).reshape(n * n, n * n)
    u, s, _ = np.linalg.svd(projected.T)
    rank = int(np.sum(s > 1e-10))
    basis = u[:, :rank].T.reshape(rank, n, n)
    if lie_algebra(group) == "gl":
        basis = units
    return basis


def _per_body(leaf: Any, bodies: int) -> bool:
    """A kinetic parameter with a leading body axis (mass [N], J [N, n, n], L [N, n, n, n, n]):
    shared parameters have an even number of axes (scalar, [n, n], [n, n, n, n]), so an odd
    number with N leading is a per-body one whatever N and n are."""
    a = np.asarray(leaf)
    return a.ndim % 2 == 1 and a.shape[0] == bodies


def _body_parameters(system, bodies: int) -> list[np.ndarray]:
    """The per-body kinetic parameters [N, -1] (one array per such leaf of ``system.kinetic``)
    with the tolerance of each: bodies are equal where every row agrees to 1e-12 of the
    leaf's largest entry."""
    out = []
    for leaf in jax.tree.leaves(system.kinetic):
        if _per_body(leaf, bodies):
            a = np.asarray(leaf, dtype=float).reshape(bodies, -1)
            out.append((a, 1e-12 * max(1.0, float(np.abs(a).max()))))
    return out


def _equal_bodies(x, phi, params, k, l) -> np.ndarray:
    """[M] True where bodies k[m], l[m] have equal phi (to 1e-10) and kinetic parameters
    (:func:`_body_parameters`): pairs compared one to one, O(M)."""
    equal = np.all(np.abs(phi[k] - phi[l]) < 1e-10, axis=(-2, -1))
    for a, tolerance in params:
        equal &= np.all(np.abs(a[k] - a[l]) <= tolerance, axis=-1)
    return equal


def box_matrix(box, n: int) -> np.ndarray:
    """The cell matrix H [n, n] (columns: the box vectors) of a periodic box given as n edges
    (orthorhombic), an n x n matrix or an :class:`affinebody.space.Space` (triclinic)."""
    if isinstance(box, Space):
        if not box.periodic:
            raise ValueError("phonons need a periodic box (got free space)")
        h = box.matrix
    else:
        h = np.asarray(box, dtype=float)
        h = np.diag(h) if h.shape == (n,) else h
    if h.shape != (n, n) or not np.linalg.det(h) > 0:
        raise ValueError(f"phonons need a periodic box of n = {n} edges or an {n} x {n} cell "
                         f"matrix with det > 0 (got {np.asarray(h).tolist()})")
    return h


def _wrap(u, h) -> np.ndarray:
    """u minus the box vectors (columns of h) that bring its fractional coordinates to
    [-1/2, 1/2): the minimum image of the pairs in range."""
    f = u @ np.linalg.inv(h).T
    return (f - np.round(f)) @ h.T


def _on_torus(fractional: np.ndarray) -> np.ndarray:
    """Fractional coordinates reduced to [0, 1) (np.mod(-1e-17, 1) rounds to 1.0: made 0)."""
    f = np.mod(fractional, 1.0)
    f[f >= 1.0] = 0.0
    return f


def _periodic_tree(fractional: np.ndarray) -> cKDTree:
    """A k-d tree of points given by fractional coordinates, on the unit torus."""
    return cKDTree(_on_torus(fractional), boxsize=1.0)


def _maps_onto_itself(x, phi, box, params, shift, tree: cKDTree) -> bool:
    """Whether x -> x + shift (mod box) maps the bodies onto bodies with equal phi, inertia.

    Each shifted body's image is the nearest body on the torus of fractional coordinates (a
    k-d tree: O(N log N)), accepted where the minimum-image difference is below 1e-8 of the
    box and the two bodies are equal (:func:`_equal_bodies`). ``tree``: the bodies'
    :func:`_periodic_tree` in the box's fractional coordinates."""
    inverse = np.linalg.inv(box)

    def mapped(bodies):
        _, image = tree.query(_on_torus((x[bodies] + shift) @ inverse.T), p=np.inf)
        u = _wrap(x[image] - (x[bodies] + shift), box)
        close = np.all(np.abs(u) < 1e-8 * np.abs(box).max(), axis=-1)
        return bool(np.all(close & _equal_bodies(x, phi, params, bodies, image)))

    # a few bodies first: most candidate translations fail on them, at O(log N)
    return mapped(np.arange(min(8, len(x)))) and mapped(np.arange(len(x)))


def find_cells(system, x, phi, box) -> tuple[int, ...]:
    """The largest numbers of primitive cells along each box vector: m_j such that the
    translation by h_j / m_j (h_j the j-th box vector, :func:`box_matrix`) maps the bodies onto
    bodies with the same phi and inertia (O(N log N) per candidate m_j, a divisor of N)."""
    x, phi = np.asarray(x, float), np.asarray(phi, float)
    bodies, n = x.shape
    box = box_matrix(box, n)
    params = _body_parameters(system, bodies)
    tree = _periodic_tree(x @ np.linalg.inv(box).T)
    cells = []
    for j in range(n):
        for m in sorted((d for d in range(1, bodies + 1) if bodies % d == 0), reverse=True):
            shift = box[:, j] / m
            if m == 1 or _maps_onto_itself(x, phi, box, params, shift, tree):
                cells.append(m)
                break
    return tuple(cells)


def _sublattices(x, phi, params, a_inv) -> tuple[np.ndarray, np.ndarray]:
    """(basis [P], sublattice [N]): bodies k, b are on one sublattice where x_k - x_b is a
    lattice vector (fractional coordinates a_inv (x_k - x_b) integers to 1e-8) and the bodies
    are equal; the basis holds each sublattice's first body in index order. One periodic k-d
    tree query per sublattice: O(N log N) for a small basis."""
    bodies = len(x)
    reduced = x @ a_inv.T
    origin = _on_torus(reduced)
    tree = cKDTree(origin, boxsize=1.0)
    sublattice = -np.ones(bodies, dtype=int)
    basis: list[int] = []
    for k in range(bodies):
        if sublattice[k] >= 0:
            continue
        near = np.asarray(tree.query_ball_point(origin[k], 1e-8, p=np.inf), dtype=int)
        near = near[sublattice[near] < 0]
        members = near[_equal_bodies(x, phi, params, np.full(len(near), k), near)]
        sublattice[members] = len(basis)
        sublattice[k] = len(basis)
        basis.append(k)
    return np.asarray(basis), sublattice


@dataclass(frozen=True)
class Crystal:
    """A periodic crystal of affine bodies at its (candidate) equilibrium.

    system: the ``HamiltonianSystem``; x [N, n], phi [N, n, n]: the bodies of the periodic box
    ``box`` [n, n] (cell matrix H, columns the box vectors h_j: orthorhombic or triclinic);
    cells: primitive cells per box vector. Derived: ``vectors`` [n, n] (columns the primitive
    vectors a_j = h_j / cells_j), ``lattice`` [n] (their lengths), ``basis`` [P] (the box
    indices of the bodies of the primitive cell), ``sublattice`` [N] and ``translation``
    [N, n] (x_K = x_basis[s] + T_K with T_K a lattice vector), ``algebra`` [g, n, n] (E_a).
    """

    system: Any
    x: np.ndarray
    phi: np.ndarray
    box: np.ndarray
    cells: tuple[int, ...]
    basis: np.ndarray
    sublattice: np.ndarray
    translation: np.ndarray
    algebra: np.ndarray

    @property
    def n(self) -> int:
        return self.x.shape[1]

    @property
    def vectors(self) -> np.ndarray:
        """Primitive vectors a_j = h_j / cells_j as the columns of [n, n]."""
        return self.box / np.asarray(self.cells, dtype=float)[None, :]

    @property
    def lattice(self) -> np.ndarray:
        """Lengths |a_j| of the primitive vectors."""
        return np.linalg.norm(self.vectors, axis=0)

    @property
    def orthorhombic(self) -> bool:
        return bool(np.all(self.box == np.diag(np.diag(self.box))))

    @property
    def dof(self) -> int:
        """Degrees of freedom per body: n + dim g."""
        return self.n + len(self.algebra)

    @property
    def cell_volume(self) -> float:
        return float(abs(np.linalg.det(self.vectors)))

    @property
    def reciprocal(self) -> np.ndarray:
        """Reciprocal vectors b_j (a_i . b_j = 2 pi delta_ij) as the columns of [n, n]."""
        return 2 * np.pi * np.linalg.inv(self.vectors).T

    def fractional(self, v) -> np.ndarray:
        """Coordinates of Cartesian vectors v [..., n] in the primitive vectors."""
        return np.asarray(v) @ np.linalg.inv(self.vectors).T


def make_crystal(system, x, phi, box, cells=None) -> Crystal:
    """The :class:`Crystal` of the bodies (x, phi) in the periodic ``box``; ``cells`` (primitive
    cells per edge) is found by :func:`find_cells` when None, and checked otherwise."""
    x, phi = np.asarray(x, dtype=float), np.asarray(phi, dtype=float)
    bodies, n = x.shape
    box = box_matrix(box, n)
    if cells is None:
        cells = find_cells(system, x, phi, box)
    cells = tuple(int(c) for c in cells)
    params = _body_parameters(system, bodies)
    tree = _periodic_tree(x @ np.linalg.inv(box).T)
    for j, m in enumerate(cells):
        shift = box[:, j] / max(m, 1)
        if m < 1 or bodies % m or not _maps_onto_itself(x, phi, box, params, shift, tree):
            raise ValueError(f"phonons.cells[{j}] = {m}: the translation by box/{m} along axis "
                             f"{j} does not map the bodies onto equal bodies (drop phonons.cells "
                             f"to find the primitive cell)")
    a_inv = np.linalg.inv(box / np.asarray(cells, dtype=float)[None, :])
    basis_arr, sublattice = _sublattices(x, phi, params, a_inv)
    translation = np.round((x - x[basis_arr[sublattice]]) @ a_inv.T) @ np.linalg.inv(a_inv).T
    return Crystal(system, x, phi, box, cells, basis_arr, sublattice, translation,
                   algebra_basis(system.group, n))


def tile(crystal: Crystal, xb, phib):
    """Box configuration (x [N, n], phi [N, n, n]) from the primitive cell's (xb, phib)."""
    s = crystal.sublattice
    return xb[s] + crystal.translation, phib[s]


# --------------------------------------------------------------------------------------------
# Terms, charts and bonds


def _terms(potential) -> tuple[list, list]:
    """(pair terms, one-body terms) of a potential; ValueError for what phonons cannot use."""
    pairs, singles = [], []
    for k, term in enumerate(terms_of(potential)):
        if "translation" not in term.symmetry:
            raise ValueError(f"potential.{k} ({type(term).__name__}) depends on the centres x "
                             f"and breaks translations: a crystal has no phonons in an external "
                             f"field (remove it)")
        if isinstance(term, PairTerm):
            if term.cutoff is None or term.cutoff.variable != "r":
                raise ValueError(f"potential.{k}: phonons need a cut-off on r in every pair "
                                 f"term (set potential.{k}.r_cut)")
            pairs.append(term)
        elif isinstance(term, OneBodyTerm):
            singles.append(term)
        else:
            raise ValueError(f"potential.{k} ({type(term).__name__}) is neither a one-body nor "
                             f"a pair term of affinebody.potentials: phonons cannot split it")
    return pairs, singles


def _chart(phi0, theta, algebra):
    """phi = (Id + X + X^2 / 2) phi0, X = theta . E (second order in theta, module docstring)."""
    xmat = jnp.einsum("a,aij->ij", theta, algebra)
    n = phi0.shape[-1]
    return (jnp.eye(n) + xmat + 0.5 * xmat @ xmat) @ phi0


def bonds(crystal: Crystal, reach: float | None = None):
    """Neighbours of the primitive cell's bodies within the largest cut-off (or ``reach``, at
    most half the box): arrays (s [B], s' [B], R [B, n] lattice vector, u [B, n] =
    x_{s', R} - x_s, J [B] box index)."""
    pairs, _ = _terms(crystal.system.potential)
    if not pairs:
        return (np.zeros(0, int), np.zeros(0, int), np.zeros((0, crystal.n)),
                np.zeros((0, crystal.n)), np.zeros(0, int))
    r_cut = max(t.cutoff.r_cut for t in pairs) if reach is None else reach
    x, box, a = crystal.x, crystal.box, crystal.vectors
    ss, ts, rs, us, js = [], [], [], [], []
    for s, b in enumerate(crystal.basis):
        u = _wrap(x - x[b], box)
        dist = np.linalg.norm(u, axis=1)
        for j in np.flatnonzero(dist < r_cut):
            if j == b:
                continue
            t = crystal.sublattice[j]
            lattice_vector = a @ np.round(crystal.fractional(x[b] + u[j] - x[crystal.basis[t]]))
            ss.append(s)
            ts.append(t)
            rs.append(lattice_vector)
            us.append(u[j])
            js.append(j)
    return (np.asarray(ss, int), np.asarray(ts, int), np.asarray(rs).reshape(-1, crystal.n),
            np.asarray(us).reshape(-1, crystal.n), np.asarray(js, int))


# --------------------------------------------------------------------------------------------
# Equilibrium


def residual_forces(crystal: Crystal) -> np.ndarray:
    """Generalized forces [P, dof] on the primitive cell's bodies in the chart coordinates:
    -dV/dx and -<dV/dphi phi^T, E_a> (the component along the group): each body's bonds
    (every neighbour within the cut-off, :func:`bonds`) and its one-body terms."""
    (s, *_), pair, one = _derivatives(crystal)
    d = crystal.dof
    total = np.zeros((len(crystal.basis), d))
    if pair is not None:
        np.add.at(total, s, pair[0][:, :d])  # each pair is a bond once from either end
    if one is not None:
        total += one[0]
    return -total


def relax(crystal: Crystal, tolerance: float = 1e-10, max_steps: int = 2000) -> Crystal:
    """The crystal at the nearest minimum of V per cell over the positions and shapes of the
    primitive cell's bodies (phi_s -> expm(X_s) phi_s stays on the group; the cell is kept),
    by BFGS on the energy of the whole box; ``tolerance`` on the largest residual force."""
    from scipy.optimize import minimize

    system = crystal.system
    p, n, g = len(crystal.basis), crystal.n, len(crystal.algebra)
    x0 = jnp.asarray(crystal.x[crystal.basis])
    phi0 = jnp.asarray(crystal.phi[crystal.basis])
    algebra = jnp.asarray(crystal.algebra)
    s, shift = jnp.asarray(crystal.sublattice), jnp.asarray(crystal.translation)
    ncell = len(crystal.x) // p

    def configuration(q):
        q = q.reshape(p, n + g)
        xmat = jnp.einsum("ka,aij->kij", q[:, n:], algebra)
        return x0 + q[:, :n], expm(xmat) @ phi0

    @jax.jit
    def energy(q):
        xb, phib = configuration(q)
        return system.potential.energy(xb[s] + shift, phib[s]) / ncell

    value_and_grad = jax.jit(jax.value_and_grad(energy))

    def fun(q):
        v, gr = value_and_grad(jnp.asarray(q))
        return float(v), np.asarray(gr, dtype=float)

    result = minimize(fun, np.zeros(p * (n + g)), jac=True, method="BFGS",
                      options={"gtol": tolerance, "maxiter": max_steps})
    xb, phib = (np.asarray(a) for a in configuration(jnp.asarray(result.x)))
    x, phi = tile(crystal, xb, phib)
    f = x @ np.linalg.inv(crystal.box).T
    x = (f - np.floor(f)) @ crystal.box.T  # back into the box
    return Crystal(system, x, phi, crystal.box, crystal.cells, crystal.basis, crystal.sublattice,
                   x - x[crystal.basis[crystal.sublattice]], crystal.algebra)


def relax_cell(crystal: Crystal, tolerance: float = 1e-10, max_steps: int = 4000) -> Crystal:
    """The crystal at the nearest minimum of V per cell over the positions and shapes of the
    primitive cell's bodies *and* a stretch of the cell along the Cartesian axes (zero normal
    stress; phi_s -> expm(X_s) phi_s, H -> diag(exp(s)) H: the edges of an orthorhombic box),
    by BFGS on the energy per cell summed over
    bonds (pairs within 1.25 r_cut, at most half the box, rechecked after each round). Returns
    the crystal in the new box, with the pair terms' box replaced (ValueError when the relaxed
    box is too small for the cut-off)."""
    from scipy.optimize import minimize

    from affinebody.potentials import total_potential

    system = crystal.system
    pairs, singles = _terms(system.potential)
    p, n, g = len(crystal.basis), crystal.n, len(crystal.algebra)
    algebra = jnp.asarray(crystal.algebra)
    for _ in range(4):
        r_cut = max((t.cutoff.r_cut for t in pairs), default=0.0)
        reach = min(1.25 * r_cut, as_space(crystal.box).max_cutoff * (1 - 1e-9))
        s, t, _, u, _ = bonds(crystal, reach)
        x0 = jnp.asarray(crystal.x[crystal.basis])
        phi0 = jnp.asarray(crystal.phi[crystal.basis])
        sj, tj, uj = jnp.asarray(s), jnp.asarray(t), jnp.asarray(u)

        def configuration(z, x0=x0, phi0=phi0):
            q = z[:p * (n + g)].reshape(p, n + g)
            xmat = jnp.einsum("ka,aij->kij", q[:, n:], algebra)
            return q[:, :n], expm(xmat) @ phi0, jnp.exp(z[p * (n + g):])

        def energy(z, sj=sj, tj=tj, uj=uj, configuration=configuration, x0=x0):
            dx, phi, scale = configuration(z)
            total = 0.0
            if pairs:
                vec = scale * uj + dx[tj] - dx[sj]
                per_bond = sum(pair.bond_energies(vec, phi[sj], phi[tj]) for pair in pairs)
                total = total + 0.5 * jnp.sum(per_bond)
            for term in singles:
                total = total + term.energy(scale * x0 + dx, phi)
            return total

        value_and_grad = jax.jit(jax.value_and_grad(energy))

        def fun(z, value_and_grad=value_and_grad):
            v, gr = value_and_grad(jnp.asarray(z))
            return float(v), np.asarray(gr, dtype=float)

        result = minimize(fun, np.zeros(p * (n + g) + n), jac=True, method="BFGS",
                          options={"gtol": tolerance, "maxiter": max_steps})
        dx, phib, scale = (np.asarray(a) for a in configuration(jnp.asarray(result.x)))
        box = scale[:, None] * crystal.box
        space = as_space(box)
        new_terms = []
        for term in terms_of(system.potential):
            if isinstance(term, PairTerm):
                if term.cutoff.r_cut > space.max_cutoff * (1 + 1e-12):
                    raise ValueError(f"phonons: the relaxed box {box.tolist()} is too small for "
                                     f"the cut-off r_cut = {term.cutoff.r_cut} (at most half "
                                     f"the box): enlarge system.box")
                term = dataclasses.replace(term, box=tuple(float(b) for b in np.diag(box))
                                           if crystal.orthorhombic else space)
            new_terms.append(term)
        moved = system.replace(potential=total_potential(new_terms))
        xb = scale * crystal.x[crystal.basis] + dx
        x = xb[crystal.sublattice] + scale * crystal.translation
        f = x @ np.linalg.inv(box).T
        x = (f - np.floor(f)) @ box.T
        phi = phib[crystal.sublattice]
        before = len(s)
        crystal = Crystal(moved, x, phi, box, crystal.cells, crystal.basis, crystal.sublattice,
                          x - x[crystal.basis[crystal.sublattice]], crystal.algebra)
        system = moved
        if len(bonds(crystal, reach)[0]) == before and abs(np.log(scale)).max() < 0.1:
            break
    return crystal


# --------------------------------------------------------------------------------------------
# Kinetic metric and force constants


@functools.partial(jax.jit, compiler_options=_QUICK)
def _metric_columns(system, x, phi, algebra):
    """Hessian-vector products of T in the chart velocities: [dof (column), N, dof (row)]."""
    n = x.shape[-1]
    d = n + algebra.shape[0]

    def energy(qdot):
        xi = jnp.einsum("ka,aij,kjb->kib", qdot[:, n:], algebra, phi)
        return jnp.sum(system.kinetic.lagrangian(VelocityState(x, phi, qdot[:, :n], xi)))

    zero = jnp.zeros((x.shape[0], d))
    directions = jnp.broadcast_to(jnp.eye(d)[:, None, :], (d, x.shape[0], d))
    return jax.vmap(lambda e: jax.jvp(jax.grad(energy), (zero,), (e,))[1])(directions)


def kinetic_metric(crystal: Crystal) -> np.ndarray:
    """Blocks [P, dof, dof] of the kinetic metric M: T = 1/2 q_dot^T M q_dot at phi0 with
    v = dx/dt and xi = dphi/dt = X_dot phi0 (chart velocities; models (63)-(74)). ValueError
    when M is not positive definite (af-af (72) for n >= 2: its A Tr(Omega^2) is indefinite)."""
    system = crystal.system
    basis, bodies = crystal.basis, len(crystal.x)
    # the primitive cell's bodies only (T is a sum over bodies), with their own parameters
    kinetic = jax.tree.map(lambda leaf: np.asarray(leaf)[basis] if _per_body(leaf, bodies)
                           else leaf, system.kinetic)
    cols = np.asarray(_metric_columns(dataclasses.replace(system, kinetic=kinetic),
                                      jnp.asarray(crystal.x[basis]),
                                      jnp.asarray(crystal.phi[basis]),
                                      jnp.asarray(crystal.algebra)))
    blocks = np.transpose(cols, (1, 2, 0))
    blocks = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    smallest = float(np.linalg.eigvalsh(blocks).min())
    if not smallest > 0:
        name = type(getattr(system.kinetic, "internal", None)).__name__
        why = (" (af-af (72) is indefinite for n >= 2: A Tr(Omega^2) has both signs; choose "
               "af-is, is-af or another positive-definite model)" if name == "AffineAffine" else
               "")
        raise ValueError(f"kinetic: the kinetic metric is not positive definite (smallest "
                         f"eigenvalue {smallest:.3g}): the harmonic frequencies are undefined{why}")
    return blocks


@dataclass(frozen=True)
class ForceConstants:
    """D(k) = sum_R K[R] exp(i k . R): ``vectors`` [nR, n] (the R), ``blocks`` [nR, P dof, P dof],
    and the kinetic metric ``metric`` [P dof, P dof] (block diagonal)."""

    vectors: np.ndarray
    blocks: np.ndarray
    metric: np.ndarray
    crystal: Crystal

    def dynamical_matrix(self, k) -> np.ndarray:
        """D(k) [..., P dof, P dof] (Hermitian) for Cartesian k [..., n]."""
        k = np.asarray(k, dtype=float)
        phases = np.exp(1j * (k @ self.vectors.T))  # [..., nR]
        size = self.blocks.shape[-1]
        out = phases.reshape(-1, len(self.vectors)) @ self.blocks.reshape(len(self.vectors), -1)
        return out.reshape(k.shape[:-1] + (size, size))


@functools.partial(jax.jit, static_argnums=0)
def _pair_derivatives(terms, xa, xb, pa, pb, algebra):
    """Gradients [B, 2 dof] and Hessians [B, 2 dof, 2 dof] of the pair energies of bonds
    (a, b) in both bodies' charts.

    Forward derivatives of the closed-form pair gradients of
    :func:`affinebody.pair_kernels.energy_and_gradients` (autodiff of the scalar function f
    only, the geometry in closed form), pulled back through the chart: one Jacobian-vector
    product per chart direction, the same direction in every bond at once (the bonds are
    independent), so the compiled graph is one first derivative, not a nested second one."""
    bonds_count, n = xa.shape
    d = n + algebra.shape[0]
    x0 = jnp.stack([xa, xb], axis=1).reshape(2 * bonds_count, n)  # u = x_a - x_b: free space
    phi0 = jnp.stack([pa, pb], axis=1).reshape(2 * bonds_count, n, n)
    first, second = jnp.arange(0, 2 * bonds_count, 2), jnp.arange(1, 2 * bonds_count, 2)
    free = as_space(None)

    def configuration(q):
        q = q.reshape(2 * bonds_count, d)
        return x0 + q[:, :n], jax.vmap(_chart, (0, 0, None))(phi0, q[:, n:], algebra)

    def gradient(q):
        x, phi = configuration(q)
        gx, gphi = 0.0, 0.0
        for term in terms:
            # program "xla": differentiated below (jax.jvp), which the GPU's Pallas kernels
            # are not written for
            _, tx, tphi = energy_and_gradients(term, free, x, phi, first, second, bonds_count,
                                               program="xla")
            gx, gphi = gx + tx, gphi + tphi
        return jax.vjp(configuration, q)[1]((gx, gphi))[0]

    zero = jnp.zeros((bonds_count, 2 * d))
    directions = jnp.broadcast_to(jnp.eye(2 * d)[:, None, :], (2 * d, bonds_count, 2 * d))
    columns = jax.vmap(lambda e: jax.jvp(gradient, (zero,), (e,))[1])(directions)
    return gradient(zero), jnp.transpose(columns, (1, 2, 0))  # [B, 2 dof], [B, row, column]


@functools.partial(jax.jit, static_argnums=0, compiler_options=_QUICK)
def _one_body_derivatives(terms, x, phi, algebra):
    """Gradients [P, dof] and Hessians [P, dof, dof] of the one-body energies in the chart."""
    n = x.shape[-1]
    d = n + algebra.shape[0]

    def one_energy(q, x, phi):
        return sum(term.energy(x[None] + q[None, :n], _chart(phi, q[n:], algebra)[None])
                   for term in terms)

    zero = jnp.zeros((x.shape[0], d))
    return (jax.vmap(jax.grad(one_energy))(zero, x, phi),
            jax.vmap(jax.jacfwd(jax.grad(one_energy)))(zero, x, phi))


def _derivatives(crystal: Crystal):
    """The bonds (:func:`bonds`) and the chart derivatives of V: (bonds, pair gradients
    [B, 2 dof] and Hessians [B, 2 dof, 2 dof] or None, one-body gradients [P, dof] and
    Hessians [P, dof, dof] or None)."""
    pairs, singles = _terms(crystal.system.potential)
    algebra = jnp.asarray(crystal.algebra)
    found = bonds(crystal)
    s, _, _, u, j = found
    pair = one = None
    if len(s):
        # the bonds are padded to a power of two (at least 16) with copies of the first, and
        # the terms compiled without their box (bond displacements are already the images in
        # range): crystals of the same potential share one compiled function
        size = max(16, 1 << (len(s) - 1).bit_length())
        rows = np.concatenate([np.arange(len(s)), np.zeros(size - len(s), int)])
        xa = crystal.x[crystal.basis[s]][rows]
        terms = tuple(dataclasses.replace(term, box=None) for term in pairs)
        pair = tuple(np.asarray(a)[:len(s)] for a in _pair_derivatives(
            terms, jnp.asarray(xa), jnp.asarray(xa + u[rows]),
            jnp.asarray(crystal.phi[crystal.basis[s]][rows]), jnp.asarray(crystal.phi[j][rows]),
            algebra))
    if singles:
        one = tuple(np.asarray(a) for a in _one_body_derivatives(
            tuple(singles), jnp.asarray(crystal.x[crystal.basis]),
            jnp.asarray(crystal.phi[crystal.basis]), algebra))
    return found, pair, one


def force_constants(crystal: Crystal) -> ForceConstants:
    """The force constants K[R] (module docstring: bonds' pair Hessians with weight 1/2 per end,
    one-body Hessians on site) and the kinetic metric of ``crystal``."""
    n, d, p = crystal.n, crystal.dof, len(crystal.basis)
    (s, t, rvec, _, _), pair, one = _derivatives(crystal)
    keys = np.round(crystal.fractional(rvec)).astype(int)
    uniq = {(0,) * n: 0}
    for key in map(tuple, keys):
        uniq.setdefault(key, len(uniq))
        uniq.setdefault(tuple(-v for v in key), len(uniq))
    blocks = np.zeros((len(uniq), p, d, p, d))
    if pair is not None:
        hess = 0.25 * (pair[1] + np.swapaxes(pair[1], 1, 2))  # weight 1/2, symmetrized
        forward = np.asarray([uniq[tuple(key)] for key in keys])
        backward = np.asarray([uniq[tuple(-key)] for key in keys])
        np.add.at(blocks, (0, s, slice(None), s), hess[:, :d, :d])
        np.add.at(blocks, (0, t, slice(None), t), hess[:, d:, d:])
        np.add.at(blocks, (forward, s, slice(None), t), hess[:, :d, d:])
        np.add.at(blocks, (backward, t, slice(None), s), hess[:, d:, :d])
    if one is not None:
        blocks[0, np.arange(p), :, np.arange(p)] += one[1]
    blocks = blocks.reshape(len(uniq), p * d, p * d)
    vectors = np.zeros((len(uniq), n))
    for key, m in uniq.items():
        vectors[m] = crystal.vectors @ np.asarray(key)
    metric_blocks = kinetic_metric(crystal)
    metric = np.zeros((p * d, p * d))
    for a in range(p):
        metric[a * d:(a + 1) * d, a * d:(a + 1) * d] = metric_blocks[a]
    return ForceConstants(vectors, blocks, metric, crystal)


# --------------------------------------------------------------------------------------------
# Spectra


def signed_frequencies(omega2) -> np.ndarray:
    """omega = sqrt(omega^2), and -sqrt(-omega^2) for an unstable mode (imaginary frequency)."""
    omega2 = np.asarray(omega2)
    return np.sign(omega2) * np.sqrt(np.abs(omega2))


def _character_matrices(fc: ForceConstants) -> np.ndarray:
    """[4, P, dof, dof]: the kinetic energy of each part (translation; dilatation, shear and
    rotation of X) of a mode is u_s^H Q_c u_s summed over bodies (cross terms dropped)."""
    crystal = fc.crystal
    n, d, p = crystal.n, crystal.dof, len(crystal.basis)
    e = crystal.algebra
    eye = np.eye(n)

    def parts(xmat):
        dil = np.trace(xmat) / n * eye
        sym = 0.5 * (xmat + xmat.T)
        return dil, sym - dil, 0.5 * (xmat - xmat.T)

    proj = np.zeros((3, len(e), len(e)))  # coordinates of each part of E_b along E_a
    for b in range(len(e)):
        for c, part in enumerate(parts(e[b])):
            proj[c, :, b] = np.einsum("aij,ij->a", e, part)
    out = np.zeros((4, p, d, d))
    for a in range(p):
        m = fc.metric[a * d:(a + 1) * d, a * d:(a + 1) * d]
        out[0, a, :n, :n] = m[:n, :n]
        for c in range(3):
            out[c + 1, a, n:, n:] = proj[c].T @ m[n:, n:] @ proj[c]
    return out


@dataclass(frozen=True)
class Spectrum:
    """omega2 [nk, modes] ascending, omega (signed, :func:`signed_frequencies`), and when asked
    the eigenvectors [nk, P dof, modes] (u^H M u = 1) and ``character`` [nk, modes, 4]."""

    k: np.ndarray
    omega2: np.ndarray
    vectors: np.ndarray | None = None
    character: np.ndarray | None = None

    @property
    def omega(self) -> np.ndarray:
        return signed_frequencies(self.omega2)

    @property
    def imaginary(self) -> np.ndarray:
        return self.omega2 < 0


def _real_times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b for a real a and a complex b as two real products (no complex copy of a)."""
    return a @ b.real + 1j * (a @ b.imag)


def solve(fc: ForceConstants, k, vectors: bool = True, chunk: int = 256) -> Spectrum:
    """omega^2 of D(k) u = omega^2 M u at Cartesian k [nk, n] (Cholesky M = L L^T, then the
    Hermitian eigenproblem of L^-1 D L^-T = sum_R (L^-1 K[R] L^-T) e^{i k.R}, the reduced
    blocks formed once); with ``vectors`` the eigenvectors and characters."""
    k = np.atleast_2d(np.asarray(k, dtype=float))
    lower = np.linalg.cholesky(fc.metric)
    linv = np.linalg.inv(lower)
    size = len(fc.metric)
    reduced_blocks = (linv @ fc.blocks @ linv.T).reshape(len(fc.vectors), -1)
    q = _character_matrices(fc) if vectors else None
    crystal = fc.crystal
    p, d = len(crystal.basis), crystal.dof
    values, vecs, chars = [], [], []
    for start in range(0, len(k), chunk):
        angles = k[start:start + chunk] @ fc.vectors.T
        reduced = (np.cos(angles) @ reduced_blocks + 1j * (np.sin(angles) @ reduced_blocks))
        reduced = reduced.reshape(len(angles), size, size)
        reduced = 0.5 * (reduced + np.conj(np.swapaxes(reduced, -1, -2)))
        if not vectors:
            values.append(np.linalg.eigvalsh(reduced))
            continue
        w, v = np.linalg.eigh(reduced)
        u = _real_times(linv.T, v)
        ub = u.reshape(len(w), p, d, -1)
        energy = np.stack([np.einsum("ksim,ksim->km", np.conj(ub), _real_times(q[c][None], ub))
                           .real for c in range(len(q))], axis=-1)
        total = np.maximum(energy.sum(-1, keepdims=True), 1e-300)
        values.append(w)
        vecs.append(u)
        chars.append(energy / total)
    omega2 = np.concatenate(values)
    # round-off zeros (|omega^2| below 1e-12 of the largest at that k, e.g. exactly flat
    # Goldstone branches) are zeros, not instabilities
    scale = np.max(np.abs(omega2), axis=1, keepdims=True)
    omega2 = np.where(np.abs(omega2) <= 1e-12 * scale, 0.0, omega2)
    if not vectors:
        return Spectrum(k, omega2)
    return Spectrum(k, omega2, np.concatenate(vecs), np.concatenate(chars))


def path_labels(n: int, labels=None) -> tuple:
    """The corners of a high-symmetry path: ``labels``, or :data:`DEFAULT_PATHS` for the
    dimension ``n`` when None."""
    return tuple(DEFAULT_PATHS[min(n, 3)] if labels is None else labels)


def path(crystal: Crystal, labels=None, points: int = 50):
    """k points along the high-symmetry path ``labels`` (names of :data:`POINTS`, default
    :data:`DEFAULT_PATHS`), ``points`` per segment: (k [nk, n] Cartesian, distance [nk],
    ticks [(label, distance)])."""
    n = crystal.n
    labels = path_labels(n, labels)
    if len(labels) < 2:
        raise ValueError("phonons.path needs at least two points (e.g. ['G', 'X'])")
    corners = []
    for label in labels:
        name = "G" if label in ("Γ", "GAMMA", "Gamma") else label
        if name not in POINTS:
            raise ValueError(f"phonons.path: unknown point {label!r} (use {', '.join(POINTS)})")
        full = np.asarray(POINTS[name])
        if np.any(full[n:]):
            raise ValueError(f"phonons.path: point {label!r} is not in the Brillouin zone of "
                             f"dimension n = {n}")
        frac = full[:n]
        corners.append(crystal.reciprocal @ frac)
    ks, dist, ticks = [], [], [(labels[0], 0.0)]
    offset = 0.0
    last = len(corners) - 2
    for m, (a, b, label) in enumerate(zip(corners[:-1], corners[1:], labels[1:], strict=True)):
        t = np.linspace(0.0, 1.0, points, endpoint=m == last)
        ks.append(a + t[:, None] * (b - a))
        length = float(np.linalg.norm(b - a))
        dist.append(offset + t * length)
        offset += length
        ticks.append((label, offset))
    return np.concatenate(ks), np.concatenate(dist), ticks


def mesh(crystal: Crystal, sizes) -> tuple[np.ndarray, np.ndarray]:
    """Gamma-centred uniform mesh of the Brillouin zone, m_j points per axis, reduced by time
    reversal (D(-k) = conj D(k), so omega(-k) = omega(k)): (k [K, n], weights [K]) with the
    weights summing to prod m."""
    sizes = [int(m) for m in sizes]
    index = np.stack(np.meshgrid(*[np.arange(m) for m in sizes], indexing="ij"), -1)
    index = index.reshape(-1, len(sizes))
    flat = np.ravel_multi_index(index.T, sizes)
    partner = np.ravel_multi_index(((-index) % np.asarray(sizes)).T, sizes)
    keep = flat <= partner
    weights = np.where(flat == partner, 1.0, 2.0)[keep]
    frac = index[keep] / np.asarray(sizes, dtype=float)
    frac = frac - (frac >= 0.5)
    return frac @ crystal.reciprocal.T, weights


def density_of_states(omega, weights=None, bins: int = 400, width: float | None = None):
    """Gaussian-broadened density of states of the signed frequencies ``omega`` [nk, modes]
    with k weights (:func:`mesh`): (grid [bins], g [bins]) with integral the number of modes
    per k (imaginary frequencies appear at negative omega); ``width``: 1% of the range."""
    omega = np.atleast_2d(np.asarray(omega, dtype=float))
    weights = np.ones(len(omega)) if weights is None else np.asarray(weights, dtype=float)
    nk = float(np.sum(weights))
    flat = omega.ravel()
    lo, hi = float(min(flat.min(), 0.0)), float(flat.max())
    span = max(hi - lo, 1e-12)
    width = 0.01 * span if width is None else float(width)
    grid = np.linspace(lo - 3 * width, hi + 3 * width, bins)
    counts, edges = np.histogram(flat, bins=4 * bins, range=(grid[0], grid[-1]),
                                 weights=np.repeat(weights, omega.shape[1]))
    centres = 0.5 * (edges[1:] + edges[:-1])
    kernel = np.exp(-0.5 * ((grid[:, None] - centres[None]) / width) ** 2)
    g = kernel @ counts / (math.sqrt(2 * math.pi) * width * nk)
    return grid, g


# --------------------------------------------------------------------------------------------
# Long waves


def _translations(fc: ForceConstants) -> np.ndarray:
    crystal = fc.crystal
    n, d, p = crystal.n, crystal.dof, len(crystal.basis)
    t = np.zeros((p * d, n))
    for a in range(p):
        t[a * d:a * d + n, :] = np.eye(n)
    return t


def christoffel(fc: ForceConstants, direction, eps: float = 1e-4) -> np.ndarray:
    """Gamma(k_hat) [n, n] = Re S(eps k_hat) / eps^2 (module docstring), k_hat a unit vector; the
    error is O(eps^2) (Re S is even in k) plus round-off ~1e-16 / eps^2 relative."""
    direction = np.asarray(direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    t = _translations(fc)
    m = fc.metric
    # M-orthogonal complement of the translations
    mt = m @ t
    qfull, _ = np.linalg.qr(np.concatenate([mt, np.eye(len(m))], axis=1))
    q = qfull[:, t.shape[1]:len(m)]
    scale = eps * float(np.min(np.linalg.norm(fc.crystal.reciprocal, axis=0)))
    dk = fc.dynamical_matrix(scale * direction)
    a = t.T @ dk @ t
    b = t.T @ dk @ q
    c = q.T @ dk @ q
    # exact zero modes of the internal block (Goldstone modes of a symmetry of V, e.g. uniform
    # rotations of the shapes) decouple from the translations: the pseudo-inverse drops them
    schur = a - b @ np.linalg.pinv(c, rcond=1e-13, hermitian=True) @ np.conj(b.T)
    return np.real(schur) / scale**2


def sound_speeds(fc: ForceConstants, direction) -> np.ndarray:
    """Sound speeds [n] (ascending) along ``direction``: sqrt(eig(Gamma, T^T M T))."""
    t = _translations(fc)
    mass = t.T @ fc.metric @ t
    gamma = christoffel(fc, direction)
    lower = np.linalg.cholesky(mass)
    li = np.linalg.inv(lower)
    return signed_frequencies(np.linalg.eigvalsh(li @ gamma @ li.T))


def voigt_pairs(n: int) -> list[tuple[int, int]]:
    """Voigt order of symmetric index pairs: (0,0), (1,1), ..., then (1,2), (0,2), (0,1)."""
    diagonal = [(i, i) for i in range(n)]
    off = sorted(((i, j) for i in range(n) for j in range(i + 1, n)), key=lambda ij: -sum(ij))
    return diagonal + off


def elastic_constants(fc: ForceConstants) -> tuple[np.ndarray, float]:
    """Effective elastic constants (Voigt matrix [v, v], v = n(n+1)/2, energy / length^n) from
    the long waves: Gamma_ik(k) = V_cell A_ijkl k_j k_l, fitted to C with the minor and major
    symmetries by least squares; returns (C, residual) where the residual (relative) is 0 for a
    stress-free crystal."""
    n = fc.crystal.n
    volume = fc.crystal.cell_volume
    eye = np.eye(n)
    # S[i, k, j, l] = (A_ijkl + A_ilkj) / 2 from Gamma along e_j and e_j + e_l
    single = [christoffel(fc, eye[j]) / volume for j in range(n)]
    sym = np.zeros((n, n, n, n))
    for j in range(n):
        sym[:, :, j, j] = single[j]
        for ll in range(j + 1, n):
            both = christoffel(fc, eye[j] + eye[ll]) * 2 / volume  # k = e_j + e_l, |k|^2 = 2
            sym[:, :, j, ll] = sym[:, :, ll, j] = 0.5 * (both - single[j] - single[ll])
    pairs = voigt_pairs(n)
    index = {}
    for a, (i, j) in enumerate(pairs):
        index[(i, j)] = index[(j, i)] = a
    unknowns = [(a, b) for a in range(len(pairs)) for b in range(a, len(pairs))]
    rows, rhs = [], []
    for i in range(n):
        for k in range(n):
            for j in range(n):
                for ll in range(n):
                    row = np.zeros(len(unknowns))
                    for (p1, p2), w in ((((i, j), (k, ll)), 0.5), (((i, ll), (k, j)), 0.5)):
                        a, b = sorted((index[p1], index[p2]))
                        row[unknowns.index((a, b))] += w
                    rows.append(row)
                    rhs.append(sym[i, k, j, ll])
    coef, *_ = np.linalg.lstsq(np.asarray(rows), np.asarray(rhs), rcond=None)
    c = np.zeros((len(pairs), len(pairs)))
    for (a, b), v in zip(unknowns, coef, strict=True):
        c[a, b] = c[b, a] = v
    fitted = np.asarray(rows) @ coef
    residual = float(np.linalg.norm(fitted - rhs) / max(np.linalg.norm(rhs), 1e-300))
    return c, residual


__all__ = [
    "CHARACTERS", "DEFAULT_PATHS", "path_labels", "POINTS", "Crystal", "ForceConstants", "Spectrum",
    "algebra_basis", "bonds", "christoffel", "density_of_states", "elastic_constants",
    "find_cells", "force_constants", "kinetic_metric", "make_crystal", "mesh", "path", "relax",
    "relax_cell",
    "residual_forces", "signed_frequencies", "solve", "sound_speeds", "tile", "voigt_pairs",
    "box_matrix",
]
