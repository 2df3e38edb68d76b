"""Thermostatted sweeps (NVT and NPT samples, ``affinebody sweep`` with [thermostat] and
[barostat]) against exact canonical and isothermal-isobaric results.

Bodies with d'Alembert kinetic energies (6), (52) on L(2) (singular phi allowed) in the
harmonic one-body potential 0.5 Tr G = 0.5 |phi|^2, no pair forces: every internal degree of
freedom is a harmonic oscillator (Lebesgue measure), the centres are free. Per body n/2 + n^2
quadratic terms, so in NVT <E> = N (n/2 + n^2) kT and C_V = var(E)/kT^2 = N (n/2 + n^2) exactly.
In NPT (stochastic cell rescaling, measure dV) the volume of the free centres is Gamma
distributed: <V> = (N + 1) kT / P, var(V) = (N + 1) (kT/P)^2, so kappa_T = var(V)/(kT <V>) = 1/P,
<P_inst> = N kT <1/V> = P, and C_P = var(E + P V)/kT^2 = N (n/2 + n^2) + N + 1.
Every comparison is against the standard error across independent samples (and a small
allowance for the bias of a variance measured over a finite run, about 1/(effective
measurements)).
"""

import math
import re
import textwrap
import warnings

import numpy as np
import pytest

from affinebody.cli.sweep import summary_lines
from affinebody.config import check_config, parse_config
from affinebody.sweep import run_sweep

N, n = 4, 2
QUADRATIC = N * (n / 2 + n * n)  # quadratic terms of H: C_V in units of k_B

BASE = textwrap.dedent("""
    [system]
    n = 2
    group = "L"
    bodies = 4
    {box}
    [body]
    mass = 1.0
    inertia = 1.0
    [kinetic]
    translational = "dalembert"
    internal = "dalembert"
    [[potential]]
    kind = "one-body"
    expr = "0.5*trG"
    [initial]
    x = [[0.2, 0.3], [1.2, 0.3], [0.2, 1.5], [1.2, 1.5]]
    [run]
    dt = {dt}
    steps = 4000
    every = 10
    [thermostat]
    kind = "langevin"
    temperature = 1.0
    friction = {friction}
    {barostat}
    [sweep]
    samples = 16
    seed = 3
    batch = 16
    equilibration = 400
    scan = {scan}
""")
NVT = BASE.format(box="", dt=0.05, friction=1.0, barostat="",
                  scan='{ "thermostat.temperature" = [0.5, 2.0] }')
NPT = BASE.format(box="box = [2.0, 2.5]", dt=0.01, friction=2.0,
                  barostat="[barostat]\npressure = 1.0\ntau = 0.5\ncompressibility = 1.0",
                  scan='{ "barostat.pressure" = [0.5, 2.0] }')


def load(text):
    return check_config(parse_config(text))


def table_cells(lines):
    """The header and the rows of the sweep command's table, as lists of cells (columns are
    at least two spaces apart, a cell's "mean ± error" one)."""
    rows = [re.split(r"\s{2,}", line.strip()) for line in lines]
    start = next(i for i, row in enumerate(rows) if "<E>" in row)
    return [rows[start], *(row for row in rows[start + 2:] if len(row) == len(rows[start]))]


def close(point, name, exact, allowance=0.0):
    mean, error = point[name], point[f"{name}_error"]
    assert abs(mean - exact) < 4 * error + allowance * abs(exact), (name, mean, error, exact)


def test_nvt_sweep_samples_equipartition_and_the_exact_heat_capacity(tmp_path):
    result = run_sweep(load(NVT), workers=0, output=tmp_path)
    assert result.summary["ensemble"] == "NVT"
    assert set(result.status.ravel()) == {"sampled"}
    for point, kt in zip(result.summary["points"], (0.5, 2.0), strict=True):
        assert point["temperature"] == kt and point["measurements"] == 360  # after 400 steps
        close(point, "mean_translational_temperature", kt)
        close(point, "mean_internal_temperature", kt)
        close(point, "mean_total_energy", QUADRATIC * kt)
        close(point, "mean_potential_energy", N * n * n / 2 * kt)
        close(point, "heat_capacity", QUADRATIC, allowance=0.05)
        # sharp enough to fail: 3% of kT, 5% of C
        assert point["mean_internal_temperature_error"] < 0.03 * kt
        assert point["heat_capacity_error"] < 0.05 * QUADRATIC
    header = (tmp_path / "samples.csv").read_text().splitlines()[0].split(",")
    assert header[:5] == ["point", "sample", "thermostat.temperature", "status", "failure"]
    assert "heat_capacity" in header and "var_total_energy" in header


def test_npt_sweep_follows_the_isobaric_ideal_gas_law():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # moves of at most 0.08 of the relaxation time
        result = run_sweep(load(NPT), workers=0)
    assert result.summary["ensemble"] == "NPT"
    assert set(result.status.ravel()) == {"sampled"}
    kt = 1.0
    for point, pressure in zip(result.summary["points"], (0.5, 2.0), strict=True):
        volume = (N + 1) * kt / pressure
        close(point, "mean_volume", volume)
        # the law N kT / P of the measure dV/V would be 20% lower: the test tells them apart
        assert point["mean_volume_error"] < 0.05 * volume
        close(point, "mean_pressure", pressure)
        close(point, "compressibility", 1.0 / pressure, allowance=0.05)
        close(point, "heat_capacity", QUADRATIC + N + 1, allowance=0.05)
        close(point, "mean_translational_temperature", kt)
        close(point, "mean_internal_temperature", kt)
        assert math.isnan(point["rejected_fraction"])  # plain moves: nothing to reject
        # a move of dt: K = -dP/d ln V along it is (1 + 2/n) P_inst at the last state, whose
        # mean over the samples is P (the barostat's measure dV), beta_T = 1, tau = 0.5
        close(point, "move_length", (1 + 2 / n) * pressure * 0.01 / 0.5)
    # the command's table shows kappa_T and the move length of each point (no rejections:
    # plain moves), each as mean ± error with the mean rounded at the error's second digit
    table = table_cells(summary_lines(result.summary))
    assert "rejected" not in table[0]
    for point, row in zip(result.summary["points"], table[1:], strict=True):
        assert float(row[0]) == point["parameters"]["barostat.pressure"]
        for name, column in (("compressibility", "kappa_T"), ("move_length", "move")):
            mean, error = map(float, row[table[0].index(column)].split(" ± "))
            assert abs(error - point[name + "_error"]) <= 0.06 * error, (name, row)
            assert abs(mean - point[name]) <= 0.06 * error, (name, row)


def test_a_negative_move_length_shows_as_unstable_in_the_table():
    """A point whose bulk modulus under a move is negative (a lattice under tension,
    docs/pressure.md) has a negative mean move length, which is no length: the table says
    "unstable" there and the usual mean ± error elsewhere."""
    quantities = ("mean_total_energy", "mean_translational_temperature",
                  "mean_internal_temperature", "mean_pressure", "mean_volume", "heat_capacity",
                  "compressibility", "move_length", "rejected_fraction")

    def point(index, move):
        values = {k: 1.0 for k in quantities} | {"move_length": move,
                                                 "rejected_fraction": math.nan}
        return {"index": index, "parameters": {"barostat.pressure": -7.5 + index},
                "sampled": 4, "failed": 0, "failures": {},
                **values, **{k + "_error": 0.1 for k in quantities}}

    summary = {"ensemble": "NPT", "samples": 4, "horizon": 1.0, "equilibration": 10,
               "points": [point(0, -0.0016), point(1, 0.02)], "total_samples": 8, "failed": 0,
               "wall_seconds": 1.0, "workers": 1, "scheduler": "local"}
    table = table_cells(summary_lines(summary))
    column = table[0].index("move")
    assert table[1][column] == "unstable (K < 0)"
    assert float(table[2][column].split(" ± ")[0]) == pytest.approx(0.02)


def test_a_scan_of_the_time_step_shows_each_points_horizon_and_values_as_written():
    """run.dt scanned over {start, stop, num}: each point runs steps x its own dt, so the
    table's title may not give one horizon (it gave the base config's) and a column gives
    each point's; the values show as written (0.15, not 0.15000000000000002)."""
    quantities = ("mean_total_energy", "mean_translational_temperature",
                  "mean_internal_temperature", "mean_pressure", "mean_volume", "heat_capacity")
    dts = np.linspace(0.1, 0.2, 3)
    assert repr(float(dts[1])) != "0.15"  # the range's arithmetic, as the sweep makes it
    points = [{"index": i, "parameters": {"run.dt": float(dt)}, "horizon": 200 * float(dt),
               "sampled": 4, "failed": 0, "failures": {}, **{k: 1.0 for k in quantities},
               **{k + "_error": 0.1 for k in quantities}} for i, dt in enumerate(dts)]
    summary = {"ensemble": "NVT", "samples": 4, "horizon": 2.0, "equilibration": 10,
               "points": points, "total_samples": 12, "failed": 0, "wall_seconds": 1.0,
               "workers": 1, "scheduler": "local"}
    lines = summary_lines(summary)
    assert "horizon per point" in lines[0] and "2 time units" not in lines[0]
    table = table_cells(lines)
    assert [row[table[0].index("run.dt")] for row in table[1:]] == ["0.1", "0.15", "0.2"]
    shown = [float(row[table[0].index("horizon")]) for row in table[1:]]
    np.testing.assert_allclose(shown, 200 * dts, rtol=1e-6)


def test_npt_sweep_with_tested_moves_follows_the_law_at_moves_five_times_as_long():
    """dt = 0.05: the volume relaxes at beta_T P / tau = 4 at P0 = 2, a move is 0.2 of that
    time, and the plain moves' boxes run away (by hand: <V> = 30 +- 16 for 2.5); with the
    Metropolis test the samples follow (N + 1) kT / P, and the sweep reports the fraction of
    the moves rejected, larger where the moves are longer against the relaxation time."""
    text = NPT.replace("dt = 0.01", "dt = 0.05").replace(
        "compressibility = 1.0", "compressibility = 1.0\nmetropolis = true")
    result = run_sweep(load(text), workers=0)
    assert set(result.status.ravel()) == {"sampled"}
    rejected = []
    for point, pressure in zip(result.summary["points"], (0.5, 2.0), strict=True):
        volume = (N + 1) * 1.0 / pressure
        close(point, "mean_volume", volume)
        assert point["mean_volume_error"] < 0.05 * volume
        close(point, "mean_pressure", pressure)
        rejected.append(point["rejected_fraction"])
        assert point["rejected_fraction_error"] < 0.1 * point["rejected_fraction"]
        close(point, "move_length", (1 + 2 / n) * pressure * 0.05 / 0.5)
    assert 0.01 < rejected[0] < rejected[1] < 0.5, rejected
    table = table_cells(summary_lines(result.summary))
    shown = [float(row[table[0].index("rejected")].split(" ± ")[0]) for row in table[1:]]
    np.testing.assert_allclose(shown, rejected, rtol=0.01)  # the table's "rejected" column


def test_a_sweep_with_long_plain_moves_says_where_in_one_line():
    from affinebody import barostat
    from affinebody.sweep import long_moves_warning

    assert long_moves_warning([0.02, 0.08, math.nan]) is None
    message = long_moves_warning([0.1, 0.4, 1.3, math.nan])
    assert "up to 1.3 of the volume's relaxation time" in message and "\n" not in message
    assert "over 0.25 at 2 of 3 points" in message and "metropolis = true" in message
    # the same words as the run's warning: var(V)'s factor at the longest, unstable past 2
    assert f"var(V) about {barostat.variance_factor(1.3):.2g}x" in message
    assert "heat_capacity" in message
    assert "unstable past 2" in long_moves_warning([0.1, 2.5])


def test_thermal_sweep_tables_are_checked_in_one_line():
    from affinebody.config import ConfigError

    no_thermostat = NPT[:NPT.index("[thermostat]")] + NPT[NPT.index("[barostat]"):].replace(
        "compressibility = 1.0", "compressibility = 1.0\ntemperature = 1.0")
    cases = (
        (NVT.replace("equilibration = 400", "equilibration = 3995"), "sweep.equilibration"),
        (NVT.replace("every = 10", "every = 7"), "multiple of run.every"),
        (no_thermostat, "needs a [thermostat]"),
    )
    for text, words in cases:
        with pytest.raises(ConfigError) as err:
            run_sweep(load(text), workers=0)
        assert words in str(err.value) and "\n" not in str(err.value)


def test_table_values_are_rounded_at_the_second_digit_of_their_error():
    """Every "mean ± error" of the sweep tables reads back as the mean within half a unit of
    the error's second significant digit, and the error to two digits, over twelve decades."""
    from affinebody.cli.sweep import _with_error

    rng = np.random.default_rng(7)
    for _ in range(2000):
        error = 10.0 ** rng.uniform(-9, 9)
        mean = rng.choice([-1, 1]) * error * 10.0 ** rng.uniform(-1, 4)
        mean_text, error_text = _with_error(mean, error).split(" ± ")
        shown_mean, shown_error = float(mean_text), float(error_text)
        unit = 10.0 ** (math.floor(math.log10(shown_error)) - 1)
        assert abs(shown_error - error) <= 0.5 * unit * (1 + 1e-9), (mean, error, error_text)
        assert abs(shown_mean - mean) <= 0.5 * unit * (1 + 1e-9), (mean, error, mean_text)
        if "e" not in mean_text:  # as many decimals as the error (none past its 2nd digit)
            assert len(mean_text.partition(".")[2]) == len(error_text.partition(".")[2])
