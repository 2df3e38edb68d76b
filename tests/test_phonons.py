"""Lattice dynamics of affine crystals (affinebody.phonons, affinebody phonons).

Facts checked against independent derivations or methods:

- the 1D chain (n = 1, nearest neighbours) has the closed-form 2x2 D(k) derived below by hand;
- the frequencies are the peaks of the power spectra of p and of the affine spin Sigma of a
  small-amplitude NVE run of the same crystal (simulate.run: an independent method);
- the acoustic sum rule, the sound speed and the elastic constant of the chain against the
  closed form and against the stress-strain response of a finite strain of the box (energy of
  the strained box from the library's all-pairs sum, internal shape relaxed);
- omega(k) is invariant under the material affine transformations phi -> phi B of a model that
  has them, and under the square lattice's quarter turn k -> R k.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.optimize import minimize_scalar

from affinebody import kinetic, phonons
from affinebody.potentials import build_potential, total_potential
from affinebody.simulate import run
from affinebody.state import State
from affinebody.system import HamiltonianSystem

# chain: V = sum_bonds [ka/2 (r - a)^2 + kd/2 (D - a)^2 + kb/2 (M1 - 1)^2] + sum_K kc/2 (det - 1)^2
KA, KD, KB, KC, A, MASS, J = 2.0, 1.5, 0.8, 3.0, 1.0, 1.3, 0.7
BODIES = 6


def chain_potential(box):
    pair = build_potential("pair", {"expr": f"{KA / 2} * (r - {A})**2 + {KD / 2} * (D - {A})**2 "
                                            f"+ {KB / 2} * (M1 - 1)**2", "r_cut": 1.6},
                           n=1, box=box)
    dil = build_potential("dilatation", {"stiffness": KC, "form": "harmonic"}, n=1)
    return total_potential([pair, dil])


def chain_dynamical_matrix(k):
    """Closed form, derived by hand. Harmonic energy of the bond (j, j + 1) with x_j = x0_j +
    dx_j, phi_j = 1 + t_j: dr = dx_{j+1} - dx_j; D = |u| sqrt((phi_j^-2 + phi_{j+1}^-2)/2)
    gives dD = dr - a/2 (t_j + t_{j+1}); M1 = phi_{j+1}/phi_j gives dM1 = t_{j+1} - t_j (both
    orders alike); det gives t_j. With Bloch waves (X, T) e^{ikja}, e = e^{ika}, the energy per
    cell is 1/2 [ka |e-1|^2 |X|^2 + kd |(e-1) X - a/2 (1+e) T|^2 + kb |e-1|^2 |T|^2 + kc |T|^2]."""
    c, s = np.cos(k * A), np.sin(k * A)
    return np.array([[(KA + KD) * 2 * (1 - c), 1j * KD * A * s],
                     [-1j * KD * A * s, KD * A**2 / 2 * (1 + c) + 2 * KB * (1 - c) + KC]])


@pytest.fixture(scope="module")
def chain():
    box = (BODIES * A,)
    system = HamiltonianSystem(
        kinetic.KineticEnergy(kinetic.DAlembertTranslational(MASS),
                              kinetic.DAlembert(J * np.eye(1))),
        chain_potential(box), "GL+")
    x = A * np.arange(BODIES, dtype=float)[:, None]
    phi = np.ones((BODIES, 1, 1))
    crystal = phonons.make_crystal(system, x, phi, box)
    return crystal, phonons.force_constants(crystal)


def test_chain_closed_form(chain):
    crystal, fc = chain
    assert crystal.cells == (BODIES,) and len(crystal.basis) == 1 and crystal.dof == 2
    assert np.abs(phonons.residual_forces(crystal)).max() < 1e-12
    ks = np.linspace(-np.pi / A, np.pi / A, 9)
    spectrum = phonons.solve(fc, ks[:, None])
    mass = np.diag([MASS, J])
    for k, omega2, in zip(ks, spectrum.omega2, strict=True):
        exact = chain_dynamical_matrix(k)
        assert np.abs(fc.dynamical_matrix(np.array([k])) - exact).max() < 1e-10
        expected = np.sort(np.linalg.eigvals(np.linalg.solve(mass, exact)).real)
        assert np.abs(omega2 - expected).max() < 1e-10 * expected.max()
    # acoustic sum rule: one zero at Gamma, translational; the optical one is the internal mode
    gamma = phonons.solve(fc, np.zeros((1, 1)))
    assert abs(gamma.omega2[0, 0]) < 1e-12
    assert gamma.omega2[0, 1] == pytest.approx((KD * A**2 + KC) / J, rel=1e-12)
    assert gamma.character[0, 0, 0] == pytest.approx(1.0, abs=1e-12)
    assert gamma.character[0, 1, 1] == pytest.approx(1.0, abs=1e-12)  # pure dilatation (n = 1)


def test_chain_long_waves_and_finite_strain(chain):
    """Sound speed and C11 from the long waves against the closed form (Schur complement of
    the closed-form D(k) as k -> 0) and against a finite strain of the box."""
    crystal, fc = chain
    c11_exact = A * ((KA + KD) - KD**2 * A**2 / (KD * A**2 + KC))  # per length a
    speed = phonons.sound_speeds(fc, [1.0])[0]
    assert speed == pytest.approx(np.sqrt(c11_exact * A / MASS), rel=1e-7)
    voigt, residual = phonons.elastic_constants(fc)
    assert voigt[0, 0] == pytest.approx(c11_exact, rel=1e-7)
    assert residual < 1e-10

    def relaxed_energy_density(strain):
        box = (BODIES * A * (1 + strain),)
        potential = chain_potential(box)
        x = (A * (1 + strain) * np.arange(BODIES, dtype=float))[:, None]

        compiled = jax.jit(potential.energy)

        def energy(f):
            return float(compiled(x, np.full((BODIES, 1, 1), f)))

        best = minimize_scalar(energy, bracket=(0.9, 1.0, 1.1), tol=1e-12)
        return best.fun / (BODIES * A)

    h = 1e-3
    w0, wp, wm = (relaxed_energy_density(e) for e in (0.0, h, -h))
    assert (wp + wm - 2 * w0) / h**2 == pytest.approx(voigt[0, 0], rel=1e-5)


def test_diatomic_chain_two_bodies_per_cell():
    """Alternating masses m1, m2 on a chain with springs k (r - a)^2 / 2 (nearest neighbours):
    the cell found has 2 bodies, and omega^2 = k (1/m1 + 1/m2) -+ k sqrt((1/m1 + 1/m2)^2 -
    4 sin^2(k_w a) / (m1 m2)) with the period 2a (textbook closed form); the shapes (held by
    kc/2 (det - 1)^2, inertia J) give two flat branches kc / J."""
    m1, m2, spring, kc, inertia, bodies = 1.0, 2.5, 3.0, 2.0, 0.4, 8
    box = (float(bodies),)
    pair = build_potential("pair", {"expr": f"{spring / 2} * (r - 1)**2", "r_cut": 1.5}, n=1,
                           box=box)
    dil = build_potential("dilatation", {"stiffness": kc, "form": "harmonic"}, n=1)
    masses = np.where(np.arange(bodies) % 2 == 0, m1, m2)
    system = HamiltonianSystem(
        kinetic.KineticEnergy(kinetic.DAlembertTranslational(masses),
                              kinetic.DAlembert(np.full((bodies, 1, 1), inertia))),
        total_potential([pair, dil]), "GL+")
    x = np.arange(bodies, dtype=float)[:, None]
    crystal = phonons.make_crystal(system, x, np.ones((bodies, 1, 1)), box)
    assert crystal.cells == (bodies // 2,) and len(crystal.basis) == 2
    ks = np.linspace(0.0, np.pi / 2, 6)
    omega2 = phonons.solve(phonons.force_constants(crystal), ks[:, None], vectors=False).omega2
    s = 1 / m1 + 1 / m2
    root = np.sqrt(s**2 - 4 * np.sin(ks) ** 2 / (m1 * m2))
    expected = np.sort(np.stack([spring * (s - root), spring * (s + root),
                                 np.full(6, kc / inertia), np.full(6, kc / inertia)], 1), 1)
    assert np.abs(omega2 - expected).max() < 1e-10 * expected.max()


def _bloch(signal, x0, k):
    return np.einsum("tk...,k->t...", signal, np.exp(-1j * k * x0[:, 0]))


def _peaks(series, dt, count):
    """The ``count`` largest local maxima of the Hann-windowed power spectrum, refined by a
    parabola through log power (angular frequencies)."""
    window = np.hanning(len(series))
    power = np.abs(np.fft.rfft((series - series.mean()) * window)) ** 2
    omega = 2 * np.pi * np.fft.rfftfreq(len(series), dt)
    inner = np.flatnonzero((power[1:-1] > power[:-2]) & (power[1:-1] > power[2:])) + 1
    best = inner[np.argsort(power[inner])[::-1][:count]]
    out = []
    for i in best:
        a, b, c = np.log(power[i - 1:i + 2])
        out.append(omega[i] + 0.5 * (a - c) / (a - 2 * b + c) * (omega[1] - omega[0]))
    return np.sort(out)


def test_chain_frequencies_are_md_power_spectrum_peaks(chain):
    """A small-amplitude NVE run (Strang splitting) of the 6-body chain: the peaks of the power
    spectra of the Bloch projections of p and of the affine spin Sigma = phi pi at the
    commensurate k = 2 pi m / (6 a) are the harmonic frequencies."""
    crystal, fc = chain
    rng = np.random.default_rng(3)
    x0 = crystal.x
    state = State(x0 + 1e-5 * rng.standard_normal(x0.shape),
                  crystal.phi + 1e-5 * rng.standard_normal(crystal.phi.shape),
                  1e-5 * rng.standard_normal(x0.shape),
                  1e-5 * rng.standard_normal(crystal.phi.shape))
    dt, steps = 0.02, 8192
    traj = run(crystal.system, state, dt, steps, observers=())
    p = np.asarray(traj.states.p)[:, :, 0]
    spin = np.asarray(traj.states.phi @ traj.states.pi)[:, :, 0, 0]
    worst = 0.0
    for m in (1, 2, 3):
        k = 2 * np.pi * m / (BODIES * A)
        harmonic = np.sort(phonons.solve(fc, [[k]], vectors=False).omega[0])
        both = _bloch(p, x0, k).real + _bloch(spin, x0, k).real
        found = _peaks(both, dt, 2)
        worst = max(worst, float(np.max(np.abs(found - harmonic) / harmonic)))
    assert worst < 2e-3


# ---------------------------------------------------------------------------------- n = 2


def square_system(internal):
    box = (3.0, 3.0)
    pair = build_potential("pair", {"expr": "(r - 1)**2 + 0.3 * (M1 - 2)**2",
                                    "r_cut": 1.5}, n=2, box=box)
    dil = build_potential("dilatation", {"stiffness": 2.0}, n=2)
    return HamiltonianSystem(kinetic.KineticEnergy(kinetic.DAlembertTranslational(1.0), internal),
                             total_potential([pair, dil]), "GL+"), box


@pytest.fixture(scope="module")
def square():
    system, box = square_system(kinetic.IsotropicAffine(0.5, 0.1, 0.05))
    grid = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0), indexing="ij"), -1)
    x = grid.reshape(-1, 2)
    return system, x, box


def test_square_acoustic_sum_rule_and_material_affine_invariance(square):
    system, x, box = square
    phi = np.broadcast_to(np.eye(2), (9, 2, 2))
    crystal = phonons.make_crystal(system, x, phi, box)
    assert crystal.cells == (3, 3) and crystal.dof == 6
    fc = phonons.force_constants(crystal)
    rng = np.random.default_rng(0)
    ks = rng.uniform(-np.pi, np.pi, (6, 2))
    reference = phonons.solve(fc, np.concatenate([np.zeros((1, 2)), ks]))
    scale = np.abs(reference.omega2).max()
    # Gamma: the n translations are zero modes (sum rule), and so are the 3 uniform sl(2)
    # shears (Goldstone modes of the material SL invariance); the dilatation is held by det
    assert np.abs(reference.omega2[0, :5]).max() < 1e-12 * scale
    assert reference.omega2[0, 5] > 1e-3 * scale
    assert np.sum(reference.character[0, :5, 0]) == pytest.approx(2.0, abs=1e-10)
    assert reference.character[0, 5, 1] == pytest.approx(1.0, abs=1e-10)
    # long waves: omega -> 0 linearly along the acoustic branches
    small = phonons.solve(fc, [[1e-3, 0.0], [2e-3, 0.0]], vectors=False).omega[:, :2]
    assert np.allclose(small[1] / small[0], 2.0, rtol=1e-5)
    # is-af (73) and a potential in r, M_a, det are materially affine (SL, for det): phi -> phi B
    b = np.array([[1.3, 0.4], [-0.2, 0.7]])
    b = b / np.sqrt(np.linalg.det(b))
    moved = phonons.make_crystal(system, x, phi @ b, box)
    other = phonons.solve(phonons.force_constants(moved), np.concatenate([np.zeros((1, 2)), ks]))
    assert np.abs(other.omega2 - reference.omega2).max() < 1e-10 * scale
    # the quarter turn of the square lattice (the model is spatially and materially Euclidean)
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])
    turned = phonons.solve(fc, ks @ turn.T, vectors=False)
    assert np.abs(turned.omega2 - reference.omega2[1:]).max() < 1e-10 * scale


def test_square_elastic_constants_against_finite_strain():
    """V(r) = (r - 1)^2 (r - sqrt 2)^2 on the square lattice with first and second neighbours:
    V' = 0 on both shells, so the crystal is stress-free and C_ijkl = sum_bonds V''(r) r_i r_j
    r_k r_l / r^2 per cell (Born): C11 = V''(1) + V''(sqrt 2), C12 = C66 = V''(sqrt 2). And the
    energy per cell of a finitely strained infinite crystal, sum_bonds V(|(Id + e) R|), summed
    here in numpy, gives the same constants by central differences."""
    box = (4.0, 4.0)
    root2 = np.sqrt(2.0)
    pair = build_potential("pair", {"expr": "(r - 1)**2 * (r - sqrt(2))**2", "r_cut": 1.6},
                           n=2, box=box)
    system = HamiltonianSystem(
        kinetic.KineticEnergy(kinetic.DAlembertTranslational(1.0), kinetic.DAlembert(np.eye(2))),
        pair, "GL+")
    x = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij"), -1).reshape(-1, 2)
    crystal = phonons.make_crystal(system, x, np.broadcast_to(np.eye(2), (16, 2, 2)), box)
    voigt, residual = phonons.elastic_constants(phonons.force_constants(crystal))
    second = 2 * (root2 - 1) ** 2
    assert residual < 1e-6
    assert np.allclose(voigt, [[2 * second, second, 0], [second, 2 * second, 0],
                               [0, 0, second]], rtol=0, atol=1e-7)

    bonds = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])

    def w(strain):
        r = np.linalg.norm(bonds @ (np.eye(2) + strain).T, axis=1)
        return np.sum((r - 1) ** 2 * (r - root2) ** 2)

    h = 1e-4
    strains = {0: np.array([[1.0, 0], [0, 0]]), 1: np.array([[0, 0], [0, 1.0]]),
               2: np.array([[0, 0.5], [0.5, 0]])}  # Voigt: engineering shear gamma = 2 e_xy
    finite = np.zeros((3, 3))
    for a in range(3):
        for b in range(3):
            e1, e2 = strains[a] * h, strains[b] * h
            finite[a, b] = (w(e1 + e2) - w(e1 - e2) - w(e2 - e1) + w(-e1 - e2)) / (4 * h * h)
    assert np.allclose(voigt, finite, rtol=0, atol=1e-6)


def test_rigid_rotors_on_so2_closed_form():
    """Group SO(2): phi = rot(alpha), the chart theta = sqrt(2) alpha along E = [[0, -1], [1, 0]]
    / sqrt(2). V = sum_bonds (r - 1)^2 - c K1 with K1 = Tr(phi_K^T phi_L) = 2 cos(alpha_K -
    alpha_L): its gradient in GL is not zero at phi = Id (constraint forces), so the chart's
    curvature term matters. By hand: c/2 dtheta^2 per bond, T = J/2 theta_dot^2 (d'Alembert,
    isotropic J), so omega_rot^2 = 2 c sum_j (1 - cos k_j) / J; the springs give
    omega^2 = 4 (1 - cos k_j) / m for the x_j polarization."""
    c, inertia = 0.6, 0.3
    box = (3.0, 3.0)
    pair = build_potential("pair", {"expr": f"(r - 1)**2 - {c} * K1", "r_cut": 1.3}, n=2, box=box)
    system = HamiltonianSystem(
        kinetic.KineticEnergy(kinetic.DAlembertTranslational(1.0),
                              kinetic.DAlembert(inertia * np.eye(2))), pair, "SO")
    x = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0), indexing="ij"), -1).reshape(-1, 2)
    crystal = phonons.make_crystal(system, x, np.broadcast_to(np.eye(2), (9, 2, 2)), box)
    assert crystal.dof == 3 and np.abs(phonons.residual_forces(crystal)).max() < 1e-12
    ks = np.random.default_rng(1).uniform(-np.pi, np.pi, (5, 2))
    spectrum = phonons.solve(phonons.force_constants(crystal), ks)
    expected = np.sort(np.stack([4 * (1 - np.cos(ks[:, 0])), 4 * (1 - np.cos(ks[:, 1])),
                                 2 * c * np.sum(1 - np.cos(ks), axis=1) / inertia], 1), axis=1)
    assert np.abs(spectrum.omega2 - expected).max() < 1e-10 * expected.max()
    rotational = np.argmax(spectrum.character[..., 3], axis=1)
    assert np.all(spectrum.character[np.arange(5), rotational, 3] > 1 - 1e-10)


def test_kinetic_metric_of_the_bi_tensor_models():
    """In the spatial chart xi = X phi0 the affine velocity is Omega = xi phi0^-1 = X for every
    phi0, so r-af (71) has the metric R (as an n^2 x n^2 matrix) at any shape; l-af (70) has L
    at phi0 = Id (Omega_hat = phi0^-1 X phi0 = X there)."""
    rng = np.random.default_rng(5)
    a = rng.standard_normal((4, 4))
    tensor = (a @ a.T + 4 * np.eye(4)).reshape(2, 2, 2, 2)
    x = np.zeros((1, 2))
    phi0 = np.array([[[1.2, 0.3], [-0.1, 0.8]]])
    for model, phi, name in ((kinetic.RightInvariant(tensor), phi0, "r-af"),
                             (kinetic.LeftInvariant(tensor), np.eye(2)[None], "l-af")):
        system = HamiltonianSystem(kinetic.KineticEnergy(kinetic.DAlembertTranslational(2.0),
                                                         model), None, "GL+")
        crystal = phonons.make_crystal(system, x, phi, (3.0, 3.0))
        metric = phonons.kinetic_metric(crystal)[0]
        assert np.allclose(metric[2:, 2:], tensor.reshape(4, 4), atol=1e-12), name
        assert np.allclose(metric[:2, :2], 2.0 * np.eye(2), atol=1e-14)
        assert np.allclose(metric[:2, 2:], 0.0, atol=1e-14)


def test_af_af_and_non_equilibrium_are_refused(square, tmp_path):
    system, x, box = square
    affine = system.replace(kinetic=kinetic.KineticEnergy(kinetic.DAlembertTranslational(1.0),
                                                          kinetic.AffineAffine(0.5, 0.1)))
    crystal = phonons.make_crystal(affine, x, np.broadcast_to(np.eye(2), (9, 2, 2)), box)
    with pytest.raises(ValueError, match="af-af"):
        phonons.kinetic_metric(crystal)
    config = tmp_path / "c.toml"
    config.write_text(CHAIN_CONFIG.replace("box = [4.4]\n", ""), encoding="utf-8")
    result = CliRunner().invoke(_main(), ["phonons", str(config), "--no-plot"])
    assert result.exit_code == 1
    assert "phonons need a periodic box: set system.box" in result.output


def _main():
    from affinebody.cli import main

    return main


CHAIN_CONFIG = """
[system]
n = 1
bodies = 4
box = [4.4]

[kinetic]
internal = "af-is"
I = 0.5
A = 0.0

[[potential]]
kind = "morse"
depth = 1.0
alpha = 2.0
r0 = 1.0
r_cut = 1.5

[[potential]]
kind = "dilatation"
stiffness = 2.0
volume = 1.2

[initial]
generator = "lattice"
spacing = 1.1

[run]
dt = 0.01
steps = 1

[phonons]
relax_cell = true
points = 5
mesh = [8]
"""


def test_cli_refuses_a_non_equilibrium_and_relaxes_it(tmp_path):
    """det phi = 1 is not the minimum of the dilatation potential with volume 1.2: refused with
    the residual force; with --relax (and phonons.relax_cell) the shapes go to det = 1.2 and the
    stretched cell (spacing 1.1) to the Morse minimum r0 = 1, where the closed forms hold."""
    config = tmp_path / "c.toml"
    config.write_text(CHAIN_CONFIG, encoding="utf-8")
    result = CliRunner().invoke(_main(), ["phonons", str(config), "--no-plot"])
    assert result.exit_code == 1 and "not an equilibrium (largest residual force" in result.output
    result = CliRunner().invoke(_main(), ["phonons", str(config), "--json", "--no-plot", "--relax",
                                          "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    omega, k = np.asarray(doc["omega"]), np.asarray(doc["k"])
    assert k.shape == (5, 1) and omega.shape == (5, 2)
    assert np.all(np.diff(omega, axis=1) >= 0) and k[-1, 0] == pytest.approx(np.pi)
    # Morse chain: acoustic omega(k) = 2 sqrt(V''/m) |sin(k a / 2)| with V'' = 2 depth alpha^2;
    # internal: V = s/2 ln(det/v0)^2 and T = I/2 (xi/phi)^2 in n = 1, so omega^2 = s / I
    acoustic = 2 * np.sqrt(8.0) * np.abs(np.sin(k[:, 0] / 2))
    expected = np.sort(np.stack([acoustic, np.full(5, np.sqrt(2.0 / 0.5))], axis=1), axis=1)
    assert np.allclose(omega, expected, rtol=1e-9, atol=1e-7)
    assert np.asarray(doc["character"]["shares"]).shape == (5, 2, 4)
    assert doc["crystal"]["relaxed"] and doc["crystal"]["residual_force"] < 1e-8
    assert doc["crystal"]["lattice"] == pytest.approx([1.0], rel=1e-8)
    assert (tmp_path / "out" / "phonons.json").exists()


@pytest.mark.parametrize("flags,named", [
    (["--mesh", "99999999999"], "phonons.mesh = [99999999999] (or --mesh) needs about"),
    (["--points", "10000000000"], "--points must be between 2 and 100000 (got 10000000000)"),
])
def test_cli_refuses_a_path_or_mesh_beyond_memory_in_one_line(tmp_path, flags, named):
    """A DOS mesh of 10^11 points (found by fuzzing the CLI: a MemoryError as an internal
    error after the relaxation) is refused with the estimate and what is available; a path of
    10^10 points per segment by the bound phonons.points has (the flag had none); the
    estimate of the chain's default document is a few kB, linear in the points."""
    from affinebody.cli.phonons import k_points_bytes

    config = tmp_path / "c.toml"
    config.write_text(CHAIN_CONFIG, encoding="utf-8")
    result = CliRunner().invoke(_main(), ["phonons", str(config), "--no-plot", "--relax",
                                          "-o", str(tmp_path / "out"), *flags])
    message = result.stderr.strip()
    assert result.exit_code == 1 and "\n" not in message, message
    assert message.startswith(f"config error: {named}"), message
    assert not (tmp_path / "out" / "phonons.json").exists()
    crystal = SimpleNamespace(basis=[0], dof=2, n=1)
    assert sum(k_points_bytes(crystal, 5, [8])) < 1e4
    assert np.allclose(k_points_bytes(crystal, 10, [16]), 2 * np.array(k_points_bytes(crystal, 5,
                                                                                    [8])))


# ---------------------------------------------------------------- an oblique (triangular) lattice


def triangular_system(box):
    """Triangular crystal (spacing 1, 6 neighbours within r_cut = 1.25), every internal branch
    held: V = sum_bonds [(r - 1)^2 - c K1] + sum_K [3 c trG + (det - 1)^2] (the one-body 3 c
    trG balances the 6 bonds' -c K1 at phi = Id, so the pair part of the shapes is
    c/2 |phi_K - phi_L|^2); af-is internal kinetic energy."""
    import dataclasses

    pair = build_potential("pair", {"expr": "(r - 1)**2 - 0.5 * K1", "r_cut": 1.25}, n=2)
    pair = dataclasses.replace(pair, box=box)  # edges or a triclinic Space
    one = build_potential("one-body", {"expr": "1.5 * trG + (det - 1)**2"}, n=2)
    return HamiltonianSystem(kinetic.KineticEnergy(kinetic.DAlembertTranslational(1.0),
                                                   kinetic.IsotropicAffine(0.5, 0.1, 0.05)),
                             total_potential([pair, one]), "GL+")


def triangular_crystal():
    """The 9 bodies of the triangular lattice in its own oblique box H = 3 [a1 a2]."""
    from affinebody.space import triclinic

    a1, a2 = np.array([1.0, 0.0]), np.array([0.5, np.sqrt(3) / 2])
    box = triclinic(3 * np.stack([a1, a2], axis=1))
    sites = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0), indexing="ij"), -1)
    x = sites.reshape(-1, 2) @ np.stack([a1, a2])
    phi = np.broadcast_to(np.eye(2), (9, 2, 2))
    system = triangular_system(box)
    return system, phonons.make_crystal(system, x, phi, box), box


def test_triangular_lattice_in_an_oblique_box():
    """The triangular lattice (spacing 1) in its own oblique box, H = 3 [a1 a2] with a1 = (1, 0),
    a2 = (1/2, sqrt 3/2): one body per primitive cell. Checked against independent methods:
    the Bloch sum of the Hessian of the whole box's energy (the all-pairs sum with the
    triclinic minimum image, reverse-mode gradient, central finite differences); the same
    lattice as 2 bodies per cell of a rectangular box (the spectrum folds: omega_rect(k) =
    omega(k) and omega(k + G) with G = (0, 2 pi / sqrt 3)); the acoustic sum rule; and the
    elastic isotropy of a six-fold lattice (C11 = C22, C66 = (C11 - C12) / 2)."""
    system, crystal, box = triangular_crystal()
    x, phi = crystal.x, crystal.phi
    a2 = np.array([0.5, np.sqrt(3) / 2])
    assert crystal.cells == (3, 3) and len(crystal.basis) == 1 and not crystal.orthorhombic
    assert np.abs(phonons.residual_forces(crystal)).max() < 1e-12
    fc = phonons.force_constants(crystal)

    # whole-box Hessian in the chart coordinates by finite differences of the gradient
    algebra = crystal.algebra
    d = crystal.dof

    def energy(q):
        q = q.reshape(9, d)
        xmat = jax.numpy.einsum("ka,aij->kij", q[:, 2:], algebra)
        eye = jax.numpy.eye(2)
        return system.potential.energy(x + q[:, :2], (eye + xmat + 0.5 * xmat @ xmat) @ phi)

    h = 1e-4
    steps = h * np.eye(9 * d)
    gradients = np.asarray(jax.jit(jax.vmap(jax.grad(energy)))(np.concatenate([steps, -steps])))
    hessian = ((gradients[:9 * d] - gradients[9 * d:]) / (2 * h)).T.reshape(9, d, 9, d)
    reciprocal = 2 * np.pi * np.linalg.inv(box.matrix).T
    scale = np.abs(hessian).max()
    for m in ((0, 0), (1, 0), (1, 2), (2, 1)):
        k = reciprocal @ np.asarray(m, dtype=float)
        phases = np.exp(1j * (x - x[0]) @ k)
        bloch = np.einsum("l,ilj->ij", phases, hessian[0])  # D(k) = sum_L K_0L e^{ik.x_L0}
        assert np.abs(fc.dynamical_matrix(k) - bloch).max() < 1e-6 * scale, m

    # acoustic sum rule at Gamma, and the folding into the rectangular box's zone
    rng = np.random.default_rng(2)
    ks = rng.uniform(-3.0, 3.0, (5, 2))
    oblique = phonons.solve(fc, np.concatenate([np.zeros((1, 2)), ks]))
    top = np.abs(oblique.omega2).max()
    # Gamma: the 2 translations and the uniform isochoric shape changes (for a uniform phi the
    # bonds' -c K1 cancels the 3 c trG, leaving (det - 1)^2: rotation and 2 shears free) are
    # the zero modes, the uniform dilatation is not; the translations are 2 of those 5
    assert np.abs(oblique.omega2[0, :5]).max() < 1e-12 * top
    assert oblique.omega2[0, 5] > 1e-3 * top
    assert np.sum(oblique.character[0, :5, 0]) == pytest.approx(2.0, abs=1e-10)
    rect_box = (3.0, 2 * np.sqrt(3))
    corners = np.stack(np.meshgrid(np.arange(3.0), np.sqrt(3) * np.arange(2.0),
                                   indexing="ij"), -1).reshape(-1, 2)
    rect_sites = np.concatenate([corners, corners + a2])
    rect = phonons.make_crystal(triangular_system(rect_box), rect_sites,
                                np.broadcast_to(np.eye(2), (12, 2, 2)), rect_box)
    assert rect.orthorhombic and rect.cells == (3, 2) and len(rect.basis) == 2
    folded = phonons.solve(phonons.force_constants(rect), ks, vectors=False).omega2
    shifted = phonons.solve(fc, ks + np.array([0.0, 2 * np.pi / np.sqrt(3)]), vectors=False)
    expected = np.sort(np.concatenate([oblique.omega2[1:], shifted.omega2], axis=1), axis=1)
    assert np.abs(folded - expected).max() < 1e-10 * top

    # six-fold symmetry: the long waves of a triangular lattice are isotropic
    voigt, residual = phonons.elastic_constants(fc)
    assert residual < 1e-8
    assert voigt[0, 0] == pytest.approx(voigt[1, 1], rel=1e-8)
    assert voigt[2, 2] == pytest.approx((voigt[0, 0] - voigt[0, 1]) / 2, rel=1e-8)


def test_triangular_md_power_spectrum_peaks_in_2d():
    """A small-amplitude NVE run (Strang splitting) of the 9-body triangular crystal
    (:func:`triangular_crystal`, every internal branch held). At the commensurate k the peaks
    of the summed power spectra of the Bloch projections of p (2 components) and of the affine
    spin Sigma = phi pi (4) are the distinct harmonic frequencies, and no other peak carries
    weight."""
    system, crystal, _ = triangular_crystal()
    x, phi = crystal.x, crystal.phi
    assert np.abs(phonons.residual_forces(crystal)).max() < 1e-12
    fc = phonons.force_constants(crystal)
    rng = np.random.default_rng(3)
    state = State(x + 1e-5 * rng.standard_normal(x.shape),
                  phi + 1e-5 * rng.standard_normal(phi.shape),
                  1e-5 * rng.standard_normal(x.shape), 1e-5 * rng.standard_normal(phi.shape))
    dt, steps = 0.04, 4096
    traj = run(system, state, dt, steps, observers=())
    spin = np.asarray(traj.states.phi @ traj.states.pi).reshape(steps + 1, 9, 4)
    signals = np.concatenate([np.asarray(traj.states.p), spin], axis=2)
    omega = 2 * np.pi * np.fft.rfftfreq(steps + 1, dt)
    for m in ((1, 0), (1, 2)):
        k = crystal.reciprocal @ np.asarray(m, dtype=float) / 3
        harmonic = np.sort(phonons.solve(fc, [k], vectors=False).omega[0])
        distinct = harmonic[np.concatenate([[True], np.diff(harmonic) > 1e-6 * harmonic[-1]])]
        bloch = np.einsum("tkc,k->tc", signals, np.exp(-1j * x @ k))
        parts = np.concatenate([bloch.real, bloch.imag], axis=1)
        window = np.hanning(len(parts))[:, None]
        spectra = np.abs(np.fft.rfft((parts - parts.mean(0)) * window, axis=0)) ** 2
        power = np.sum(spectra / spectra.sum(0), axis=1)
        inner = np.flatnonzero((power[1:-1] > power[:-2]) & (power[1:-1] > power[2:])) + 1
        ranked = inner[np.argsort(power[inner])[::-1]]
        found = []
        for i in ranked[:len(distinct)]:
            a, b, c = np.log(power[i - 1:i + 2])
            found.append(omega[i] + 0.5 * (a - c) / (a - 2 * b + c) * (omega[1] - omega[0]))
        assert np.abs(np.sort(found) - distinct).max() < 2e-3 * distinct.max(), m
        assert power[ranked[len(distinct)]] < 1e-3 * power[ranked[:len(distinct)]].min(), m


def test_cells_and_sublattices_found_in_n_log_n_match_the_definition():
    """find_cells / make_crystal (periodic k-d tree, O(N log N)) against the definition checked
    pair by pair (O(N^2), written here): a 3D crystal with a 2-body basis of different inertia
    and shape in an oblique box of 4 x 3 x 2 primitive cells, its bodies shuffled. The largest
    translations h_j / m_j that map bodies onto equal bodies are found, every body's sublattice
    differs from its basis body by a lattice vector with equal phi and inertia; one body with a
    changed inertia leaves no translation (cells 1, 1, 1; every body its own sublattice)."""
    rng = np.random.default_rng(5)
    a = np.array([[1.0, 0.3, 0.1], [0.0, 1.1, 0.2], [0.0, 0.0, 0.9]])  # primitive vectors
    cells = np.array([4, 3, 2])
    box = a * cells[None, :]
    offsets = np.array([[0.0, 0.0, 0.0], [0.4, 0.5, 0.3]])
    shapes = np.stack([np.eye(3), np.eye(3) + 0.1 * rng.standard_normal((3, 3))])
    grid = np.stack(np.meshgrid(*(np.arange(c) for c in cells), indexing="ij"), -1)
    lattice = grid.reshape(-1, 3) @ a.T
    x = np.concatenate([lattice + a @ o for o in offsets])
    phi = np.concatenate([np.broadcast_to(s, (len(lattice), 3, 3)) for s in shapes])
    inertia = np.concatenate([np.full(len(lattice), 0.7), np.full(len(lattice), 1.3)])
    order = rng.permutation(len(x))
    x, phi, inertia = x[order], phi[order], inertia[order]

    def system_of(inertia):
        return HamiltonianSystem(
            kinetic.KineticEnergy(kinetic.DAlembertTranslational(np.ones(len(x))),
                                  kinetic.DAlembert(inertia[:, None, None] * np.eye(3))),
            None, "GL+")

    def maps_onto_itself(shift, inertia):  # the definition, every pair of bodies
        f = (x[None, :] - x[:, None] - shift) @ np.linalg.inv(box).T
        close = np.all(np.abs(f - np.round(f)) < 1e-9, -1)
        equal = (np.all(np.abs(phi[None] - phi[:, None]) < 1e-10, (-2, -1))
                 & (np.abs(inertia[None] - inertia[:, None]) < 1e-12))
        return bool(np.all(np.any(close & equal, axis=1)))

    def brute_cells(inertia):
        return tuple(max(m for m in range(1, len(x) + 1) if len(x) % m == 0
                         and (m == 1 or maps_onto_itself(box[:, j] / m, inertia)))
                     for j in range(3))

    crystal = phonons.make_crystal(system_of(inertia), x, phi, box)
    assert crystal.cells == brute_cells(inertia) == tuple(cells)
    assert len(crystal.basis) == 2
    for k in range(len(x)):
        b = crystal.basis[crystal.sublattice[k]]
        f = np.linalg.solve(a, x[k] - x[b])
        assert np.abs(f - np.round(f)).max() < 1e-9
        assert np.array_equal(phi[k], phi[b]) and inertia[k] == inertia[b]
        assert np.allclose(x[b] + crystal.translation[k], x[k], atol=1e-12)
    defect = inertia.copy()
    defect[7] *= 1.01
    broken = phonons.make_crystal(system_of(defect), x, phi, box)
    assert broken.cells == brute_cells(defect) == (1, 1, 1)
    assert len(broken.basis) == len(x)


def test_a_crystal_whose_force_constants_overflow_is_refused_in_one_line(tmp_path):
    """A dilatation stiffness of 1e308 (the crystal of the phonons tutorial; found by fuzzing
    the CLI): its second derivatives overflow, LAPACK cannot diagonalise, and the command said
    only 'Eigenvalues did not converge' after nine overflow warnings: one line now, saying
    why."""
    config = tmp_path / "crystal.toml"
    config.write_text(TUTORIAL_CRYSTAL.replace("stiffness = 5.0", "stiffness = 1e308"),
                      encoding="utf-8")
    result = CliRunner().invoke(_main(), ["phonons", str(config), "--no-plot",
                                          "-o", str(tmp_path / "out")])
    message = result.stderr.strip()
    assert result.exit_code == 1 and "\n" not in message, message
    assert "could not be diagonalised" in message and "too large" in message, message


#: The crystal of docs/tutorials/phonons.md (16 bodies of the demo's potential, relaxed).
TUTORIAL_CRYSTAL = """
[system]
n = 2
bodies = 16
box = [4.0, 4.0]
[kinetic]
internal = "af-is"
I = 0.5
A = 0.1
B = 0.05
[[potential]]
kind = "morse"
depth = 1.0
alpha = 3.0
r0 = 1.0
r_cut = 1.5
[[potential]]
kind = "pair"
expr = "0.5 * exp(-D**2 / 4) * (M1 - 2)**2"
r_cut = 1.5
[[potential]]
kind = "dilatation"
stiffness = 5.0
[[potential]]
kind = "elastic"
lam = 0.5
mu = 1.0
[initial]
generator = "lattice"
spacing = 1.0
shape = [4, 4]
[run]
dt = 0.01
steps = 1
[phonons]
relax = true
points = 5
mesh = [4, 4]
"""
