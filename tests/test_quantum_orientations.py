"""Orientation densities and densities of the components of G (quantum/densities.py, n = 2)
against closed forms of the d'Alembert oscillator (phi's entries Gaussian): sector states,
a superposition across sectors and the thermal mixture."""

import itertools
import json
import math

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import special

from affinebody.quantum import spectra as sp
from affinebody.quantum.cli import density
from affinebody.quantum.densities import (
    ORIENTATION_NODES,
    _g_density,
    angle_densities,
    densities,
    g_component_densities,
    orientation_densities,
    pure_state,
    state_components,
    thermal_states,
)
from oracles import oscillator_config

HBAR, INERTIA, K = 0.8, 1.3, 2.0
OMEGA = math.sqrt(K / INERTIA)
#: variance of each entry of phi in the ground state: hbar / (2 I omega)
S2 = HBAR / (2 * INERTIA * OMEGA)


#: the oscillator as a config file, for the density command
OSCILLATOR_CONFIG = oscillator_config(HBAR, INERTIA, K, "basis_size = 9\ndensity_points = 11")


@pytest.fixture(scope="module")
def oscillator():
    """Levels N = 0, 1, 2 of the R^4 oscillator (1 + 4 + 10 states)."""
    spectrum = sp.solve("dalembert", 2, lambda q: 0.5 * K * np.sum(q**2, axis=-1), HBAR,
                        inertia=INERTIA, levels=15, settings=sp.Settings(basis_size=9))
    assert len(spectrum.energies()) >= 15
    return spectrum


def _fourier(angle, density, m):
    """int_0^2pi p(a) e^{-i m a} da (the grid's end point repeats its start)."""
    return np.sum((density * np.exp(-1j * m * angle))[:-1]) * (angle[1] - angle[0])


def test_sector_states_have_uniform_orientations_and_gaussian_g(oscillator):
    """Ground state: phi's entries are iid N(0, s^2), so G11 = |phi e1|^2 is exponential with
    mean 2 s^2, and G12 = a b + c d (a sum of two products of independent normals) is Laplace,
    e^{-|y|/s^2} / (2 s^2); every sector state's L and R are uniform."""
    d = orientation_densities(oscillator, state=0, points=9)
    assert d["warnings"] == []
    for key in ("L_angle", "R_angle"):
        assert np.abs(d["orientation"][key] - 1 / (2 * np.pi)).max() < 1e-12
    g11, g12 = d["G"]["G11"], d["G"]["G12"]
    exact11 = np.exp(-g11.x / (2 * S2)) / (2 * S2)
    peak = 1 / (2 * S2)  # both densities' values at y = 0
    assert np.abs(g11.density - exact11).max() < 1e-6 * peak
    exact12 = np.exp(-np.abs(g12.x) / S2) / (2 * S2)
    assert np.abs(g12.density - exact12).max() < 1e-6 * peak
    # G22 of a sector state is G11's (R uniform), taken from it: against G22 itself
    for k in (0, 7):
        pure = pure_state(oscillator, {k: 1.0})
        g = g_component_densities([(1.0, pure)], points=9, components=("G11", "G22"))["G22"]
        direct = _g_density([(1.0, pure)], "G22", g.x, *ORIENTATION_NODES[2])
        assert np.abs(direct - g.density).max() < 1e-6 * np.max(g.density), k
    table = state_components(oscillator, 14)
    angle = np.linspace(0, 2 * np.pi, 73)
    for k in (1, 7, 14):
        one = angle_densities(pure_state(oscillator, {k: 1.0}), angle)
        assert np.abs(one["L_angle"] - 1 / (2 * np.pi)).max() < 1e-10, table[k][1]
        assert np.abs(one["R_angle"] - 1 / (2 * np.pi)).max() < 1e-10, table[k][1]


def test_superposition_across_sectors(oscillator):
    """Psi = (psi_0 + psi_zw) / sqrt 2 with psi_zw the (s, k) = (2, 0) state of level N = 2:
    in the complex coordinates z = (a + d) + i(c - b), w = (a - d) + i(c + b) of phi, psi_zw
    is z w e^{-|phi|^2 / 4 s^2} / (4 s^2) (normalised against psi_0), and z w = (Q1^2 - Q2^2)
    e^{2 i alpha}. So <e^{-2 i alpha}> = <psi_0| |z w| |psi_0> / (2 * 4 s^2) = pi s^2 / (8 s^2)
    = pi / 8 (|z|, |w| independent Rayleigh, mean sqrt(pi s^2)), and R stays uniform (the two
    states have equal vorticity)."""
    table = state_components(oscillator, 14)
    k2 = next(k for k, (_, sec) in enumerate(table) if (sec.spin, sec.vorticity) == (2, 0))
    angle = np.linspace(0, 2 * np.pi, 361)
    d = angle_densities(pure_state(oscillator, {0: 1.0, k2: 1.0}), angle)
    assert abs(_fourier(angle, d["L_angle"], 0) - 1) < 1e-12
    assert abs(abs(_fourier(angle, d["L_angle"], 2)) - np.pi / 8) < 1e-9
    assert np.abs(d["R_angle"] - 1 / (2 * np.pi)).max() < 1e-12
    assert d["L_angle"].min() > 0
    # with the (0, 2) state instead the vorticities differ: R is not uniform, G22's law is not
    # G11's, and G22 is computed, not taken from G11
    k02 = next(k for k, (_, sec) in enumerate(table) if (sec.spin, sec.vorticity) == (0, 2))
    pure = pure_state(oscillator, {0: 1.0, k02: 1.0})
    g = g_component_densities([(1.0, pure)], points=5, components=("G11", "G22"))
    peak = np.max(g["G11"].density)
    assert np.abs(g["G11"].density - g["G22"].density).max() > 0.1 * peak
    direct = _g_density([(1.0, pure)], "G22", g["G22"].x, *ORIENTATION_NODES[2])
    assert np.abs(direct - g["G22"].density).max() < 1e-6 * peak
    assert abs(g["G22"].integral - 1) <= g["G22"].integral_error


def test_thermal_mixture(oscillator):
    """At temperature T the oscillator's phi entries are Gaussian with variance
    s^2 coth(hbar omega / 2T): G11 is exponential with mean twice that; orientations uniform."""
    temperature = 0.15
    states, weights, tail = thermal_states(oscillator, temperature)
    # the last state computed is in N = 2; each state left out (N >= 3) weighs e^{-hbar omega
    # / T} ~ 1e-3 of it. The 15 states are 8 reduced eigenfunctions (conjugate sectors share
    # one: N = 1 has 2, N = 2 has 5), each once with its states' probabilities summed
    assert len(states) == 8 and weights.sum() == pytest.approx(1.0, abs=1e-15)
    assert tail == pytest.approx(math.exp(-2 * HBAR * OMEGA / temperature), rel=1e-6)
    g11 = g_component_densities(list(zip(weights, states, strict=True)), points=7,
                                components=("G11",))["G11"]
    s2t = S2 / math.tanh(HBAR * OMEGA / (2 * temperature))
    exact = np.exp(-g11.x / (2 * s2t)) / (2 * s2t)
    peak = 1 / (2 * s2t)  # the density at y = 0
    assert g11.converged and np.abs(g11.density - exact).max() < 1e-6 * peak
    assert abs(g11.integral - 1) <= g11.integral_error < 1e-5
    # the states evaluated together (basis values shared) = each alone, weighted
    mixture = list(zip(weights, states, strict=True))
    together = _g_density(mixture, "G11", g11.x, 96, 72)
    alone = sum(w * _g_density([(1.0, pure)], "G11", g11.x, 96, 72) for w, pure in mixture)
    np.testing.assert_allclose(together, alone, rtol=1e-13, atol=1e-15 * peak)
    with pytest.raises(ValueError, match="exactly one"):
        orientation_densities(oscillator, state=0, temperature=1.0)


def _hermite_moments(n):
    """<x^2>, <x^4> of the 1D oscillator's n-th state (variance s^2 in the ground state)."""
    return S2 * (2 * n + 1), 3 * S2**2 * (2 * n * n + 2 * n + 1)


def _shell_g11(N, y):
    """Density of G11 = a^2 + c^2 in the uniform mixture of the R^4 oscillator's states with N
    quanta, phi = [[a, b], [c, d]], from the Cartesian product states: the (b, d) factor
    integrates out, each 2D shell of (a, c) is rotation invariant, so its density at radius
    r = sqrt(y) is its value on the axis, sum_{n1 + n2 = N1} h_{n1}(r)^2 h_{n2}(0)^2, and
    p(y) = pi x that (d^2x = pi dy)."""
    def h2(n, x):
        return (special.eval_hermite(n, x / math.sqrt(2 * S2)) ** 2 / (2.0**n * math.factorial(n))
                * np.exp(-x**2 / (2 * S2)) / math.sqrt(2 * math.pi * S2))
    r = np.sqrt(y)
    return sum((N - N1 + 1) * math.pi * sum(h2(n, r) * h2(N1 - n, 0.0) for n in range(N1 + 1))
               for N1 in range(N + 1)) / math.comb(N + 3, 3)


def test_every_state_of_a_degenerate_level_is_its_own_eigenvector(oscillator):
    """The N = 2 level (states 5-14) holds two eigenvectors of the sector (0, 0) (|z|^2 and
    |w|^2 in their combinations). Each state must be its own: the uniform mixture of the level
    is basis independent, so its G11 density is the closed form of the Cartesian states
    (:func:`_shell_g11`), and its mean det(phi)^2 (from each state's det marginal, as
    ``density --state k`` computes it) is <|phi|^4> / 12 (the mixture is rotation invariant
    in R^4; (ad - bc)^2 averages to 1/12 on the unit sphere). The code before gave the second
    (0, 0) state the first one's eigenvector (G11 off by 8 % of the peak) and every state of a
    level the level's first eigenvector's invariant densities (mean det^2 0.74 for 0.42)."""
    level = range(5, 15)
    assert len({(lv.block, lv.index, sector)
                for lv, sector in map(oscillator.state_eigenvector, level)}) == 10
    mixture = [(0.1, pure_state(oscillator, {k: 1.0})) for k in level]
    g11 = g_component_densities(mixture, points=7, components=("G11",))["G11"]
    exact = _shell_g11(2, g11.x)
    assert g11.converged and np.abs(g11.density - exact).max() < 1e-6 * exact.max()
    det2 = []
    for k in level:
        x, p = densities(oscillator, k, points=101)["marginals"]["det"]
        det2.append(np.trapezoid(x**2 * p, x))
    shell = [t for t in itertools.product(range(3), repeat=4) if sum(t) == 2]
    r4 = np.mean([sum(_hermite_moments(n)[1] for n in t)
                  + sum(_hermite_moments(t[i])[0] * _hermite_moments(t[j])[0]
                        for i in range(4) for j in range(4) if i != j) for t in shell])
    assert np.mean(det2) == pytest.approx(r4 / 12, rel=1e-3)


def test_density_command_temperature_solves_for_the_states_its_mixture_needs(tmp_path):
    """affinebody density --temperature 0.15 with quantum.levels = 1 (the ground state: a
    mixture truncated far above the tolerance, which the command only warned of) asks for more
    states until the last state's Boltzmann factor is below the densities' tolerance, at least
    twice as many and more than it has, since a level is solved whole: 1 (-> 1 state) -> 2 (the
    N = 1 level: 5 states, 1.3e-3) -> 6 (N <= 2: 15, 1.8e-6) -> 16 (at basis_size 9 the N = 3
    states come out unconverged: the request stops there, and the mixture of 15 states leaves
    out states of factor 2.4e-9 each). Doubling the request alone stopped at 5 states (4 asked
    for, 5 already had). Then no warning, exit 0,
    and G11 is the Gaussian thermal state's exponential law to 1e-6 of its peak."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR_CONFIG + "levels = 1\n")
    result = CliRunner().invoke(density, [str(path), "--temperature", "0.15", "-o",
                                          str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    states = int(result.output.split("(thermal of ")[1].split()[0])
    assert states >= 15 and "warning" not in result.output
    doc = json.loads((tmp_path / "o" / "orientation.json").read_text())
    g11 = doc["densities"]["G11"]
    s2t = S2 / math.tanh(HBAR * OMEGA / (2 * 0.15))
    exact = np.exp(-np.asarray(g11["x"]) / (2 * s2t)) / (2 * s2t)
    assert doc["warnings"] == [] and np.abs(g11["density"] - exact).max() < 1e-6 * exact.max()


def test_density_command_superposition(tmp_path):
    """affinebody density --superpose: the ground state and an N = 1 state (s = +-1, k = +-1:
    both labels differ, so no cross term survives either angle integral): uniform angles,
    and each G density is the mean of the two states' (Laplace for the ground state's G12 at
    large |y| is not asserted here); orientation.json / .npz / .png written, exit 0."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR_CONFIG)
    out = tmp_path / "o"
    result = CliRunner().invoke(density, [str(path), "--superpose", "0:1,1:1j", "-o", str(out),
                                          "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["kind"] == "superposition" and doc["warnings"] == []
    for key in ("L_angle", "R_angle"):
        assert np.abs(np.asarray(doc["densities"][key]["density"]) - 1 / (2 * np.pi)).max() < 1e-12
    assert {"G11", "G22", "G12"} <= set(doc["densities"])
    assert all((out / name).exists() for name in ("orientation.json", "orientation.npz",
                                                  "orientation.png"))
    result = CliRunner().invoke(density, [str(path), "--state", "0", "--temperature", "1",
                                          "-o", str(out)])
    assert result.exit_code == 1 and "exactly one of --state" in result.output
    # non-finite amplitudes and temperatures: refused at once in one line naming the flag (an
    # inf amplitude wrote nan files with four warnings, an infinite kT ran for minutes:
    # found by fuzzing the CLI); an amplitude of nan is not "zero"
    for flags, needle in ((["--superpose", "0:inf"], "--superpose: the amplitude of state 0"),
                          (["--superpose", "0:1,1:nan"], "--superpose: the amplitude of state 1"),
                          (["--superpose", "0:1,0:1"], "--superpose: state 0 is given twice"),
                          (["--temperature", "inf"], "--temperature must be a finite kT > 0"),
                          (["--temperature", "0"], "--temperature must be a finite kT > 0")):
        bad = tmp_path / "refused"
        result = CliRunner().invoke(density, [str(path), *flags, "-o", str(bad)])
        message = result.stderr.strip()
        assert result.exit_code == 1 and "\n" not in message and needle in message, message
        assert not bad.exists()
