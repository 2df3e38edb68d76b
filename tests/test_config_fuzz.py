"""Hostile configs, generated: Hypothesis mutates the built-in demo config (a key deleted, an
unknown key added, a value replaced by another type, a huge or non-finite number, unicode, a
list of the wrong shape, a whole table dropped) and ``affinebody validate`` (load, both checking
passes, and the build with the initial state and energy) must answer each with exit 0, or with
exit 1 and a single line on stderr: never a traceback, never a hang (each example has a
deadline)."""

import json
import math
import tomllib

import click
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from affinebody._checks import enable_x64
from affinebody.cli.run import COMMANDS
from affinebody.runner import demo_config_text

BASE = tomllib.loads(demo_config_text())
CLI = click.Group("affinebody", commands={c.name: c for c in COMMANDS})


def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return repr(value)


def dump(data: dict) -> str:
    lines = []
    for name, table in data.items():
        for entry in table if isinstance(table, list) else [table]:
            lines.append(f"[[{name}]]" if isinstance(table, list) else f"[{name}]")
            lines += [f"{json.dumps(k)} = {toml_value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


HOSTILE = st.one_of(
    st.integers(-3, 20), st.sampled_from([10**9, 10**20, -(10**20), 0]),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e308, -1e308, 5e-324]),
    st.booleans(), st.text(max_size=12),
    st.lists(st.floats(-10, 10), max_size=4),
    st.lists(st.lists(st.integers(-2, 2), max_size=3), max_size=3),
)


@st.composite
def mutated(draw):
    data = json.loads(json.dumps(BASE))
    tables = [(name, k) if isinstance(v, list) else (name, None)
              for name, v in data.items() for k in (range(len(v)) if isinstance(v, list) else [0])]
    name, index = draw(st.sampled_from(tables))
    table = data[name] if index is None else data[name][index]
    action = draw(st.sampled_from(["replace", "replace", "replace", "delete", "extra", "drop"]))
    if action == "drop":
        del data[name]
    elif action == "extra":
        table[draw(st.text(min_size=1, max_size=8))] = draw(HOSTILE)
    else:
        key = draw(st.sampled_from(sorted(table)))
        if action == "delete":
            del table[key]
        else:
            table[key] = draw(HOSTILE)
    return dump(data)


@settings(max_examples=60, deadline=30_000, suppress_health_check=[HealthCheck.too_slow])
@given(text=mutated())
def test_any_mutated_config_is_accepted_or_refused_in_one_line(tmp_path_factory, text):
    enable_x64()
    path = tmp_path_factory.mktemp("fuzz") / "config.toml"
    path.write_text(text, encoding="utf-8")
    result = CliRunner().invoke(CLI, ["validate", str(path)])
    message = result.stderr.strip()
    assert result.exit_code in (0, 1), (text, result.output, message, result.exception)
    assert "Traceback" not in result.output + message
    if result.exit_code == 1:
        assert message and "\n" not in message, (text, message)
        assert not message.startswith("internal error"), (text, message)
    else:
        assert ": ok (" in result.output, (text, result.output)


@settings(max_examples=3, deadline=60_000, suppress_health_check=[HealthCheck.too_slow])
@given(text=mutated())
def test_a_mutated_config_runs_or_is_refused_and_never_leaves_a_broken_file(tmp_path_factory,
                                                                            text):
    """The same mutations through ``affinebody run`` (a few steps): exit 0 with a trajectory
    that opens and holds every frame, or a one-line refusal (exit 1) or stop (exit 3) that
    leaves either no file or one that opens."""
    from affinebody.h5md import read_trajectory

    enable_x64()
    folder = tmp_path_factory.mktemp("fuzzrun")
    path, out = folder / "config.toml", folder / "out.h5"
    path.write_text(text, encoding="utf-8")
    result = CliRunner().invoke(CLI, ["run", str(path), "-o", str(out), "--steps", "40",
                                      "--quiet"])
    message = result.stderr.strip()
    assert result.exit_code in (0, 1, 3), (text, result.output, message, result.exception)
    assert "Traceback" not in result.output + message
    if result.exit_code == 0:
        assert read_trajectory(out).frames >= 2
    else:
        assert message and "\n" not in message and not message.startswith("internal error")
        if out.exists():
            read_trajectory(out)  # opens: never half-written
