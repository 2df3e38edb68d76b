"""Time evolution of an n = 3 wave packet in the SO(3) x SO(3) sector (0, 0)
(quantum/evolution3.py, docs/quantum-transitions.md): in the harmonic potential the mean of
Tr G follows its closed-form (Heisenberg) orbit, with the initial values and the energy of the
packet computed by an independent quadrature; norm and energy conserved to round-off; the
distance to the classical orbit shrinks with hbar (harmonic, closed form; anharmonic, against
the simulator); the Fourier lines of the survival probability at level spacings."""

import json
import textwrap
from functools import cache
from itertools import permutations

import numpy as np
import pytest

from affinebody.config import build, parse_config
from affinebody.quantum.evolution import spectrum_lines
from affinebody.quantum.evolution3 import evolve3, scalar_sector3
from affinebody.quantum.levels import Settings, level_starts
from affinebody.simulate import run

Q0 = np.array([1.5, 0.9, 0.3])  # phi = diag(Q0), pi = diag(P0)
P0 = np.array([0.0, 0.2, -0.1])
TIMES = np.linspace(0.0, 6.4, 161)  # the frames of the simulator (dt = 0.005, every 8)
RUNS = ((1.0, 12), (0.5, 16))  # (hbar, polynomial degree)
ANHARMONIC = "0.5*trG + 0.02*trG**2"


def harmonic(Q):
    return 0.5 * np.sum(Q * Q, -1)


def anharmonic(Q):
    r2 = np.sum(Q * Q, -1)
    return 0.5 * r2 + 0.02 * r2 * r2


def chamber(D):
    """Signed singular values (Q1 >= Q2 >= |Q3|, sign of det on Q3) of diag(D) [T, 3]."""
    Q = np.sort(np.abs(D), -1)[:, ::-1].copy()
    Q[:, 2] *= np.sign(np.prod(D, -1))
    return Q


@pytest.fixture(scope="module")
def evolutions():
    out = {}
    for name, V in (("harmonic", harmonic), ("anharmonic", anharmonic)):
        for hbar, degree in RUNS:
            w = np.sqrt(hbar / 2)
            # the oscillator length as the scale (the variational one, narrower for the
            # quartic term, does not hold the packet); nested check at degree - 2 as the CLI
            settings = Settings(basis_size=degree, scale=np.sqrt(hbar), check_shrink=2)
            sector = scalar_sector3("dalembert", V, hbar, settings=settings,
                                    reach=float(np.linalg.norm(Q0)) + 8 * w)
            out[name, hbar] = (sector, evolve3(sector, Q0, P0, w, TIMES, hbar))
    return out


@cache
def packet_moments(hbar: float) -> dict:
    """<Tr G>, <D> = <phi.pi + pi.phi>, the kinetic energy <T> and <V> of both potentials for
    the W-symmetrised Gaussian at t = 0, from its closed-form gradient on a product
    Gauss-Legendre rule of our own over the chamber (Q1 = r, Q2 = r s, Q3 = r s t;
    dQ = r^2 s dr ds dt; measure prod (Q_a^2 - Q_b^2)): <D> = 2 Re <psi| -i hbar Q.grad_Q psi>
    (phi.grad_phi = Q.grad_Q on invariant functions), <T> = (hbar^2/2) int |grad_Q psi|^2 m dQ
    (the Laplacian of R^9 on invariant functions)."""
    w = np.sqrt(hbar / 2)
    group = [np.eye(3)[list(p)] * np.array(f, float)[:, None] for p in permutations(range(3))
             for f in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1))]
    R = float(np.linalg.norm(Q0)) + 10 * w

    def rule(n, a, b):
        x, wx = np.polynomial.legendre.leggauss(n)
        return a + (b - a) * (x + 1) / 2, (b - a) * wx / 2

    (r, wr), (s, ws), (t, wt) = rule(80, 0, R), rule(48, 0, 1), rule(48, -1, 1)
    Rr, S, T = np.meshgrid(r, s, t, indexing="ij")
    Q = np.stack([Rr, Rr * S, Rr * S * T], -1).reshape(-1, 3)
    m = (Q[:, 0] ** 2 - Q[:, 1] ** 2) * (Q[:, 0] ** 2 - Q[:, 2] ** 2) * (
        Q[:, 1] ** 2 - Q[:, 2] ** 2)
    W = (wr[:, None, None] * ws[None, :, None] * wt[None, None, :] * Rr**2 * S).ravel() * m
    psi, grad = np.zeros(len(Q), complex), np.zeros((len(Q), 3), complex)
    for g in group:
        d = Q @ g.T - Q0
        f = np.exp(-np.sum(d * d, -1) / (4 * w * w) + 1j * (d @ P0) / hbar)
        psi += f
        grad += f[:, None] * ((-d / (2 * w * w) + 1j * P0 / hbar) @ g)
    rho = W * np.abs(psi) ** 2 / np.sum(W * np.abs(psi) ** 2)
    return {"trG": np.sum(rho * np.sum(Q * Q, -1)),
            "D": 2 * np.real(np.sum(W * np.conj(psi) * (-1j * hbar) * np.sum(Q * grad, -1)))
            / np.sum(W * np.abs(psi) ** 2),
            "T": hbar**2 / 2 * np.sum(W * np.sum(np.abs(grad) ** 2, -1))
            / np.sum(W * np.abs(psi) ** 2),
            "harmonic": np.sum(rho * harmonic(Q)), "anharmonic": np.sum(rho * anharmonic(Q))}


def test_harmonic_trG_follows_its_closed_form(evolutions):
    """V = |phi|^2/2 (I = omega = 1): for any state d^2<trG>/dt^2 = 4<H> - 4<trG>, so
    <trG>(t) = E + (X0 - E) cos 2t + (D0/2) sin 2t, exactly. With X0, D0, E of the packet from
    the independent quadrature (packet_moments) the evolved mean agrees to 5e-6 (relative) over
    two periods (measured 2.7e-7 at hbar = 1, 6.6e-7 at hbar = 0.5: the part of the packet
    beyond the basis); norm and energy constant to round-off."""
    for hbar, _ in RUNS:
        _, ev = evolutions["harmonic", hbar]
        moments = packet_moments(hbar)
        X0, D0, E = moments["trG"], moments["D"], moments["T"] + moments["harmonic"]
        assert ev.captured > 1 - 1e-6
        assert np.ptp(ev.norm) < 1e-13 and np.ptp(ev.energy) < 1e-13 * ev.energy[0]
        assert abs(ev.energy[0] - E) < 1e-6 * E
        closed = E + (X0 - E) * np.cos(2 * TIMES) + D0 / 2 * np.sin(2 * TIMES)
        assert np.max(np.abs(ev.mean["trG"] - closed)) < 5e-6 * X0
        assert ev.survival[0] == pytest.approx(1.0, abs=1e-12)


def test_harmonic_ehrenfest_error_shrinks_with_hbar(evolutions):
    """Against the classical orbit phi(t) = diag(Q0 cos t + P0 sin t) (its signed singular
    values): the largest distance of <trG> over t in [0, 6.4] is 5.48 at hbar = 1 and 2.97 at
    hbar = 0.5 (the zero-point 9 hbar/2 of R^9 dominates), of <Q1> 1.19 and 0.70, of <Q2>
    0.62 and 0.37: O(hbar)."""
    classical = np.outer(np.cos(TIMES), Q0) + np.outer(np.sin(TIMES), P0)
    Qc = chamber(classical)
    errors = {}
    for hbar, _ in RUNS:
        _, ev = evolutions["harmonic", hbar]
        errors[hbar] = (np.max(np.abs(ev.mean["trG"] - np.sum(classical**2, -1))),
                        np.max(np.abs(ev.mean["Q1"] - Qc[:, 0])),
                        np.max(np.abs(ev.mean["Q2"] - Qc[:, 1])))
    for a, b in zip(errors[1.0], errors[0.5], strict=True):
        assert b < 0.65 * a


@pytest.fixture(scope="module")
def simulated():
    """The simulator's trajectory (affinebody.simulate.run, J = Id, group L: det phi may
    change sign) of the anharmonic body from diag(Q0) with momentum diag(P0): it stays
    diagonal (zero spin and vorticity); its signed singular values."""
    phi = np.diag(Q0).tolist()
    pi = np.diag(P0).tolist()
    cfg = parse_config(textwrap.dedent(f"""
        [system]
        n = 3
        group = "L"
        bodies = 1
        [body]
        mass = 1.0
        inertia = 1.0
        [kinetic]
        internal = "dalembert"
        [[potential]]
        kind = "one-body"
        expr = "{ANHARMONIC}"
        [initial]
        x = [[0.0, 0.0, 0.0]]
        phi = [{phi}]
        phi_momentum = [{pi}]
        [run]
        dt = 0.005
        steps = 1280
        every = 8
        """))
    built = build(cfg)
    traj = run(built.system, built.state, 0.005, 1280, every=8)
    phi = np.asarray(traj.states.phi)[:, 0]
    assert np.max(np.abs(phi - np.einsum("tii->ti", phi)[:, :, None] * np.eye(3))) < 1e-12
    return np.asarray(traj.times), chamber(np.einsum("tii->ti", phi))


def test_anharmonic_ehrenfest_against_the_simulator(evolutions, simulated):
    """V = trG/2 + trG^2/50: the largest distance over t in [0, 6.4] between <Q_a>(t) and the
    simulator's signed singular values shrinks with hbar (measured 1.94, 1.00, 0.34 at
    hbar = 1; 1.09, 0.64, 0.24 at hbar = 0.5; the eigenvalue error estimate weighted by the
    packet is 0.04 and 0.009); norm and energy constant to round-off, and the energy equals
    that of the packet from the independent quadrature."""
    times, Q = simulated
    np.testing.assert_allclose(times, TIMES, atol=1e-12)
    errors = {}
    for hbar, _ in RUNS:
        _, ev = evolutions["anharmonic", hbar]
        assert np.ptp(ev.norm) < 1e-13 and np.ptp(ev.energy) < 1e-13 * ev.energy[0]
        moments = packet_moments(hbar)
        assert abs(ev.energy[0] - moments["T"] - moments["anharmonic"]) < 1e-5 * ev.energy[0]
        errors[hbar] = [np.max(np.abs(ev.mean[f"Q{a + 1}"] - Q[:, a])) for a in range(3)]
    assert np.ptp(Q[:, 0]) > 0.5  # the motion is not small against the errors
    for a, b in zip(errors[1.0], errors[0.5], strict=True):
        assert b < 0.8 * a


def test_survival_lines_at_level_spacings(evolutions):
    """The two strongest Fourier lines of |<psi(0)|psi(t)>|^2 over t in [0, 60] (anharmonic,
    hbar = 1) lie within half a frequency bin (pi/60) of differences (E_m - E_n)/hbar of
    populated states, the strongest at that of the most populated pair."""
    hbar = 1.0
    sector, _ = evolutions["anharmonic", hbar]
    T = 60.0
    ev = evolve3(sector, Q0, P0, np.sqrt(hbar / 2), np.linspace(0, T, 601), hbar)
    p, E = np.abs(ev.coefficients) ** 2, ev.energies
    top = np.argsort(-p)[:8]
    pairs = sorted(((p[m] * p[n], (E[m] - E[n]) / hbar) for m in top for n in top
                    if E[m] > E[n]), reverse=True)
    lines = spectrum_lines(ev, 2)
    assert abs(lines[0] - pairs[0][1]) < np.pi / T
    for line in lines:
        assert min(abs(line - w) for weight, w in pairs if weight > 0.01 * pairs[0][0]) < np.pi / T


def test_results_do_not_depend_on_the_eigenvectors_chosen_in_a_degenerate_level(evolutions):
    """The anharmonic potential depends on Tr G = |phi|^2 only (SO(9)-invariant), so the sector
    has exactly degenerate levels. Rotating each level's eigenvectors by a random orthogonal
    matrix (another basis of the same eigenspace) changes no output: not the survival
    probability or the means, and not the packet's energy_error either (its per-state error
    estimates are one per level: bases.level_errors; index-paired estimates moved it by 1e-5
    relative here)."""
    from dataclasses import replace

    hbar = 0.5
    sector, ev = evolutions["anharmonic", hbar]
    E = sector.energies
    starts = level_starts(E, Settings().merge)
    ends = np.r_[starts[1:], len(E)]
    assert max(ends - starts) > 1  # the test needs a degenerate level
    rng = np.random.default_rng(7)
    vectors = sector.vectors.copy()
    for a, b in zip(starts, ends, strict=True):
        rotation, _ = np.linalg.qr(rng.normal(size=(b - a, b - a)))
        vectors[:, a:b] = vectors[:, a:b] @ rotation
        assert np.all(sector.errors[a:b] == sector.errors[a])
    turned = evolve3(replace(sector, vectors=vectors), Q0, P0, np.sqrt(hbar / 2), TIMES, hbar)
    assert turned.energy_error == pytest.approx(ev.energy_error, rel=1e-12)
    assert np.allclose(turned.survival, ev.survival, rtol=0, atol=1e-12)
    assert np.allclose(turned.mean["trG"], ev.mean["trG"], rtol=1e-12)


CONFIG3 = f"""
[system]
n = 3
[quantum]
hbar = 1.0
kinetic = "dalembert"
inertia = 1.0
potential = "{ANHARMONIC}"
basis_size = 12
scale = 1.0
"""


def test_cli_evolve_n3_json_and_errors(tmp_path):
    """``affinebody evolve`` for n = 3: JSON with the five observables, norm constant, the
    packet's <trG> at t = 0 that of the independent quadrature at hbar = 1 (packet_moments,
    the same packet: the CLI's default width sqrt(hbar/2)); one-line refusals (exit 1)."""
    from click.testing import CliRunner

    from affinebody.cli.quantum_dynamics import evolve as evolve_command

    path = tmp_path / "n3.toml"
    path.write_text(CONFIG3)
    args = [str(path), "--at", "1.5,0.9,0.3", "--momentum", "0,0.2,-0.1", "--time", "1",
            "--steps", "4"]
    result = CliRunner().invoke(evolve_command, [*args, "--json", "--plot",
                                                 str(tmp_path / "n3.png")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "n3.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(result.output)
    assert data["n"] == 3 and set(data["mean"]) == {"Q1", "Q2", "Q3", "det", "trG"}
    assert np.ptp(data["norm"]) < 1e-13 and data["captured"] > 1 - 1e-6
    assert abs(data["mean"]["trG"][0] - packet_moments(1.0)["trG"]) < 1e-4
    for extra, needle in ((["--at", "0.9,1.5,0.3"], "must lie in the chamber"),
                          (["--at", "1.5,0.9"], "three finite numbers"),
                          (["--steps", "1000000"], "--steps must be between"),
                          (["--at", "3,2,1", "--momentum", "0,3,0"], "hold only")):
        bad = CliRunner().invoke(evolve_command, [*args, *extra])
        assert bad.exit_code == 1, (extra, bad.output)
        assert needle in bad.output and len(bad.output.strip().splitlines()) == 1
    spin = CliRunner().invoke(evolve_command, [str(path), "--phi", "1,0,0,1"])
    assert spin.exit_code == 1 and "--phi is for n = 2" in spin.output


def test_affine_packet_energy_and_conservation():
    """af-is (I = 1, A = 0.2, B = 0.1), n = 3, V = (det - 1)^2/2 + (trG - 3)^2/4, hbar = 0.5, the
    W-symmetrised Gaussian in q at (0.3, 0, -0.3) with momentum (0, 0.2, 0), w = 0.2 (degree 14,
    147 states): norm and energy constant to round-off, and the energy equals the one computed
    apart from the sector's basis, <T> + <V> with <T> = hbar^2 <H_kin(phi, Re xi) +
    H_kin(phi, Im xi)> from the classical af-is kinetic energy of affinebody.kinetic at
    phi = diag(e^q), xi = diag(e^-q_a d_a psi) (an invariant function's gradient at a diagonal
    phi), on a product Gauss-Legendre rule of the chamber q3 = u, q2 = u + a, q1 = u + a + b
    with the Haar measure sinh(a) sinh(b) sinh(a + b). Measured: 1.6e-8 (relative)."""
    import jax.numpy as jnp

    from affinebody.kinetic import AffineIsotropic

    def V(Q):
        det, trG = np.prod(Q, -1), np.sum(Q * Q, -1)
        return 0.5 * (det - 1) ** 2 + 0.25 * (trG - 3) ** 2

    hbar, w = 0.5, 0.2
    X0, p0 = np.array([0.3, 0.0, -0.3]), np.array([0.0, 0.2, 0.0])
    sector = scalar_sector3("af-is", V, hbar, I=1.0, A=0.2, B=0.1,
                            settings=Settings(basis_size=14, check_shrink=2, scale=0.35,
                                              scale_sigma=0.35, centre=0.0, check_widen=1.0))
    ev = evolve3(sector, X0, p0, w, np.linspace(0.0, 3.0, 7), hbar)
    assert ev.captured > 1 - 1e-6
    assert np.ptp(ev.norm) < 1e-13 and np.ptp(ev.energy) < 1e-13 * ev.energy[0]

    def rule(n, a, b):
        x, wx = np.polynomial.legendre.leggauss(n)
        return a + (b - a) * (x + 1) / 2, (b - a) * wx / 2

    (u, wu), (a, wa), (b, wb) = rule(40, -2.0, 1.2), rule(40, 0, 2.5), rule(40, 0, 2.5)
    U, A, B = np.meshgrid(u, a, b, indexing="ij")
    q = np.stack([U + A + B, U + A, U], -1).reshape(-1, 3)
    W = (wu[:, None, None] * wa[None, :, None] * wb[None, None, :]
         * np.sinh(A) * np.sinh(B) * np.sinh(A + B)).ravel()
    psi, grad = np.zeros(len(q), complex), np.zeros((len(q), 3), complex)
    for perm in permutations(range(3)):
        d = q[:, list(perm)] - X0
        f = np.exp(-np.sum(d * d, -1) / (4 * w * w) + 1j * (d @ p0) / hbar)
        psi += f
        # d/dq_c of d_a = q_perm[a]: the a with perm[a] = c
        grad += f[:, None] * ((-d / (2 * w * w) + 1j * p0 / hbar)[:, np.argsort(perm)])
    phi = jnp.asarray(np.eye(3) * np.exp(q)[:, None, :])
    kinetic = AffineIsotropic(I=1.0, A=0.2, B=0.1)
    T = sum(np.asarray(kinetic.hamiltonian(phi, jnp.asarray(
        np.eye(3) * (part * np.exp(-q))[:, None, :])))
        for part in (grad.real, grad.imag))
    norm = np.sum(W * np.abs(psi) ** 2)
    energy = np.sum(W * (hbar**2 * T + V(np.exp(q)) * np.abs(psi) ** 2)) / norm
    assert abs(ev.energy[0] - energy) < 1e-6 * energy
