"""A worked example of paper §1: one affine body's tensors, invariants and two-polar coordinates.

``affinebody kinematics-demo`` prints it; every line states a relation of the paper and the
numbers that show it holds for a concrete body.
"""

from __future__ import annotations

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from affinebody import deformation, momenta, mutual, polar, velocities
from affinebody.inertia import from_constituents


def _fmt(a) -> str:
    return np.array2string(np.asarray(a), precision=4, suppress_small=True, separator=", ")


def print_worked_example(console: Console | None = None) -> None:
    """Print the worked example of one 3D affine body (and a neighbour) to ``console``."""
    console = console or Console()

    def say(text: str) -> None:
        console.print(text, markup=False, highlight=False)

    # A "molecule" of four atoms: M and J from its constituents, eq. (8).
    masses = np.array([1.0, 1.0, 2.0, 0.5])
    atoms = np.array([[0.5, 0.0, 0.0], [-0.5, 0.1, 0.0], [0.0, -0.3, 0.4], [0.1, 0.6, -0.7]])
    total_mass, inertia, centre = from_constituents(masses, atoms)
    phi = np.array([[1.2, 0.3, 0.0], [-0.1, 0.9, 0.2], [0.05, 0.0, 1.1]])
    xi = np.array([[0.0, 0.2, 0.0], [-0.2, 0.1, 0.0], [0.0, 0.0, -0.1]])
    pi = inertia @ xi.T  # d'Alembert Legendre map pi = J xi^T, eq. (51)
    psi = np.array([[1.0, 0.1, 0.0], [0.0, 1.1, 0.0], [0.0, 0.0, 0.95]])
    x_k, x_l = np.zeros(3), np.array([1.5, 0.2, -0.1])

    console.rule("[bold]affinebody: kinematics of an affinely-rigid body (paper §1)")
    say(f"M = {float(total_mass):.4g}, centre of mass = {_fmt(centre)}  (8)")
    say(f"J (about the centre) =\n{_fmt(inertia)}  (8), (9)")
    say(f"phi =\n{_fmt(phi)}   det phi = {np.linalg.det(phi):.6f}")

    table = Table(title="Deformation tensors and invariants")
    table.add_column("quantity")
    table.add_column("value")
    table.add_column("paper")
    table.add_row("Green G = phi^T phi", escape(_fmt(deformation.green_tensor(phi))), "(11)")
    table.add_row("Cauchy C = phi^-T phi^-1", escape(_fmt(deformation.cauchy_tensor(phi))), "(11)")
    table.add_row("Lagrange strain E", escape(_fmt(deformation.lagrange_strain(phi))), "(32)")
    table.add_row("K_a = Tr G^a", escape(_fmt(deformation.trace_invariants(phi))), "(17)")
    table.add_row("eigenvalues of G", escape(_fmt(deformation.green_eigenvalues(phi))), "(18)")
    invariants = deformation.characteristic_invariants(phi)
    table.add_row("I_p (char. poly.)", escape(_fmt(invariants)), "(19)")
    console.print(table)

    tp = polar.two_polar(phi)
    rebuilt = polar.from_two_polar(*tp)
    console.print("[bold]Two-polar decomposition[/] phi = L diag(exp q) R^T (last section)")
    say(f"q = {_fmt(tp.q)}, Q = exp q = {_fmt(np.exp(tp.q))}")
    say(f"det L = {np.linalg.det(tp.L):+.3f}, det R = {np.linalg.det(tp.R):+.3f}, "
                  f"|phi - L D R^T| = {np.max(np.abs(rebuilt - phi)):.1e}")
    say(f"Haar density |det phi|^-3 = {float(polar.haar_density(phi)):.6f}  (91); "
                  f"prod sinh|q_a - q_b| = {float(polar.two_polar_haar_density(tp.q)):.6f}")

    omega = velocities.spatial_affine_velocity(phi, xi)
    omega_hat = velocities.comoving_affine_velocity(phi, xi)
    sigma = momenta.affine_spin(phi, pi)
    sigma_hat = momenta.comoving_affine_spin(phi, pi)
    console.print("[bold]Affine velocity and affine spin[/] (34), (45), (46)")
    say(f"Tr(Sigma Omega) = {float(np.trace(sigma @ omega)):.12f}")
    say(f"Tr(Sigma_hat Omega_hat) = {float(np.trace(sigma_hat @ omega_hat)):.12f}")
    say(f"Tr(pi xi) = {float(np.trace(pi @ xi)):.12f}")
    say(f"spin S = Sigma - Sigma^T =\n{_fmt(momenta.spin(sigma))}  (49)")

    console.print("[bold]A neighbour psi[/]: mutual invariants (28), (30), affine distance (75)")
    a = np.array([[2.0, 0.5, 0.0], [0.0, 0.7, 0.3], [0.1, 0.0, 1.4]])  # any A in GL(3)
    say(f"K_a[psi, phi] = {_fmt(mutual.mutual_trace_invariants(psi, phi))}")
    moved = mutual.affine_invariants(a @ psi, a @ phi)
    say(f"M_a[psi, phi] = {_fmt(mutual.affine_invariants(psi, phi))}")
    say(f"M_a[A psi, A phi] = {_fmt(moved)}  (31: affinely invariant)")
    d = mutual.affine_distance(x_k, psi, x_l, phi)
    d_moved = mutual.affine_distance(a @ x_k, a @ psi, a @ x_l, a @ phi)
    say(f"D = {float(d):.12f}; after the affine map A: {float(d_moved):.12f}  (76)")
    volume = float(mutual.relative_volume(psi, phi))
    say(f"relative volume det Gamma[psi, phi] = {volume:.6f}  (79)")


__all__ = [
    "print_worked_example"
]
