"""The public CLI contract of `affinebody spectrum` / `affinebody density` (quantum/cli.py)."""

import json
from math import comb

import numpy as np
import pytest
from click.testing import CliRunner

from affinebody.quantum.cli import density, spectrum

OSCILLATOR = """
[system]
n = 2
[quantum]
hbar = 1.0
kinetic = "dalembert"
inertia = 2.0
potential = "0.5*8.0*trG"
basis_size = 12
"""


def test_spectrum_json_reproduces_oscillator(tmp_path):
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR)
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "15", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    omega = np.sqrt(8.0 / 2.0)
    expected = [omega * (N + 2) for N in range(4) for _ in range(comb(N + 3, 3))][:15]
    assert np.allclose(data["energies"], expected, atol=1e-9, rtol=0)
    assert data["energies"] == sorted(data["energies"])
    mults = [s["multiplicity"] for s in data["states"]]
    assert mults[:3] == [1, 4, 10]
    for key in ("energy", "multiplicity", "spin", "vorticity", "parity", "error"):
        assert key in data["states"][0]


def test_spectrum_table_and_config_error(tmp_path):
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR)
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    assert result.exit_code == 0 and "energy" in result.output
    bad = tmp_path / "bad.toml"
    bad.write_text(OSCILLATOR.replace("hbar = 1.0", "hbar = -1.0"))
    result = CliRunner().invoke(spectrum, [str(bad)])
    assert result.exit_code == 1
    assert "quantum.hbar must be > 0" in result.output


def test_density_command_writes_normalised_densities(tmp_path):
    """density --json: the JSON on stdout and in densities.json carries every array with its
    error; npz and PNGs as before; the N = 1 level obeys the virial theorem; a tolerance no
    quadrature meets is flagged (converged false, a warning, exit status 3)."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR)
    out = tmp_path / "dens"
    result = CliRunner().invoke(density, [str(path), "--state", "2", "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    printed = json.loads(result.output)
    summary = json.loads((out / "densities.json").read_text())
    assert printed == summary
    assert abs(summary["normalisation"] - 1) < 1e-8 and summary["variables"] == "Q"
    assert all(abs(v - 1) < 1e-9 for v in summary["integrals"].values())
    for name in ("Q1", "Q2", "det", "trG", "orientation"):
        assert (out / f"density_{name}.png").stat().st_size > 1000
    arrays = np.load(out / "densities.npz")
    for name in ("Q1", "Q2", "det", "trG"):
        entry = summary["densities"][name]
        assert entry["converged"] and entry["error"] <= 1e-8 * max(entry["density"])
        assert np.array_equal(arrays[f"{name}_x"], entry["x"])
        assert np.array_equal(arrays[f"{name}_density"], entry["density"])
    x, p = arrays["trG_x"], arrays["trG_density"]
    # virial theorem for the oscillator: <V> = E/2, so <Tr G> = E / k = 3 omega / k (N = 1
    # level); the mean by the rectangle rule on the 301 points (its own error ~ 1e-7)
    mean = np.sum(x * p) * (x[1] - x[0])
    assert abs(mean - 3 * np.sqrt(8.0 / 2.0) / 8.0) < 1e-6
    table = CliRunner().invoke(density, [str(path), "--state", "0", "-o", str(out)])
    assert table.exit_code == 0 and "integral" in table.output
    strict = tmp_path / "strict.toml"
    strict.write_text(OSCILLATOR + "density_tolerance = 1e-30\n")
    result = CliRunner().invoke(density, [str(strict), "--state", "0", "-o", str(out), "--json"])
    assert result.exit_code == 3
    flagged = json.loads((out / "densities.json").read_text())
    assert not flagged["densities"]["det"]["converged"] and flagged["warnings"]


N3_SPIN1 = """
[system]
n = 3
[quantum]
hbar = 0.9
kinetic = "dalembert"
inertia = 0.7
potential = "0.5*1.3*trG"
sectors = "scalar+spin1"
basis_size = 6
scale = {scale}
"""


def test_n3_dalembert_spectrum_defaults_to_harmonics_times_radial_functions(tmp_path):
    """Without quantum.radial_size an n = 3 d'Alembert spectrum over every sector is solved in
    harmonics x DEFAULT_RADIAL_SIZE radial functions (the Gaussian x polynomial basis, ~50x
    slower on a non-polynomial potential, with radial_size = 0): the R^9 oscillator's levels
    hbar w (N + 9/2), multiplicities 1 and 9, exact through the default."""
    from affinebody.quantum.config import DEFAULT_RADIAL_SIZE, parse, solver_arguments

    text = "[system]\nn = 3\n[quantum]\nhbar = 0.9\ninertia = 0.7\npotential = '0.65*trG'\n"
    assert solver_arguments(parse(text))["settings"].radial_size == DEFAULT_RADIAL_SIZE
    chosen = parse(text + "radial_size = 0\n")
    assert solver_arguments(chosen)["settings"].radial_size is None
    path = tmp_path / "n3.toml"
    path.write_text(text)
    result = CliRunner().invoke(spectrum, [str(path), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["settings"]["radial_size"] == DEFAULT_RADIAL_SIZE
    omega, hbar = np.sqrt(1.3 / 0.7), 0.9
    expected = [hbar * omega * (N + 4.5) for N, m in ((0, 1), (1, 9)) for _ in range(m)]
    assert np.allclose(data["energies"], expected, atol=1e-9, rtol=0)
    assert [s["multiplicity"] for s in data["states"]] == [1, 9] and data["certified"]


def test_spectrum_n3_spin1_json_and_density(tmp_path):
    """n = 3 oscillator through the CLI: levels 1 (scalar) + 9 (spin 1) + 10 (9 + 1) at
    hbar w (N + 9/2); the JSON says which sectors are computed; a spin-1 state's densities are
    normalised."""
    omega, hbar = np.sqrt(1.3 / 0.7), 0.9
    path = tmp_path / "n3.toml"
    path.write_text(N3_SPIN1.format(scale=(hbar**2 / (0.7 * 1.3)) ** 0.25))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "20", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    expected = [hbar * omega * (N + 4.5) for N, m in ((0, 1), (1, 9), (2, 10)) for _ in range(m)]
    assert np.allclose(data["energies"], expected, atol=1e-9, rtol=0)
    assert [s["multiplicity"] for s in data["states"]] == [1, 9, 10]
    assert data["states"][1]["sectors"][0]["dimension"] == 9
    assert data["sectors"] == "scalar+spin1" and data["bounded_below"] is True
    assert any("(0, 0) and (1, 1)" in w for w in data["warnings"])
    out = tmp_path / "dens"
    result = CliRunner().invoke(density, [str(path), "--state", "3", "-o", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "densities.json").read_text())
    assert abs(summary["normalisation"] - 1) < 1e-8
    assert summary["sector"]["spin"] == 1


AF_AF = """
[system]
n = 2
[quantum]
kinetic = "af-af"
A = 1.0
B = 0.2
potential = "q1**2 + q2**2"
basis_size = 12
max_spin = 4
"""


def test_af_af_spectrum_says_unbounded_below(tmp_path):
    path = tmp_path / "afaf.toml"
    path.write_text(AF_AF)
    # none of the levels of this small basis converges: written, then exit 3
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3", "--json"])
    assert result.exit_code == 3, result.output
    data = json.loads(result.stdout)
    assert data["bounded_below"] is False
    assert any("unbounded below" in w for w in data["warnings"])
    table = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    assert table.exit_code == 3 and "unbounded below" in table.output


UNBOUNDED = """
[system]
n = 2
[quantum]
hbar = 1.0
kinetic = "dalembert"
inertia = 1.0
potential = "{potential}"
"""


@pytest.mark.parametrize("n, potential", [(2, "-0.5*trG"), (2, "0.1*trG - det**2"),
                                          (3, "0.5*det - sqrt(trG)**3")])
def test_a_potential_unbounded_below_is_refused_at_once(tmp_path, n, potential):
    """H has no lowest level: one line, exit 1, before any sector is solved (it used to run
    for minutes with no output)."""
    import time

    path = tmp_path / "unbounded.toml"
    path.write_text(UNBOUNDED.format(potential=potential).replace("n = 2", f"n = {n}"))
    started = time.perf_counter()
    result = CliRunner().invoke(spectrum, [str(path)])
    assert time.perf_counter() - started < 20
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert "\n" not in message and "unbounded below" in message


def test_affine_potential_that_does_not_confine_is_refused_naming_the_fix(tmp_path):
    """trG with af-is tends to 0 as det -> 0: the sum of levels the automatic affine basis
    minimises has no minimum, and the search drifted until round-off chose (scale at its clip
    e^3, centre ~ 423, where e^(2q) overflows). One line, exit 1, saying so and naming the
    settings, not 'trG is not finite ... bound it (log(det) or 1/det ...)', which blamed a
    finite potential."""
    path = tmp_path / "trg.toml"
    path.write_text('[system]\nn = 2\n[quantum]\nkinetic = "af-is"\nI = 1.0\nA = 0.2\n'
                    'B = 0.3\npotential = "trG"\n')
    result = CliRunner().invoke(spectrum, [str(path)])
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert "\n" not in message and "does not confine" in message
    assert all(f"quantum.{name}" in message for name in ("scale", "scale_sigma", "centre"))


def test_n3_affine_potential_that_does_not_confine_is_refused_before_the_density(tmp_path):
    """README's n = 3 potential with af-is (tests/test_quantum_n3.py, README_N3): `density
    --state 0` searched every sector (over 12 min of CPU with the default max_spin) and then
    refused the ground state as not converged (error 7e-3). It is refused at the choice of the
    basis, before any sector or density, in one line naming the keys to change, exit 1 as for
    n = 2 (max_spin = 0 keeps the search short where it would still run); nothing is written."""
    from test_quantum_n3 import README_N3

    path = tmp_path / "afis3.toml"
    path.write_text(f'[system]\nn = 3\n[quantum]\nkinetic = "af-is"\nI = 1.0\nA = 0.2\n'
                    f'B = 0.1\npotential = "{README_N3}"\nmax_spin = 0\n')
    out = tmp_path / "dens"
    result = CliRunner().invoke(density, [str(path), "--state", "0", "-o", str(out)])
    message = result.stderr.strip()
    assert result.exit_code == 1 and "\n" not in message, result.output
    assert message.startswith("error: the automatic basis of the n = 3 af-is model ran away")
    assert "does not confine" in message and "quantum.potential" in message
    assert not out.exists()


def test_wells_bounded_below_pass_the_unboundedness_check():
    """Negative but bounded potentials (the shear well of the completeness tests, a Gaussian
    well, a log barrier at det -> 0 that rises at infinity) are not refused."""
    from affinebody.quantum.config import compile_potential
    from affinebody.quantum.spectra import require_bounded_below

    for n, text in [(2, "0.5*(q1 + q2)**2 + (-24.0)*Q1*Q2/(Q1 + Q2)**2"),
                    (2, "0.5*trG - 5*exp(-trG)"), (3, "0.5*trG - log(det**2 + 1e-3)")]:
        require_bounded_below(compile_potential(text, n), n)


def test_more_levels_than_the_solver_can_deliver_is_refused(tmp_path):
    path = tmp_path / "oscillator.toml"
    path.write_text(UNBOUNDED.format(potential="0.5*trG"))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "100000"])
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert "\n" not in message and "--levels 100000" in message


def test_af_af_without_a_shell_limit_is_refused_at_once(tmp_path):
    """af-af's kinetic energy is indefinite: no lowest level exists, and a search for one would
    run through every shell of the default limit (minutes, no output); refused in one line
    unless quantum.max_spin says which shells to solve (test_af_af_spectrum_says_...)."""
    path = tmp_path / "afaf.toml"
    path.write_text(AF_AF.replace("max_spin = 4\n", ""))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert "\n" not in message and "indefinite" in message and "quantum.max_spin" in message


@pytest.mark.parametrize("command, flags, name", [(spectrum, ["--levels", "0"], "--levels"),
                                                  (density, ["--state", "-1", "-o", "out"],
                                                   "--state"),
                                                  # was about --levels 100000001, a flag not
                                                  # given (found by fuzzing the CLI)
                                                  (density, ["--state", "100000000", "-o",
                                                             "out"], "--state must be from 0"),
                                                  (density, ["--superpose", "5000:1", "-o",
                                                             "out"], "--superpose: state")])
def test_out_of_range_counts_are_one_line_exit_1(tmp_path, command, flags, name):
    """A count out of range is bad input (exit 1, one line naming the flag), not click's usage
    error (exit 2), and is refused before any solving."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR)
    result = CliRunner().invoke(command, [str(path), *flags])
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert "\n" not in message and name in message


@pytest.mark.parametrize("line, name", [("hbar = 1e308", "quantum.hbar"),
                                        ("hbar = 1.0\nscale = 1e308", "quantum.scale"),
                                        ("hbar = 1.0\nscale = 5e-324", "quantum.scale"),
                                        ("hbar = 1e-150", "quantum.hbar")])
def test_constants_beyond_float64_are_refused_in_one_line_naming_them(tmp_path, line, name):
    """hbar or a basis scale so large or small that the solvers' squares and inverses leave
    float64 (found by fuzzing the CLI: an OverflowError as an internal error, or eleven
    overflow warnings and then one) is refused before any solving, naming the key."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR.replace("hbar = 1.0", line))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    message = result.stderr.strip()
    assert result.exit_code == 1 and "\n" not in message, message
    assert message.startswith(f"config error: {name} = ") and "float64" in message


@pytest.mark.parametrize("line, message", [
    ("max_spin = 100000000000000000000", "quantum.max_spin must be between 0 and 1000"),
    ("density_tolerance = true", "quantum.density_tolerance must be a number (got True)")])
def test_a_huge_shell_limit_or_a_boolean_number_is_refused_naming_the_key(tmp_path, line,
                                                                          message):
    """max_spin = 10^20 gave NumPy's 'Maximum allowed dimension exceeded'; true was read as
    1 (the quantum config was not strict, as the simulator's is): found by fuzzing the CLI."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR + line + "\n")
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    assert result.exit_code == 1 and result.stderr.strip().startswith(
        f"config error: {message}"), result.stderr


@pytest.mark.parametrize("potential", ["log(det)", "exp(trG)"])
def test_a_potential_infinite_on_the_basis_is_named_in_the_error(tmp_path, potential):
    """log(det) is -inf where det = 0 and exp(trG) overflows on the far nodes: the Hamiltonian
    is not finite and LAPACK said only 'array must not contain infs or NaNs' (found by
    fuzzing the CLI); the message now names quantum.potential and what to do."""
    path = tmp_path / "osc.toml"
    path.write_text(OSCILLATOR.replace('potential = "0.5*8.0*trG"', f'potential = "{potential}"'))
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "3"])
    message = result.stderr.strip()
    assert result.exit_code == 1 and "\n" not in message, message
    assert message.startswith(f"error: quantum.potential = '{potential}' is not finite"), message


def test_a_spectrum_with_no_converged_level_exits_3(tmp_path):
    """V = 0: a free body has a continuous spectrum, so every candidate of a finite basis is
    unconverged. The command still writes its output (strict JSON, energies null) and then
    warns in one line and exits 3, as density does for an unconverged state (it exited 0)."""
    from affinebody.cli.common import EXIT_STOPPED

    path = tmp_path / "free.toml"
    path.write_text(UNBOUNDED.format(potential="0.0*trG") + "basis_size = 8\n")
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "2", "--json"])
    assert result.exit_code == EXIT_STOPPED, result.output
    data = json.loads(result.stdout)
    assert data["energies"] == [None, None]
    assert result.stderr.startswith("warning: no level converged") and \
        result.stderr.count("\n") == 1
