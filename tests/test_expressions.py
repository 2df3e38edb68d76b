"""The restricted config-expression compiler: agrees with hand-written JAX, refuses code."""

import builtins

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody.expressions import (
    MAX_LENGTH,
    compile_expression,
    expression_variables,
)

PAIR_VARIABLES = ("r", "D", "K1", "K2", "M1", "M2", "det")
FIELD = "potential.0.expr"

# (text, the same function written by hand)
CASES = [
    (
        "exp(-D**2) * (M1 - 2)**2",
        lambda r, D, K1, K2, M1, M2, det: jnp.exp(-(D**2)) * (M1 - 2) ** 2,
    ),
    ("10*(det - 1)**2", lambda r, D, K1, K2, M1, M2, det: 10 * (det - 1) ** 2),
    (
        "4*1.5*((0.9/r)**12 - (0.9/r)**6)",
        lambda r, D, K1, K2, M1, M2, det: 6.0 * ((0.9 / r) ** 12 - (0.9 / r) ** 6),
    ),
    (
        "2.0*(1 - exp(-1.3*(D - 1.1)))**2 - 2.0",
        lambda r, D, K1, K2, M1, M2, det: 2.0 * (1 - jnp.exp(-1.3 * (D - 1.1))) ** 2 - 2.0,
    ),
    (
        "sqrt(K1) + log(K2) - cbrt(M2) + atan(r) * tanh(D) / cosh(M1) + sinh(det)",
        lambda r, D, K1, K2, M1, M2, det: (
            jnp.sqrt(K1)
            + jnp.log(K2)
            - jnp.cbrt(M2)
            + jnp.arctan(r) * jnp.tanh(D) / jnp.cosh(M1)
            + jnp.sinh(det)
        ),
    ),
    (
        "max(r, D) - min(K1, M1) + abs(-r) + log1p(D) + expm1(-r)"
        " + sin(pi*r)*cos(e*D) + tan(0.1*r)",
        lambda r, D, K1, K2, M1, M2, det: (
            jnp.maximum(r, D)
            - jnp.minimum(K1, M1)
            + jnp.abs(-r)
            + jnp.log1p(D)
            + jnp.expm1(-r)
            + jnp.sin(jnp.pi * r) * jnp.cos(jnp.e * D)
            + jnp.tan(0.1 * r)
        ),
    ),
    ("-r**2 + +D - -1e-3*K1", lambda r, D, K1, K2, M1, M2, det: -(r**2) + D + 1e-3 * K1),
    ("2**-1 * r**0.5 / (1 + D)", lambda r, D, K1, K2, M1, M2, det: 0.5 * r**0.5 / (1 + D)),
]


def random_inputs(seed: int, shape=(7,)) -> dict:
    """Positive random values for every pair variable (logs and roots stay defined)."""
    rng = np.random.default_rng(seed)
    return {name: jnp.asarray(rng.uniform(0.5, 2.5, size=shape)) for name in PAIR_VARIABLES}


@pytest.mark.parametrize("text, reference", CASES)
def test_agrees_with_hand_written_jax(text, reference):
    f = compile_expression(text, PAIR_VARIABLES, field=FIELD)
    for seed in range(3):
        values = random_inputs(seed)
        used = {k: v for k, v in values.items() if k in f.used}
        np.testing.assert_allclose(f(**values), reference(**values), rtol=1e-14, atol=1e-14)
        # only the variables the text mentions need to be passed
        np.testing.assert_allclose(f(**used), reference(**values), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("text, reference", CASES)
def test_gradients_jit_and_vmap_match_hand_written(text, reference):
    f = compile_expression(text, PAIR_VARIABLES, field=FIELD)
    values = random_inputs(11, shape=())
    args = tuple(values[name] for name in PAIR_VARIABLES)

    def compiled(*a):
        return f(**dict(zip(PAIR_VARIABLES, a, strict=True)))

    argnums = tuple(range(len(PAIR_VARIABLES)))
    got = jax.jit(jax.grad(compiled, argnums=argnums))(*args)
    want = jax.grad(reference, argnums=argnums)(*args)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    batch = random_inputs(12, shape=(5,))
    batch_args = tuple(batch[name] for name in PAIR_VARIABLES)
    np.testing.assert_allclose(
        jax.vmap(compiled)(*batch_args), reference(*batch_args), rtol=1e-14, atol=1e-14
    )


def test_gradient_against_closed_form():
    # d/dD [exp(-D^2) (M1 - 2)^2] = -2 D exp(-D^2) (M1 - 2)^2
    f = compile_expression("exp(-D**2) * (M1 - 2)**2", PAIR_VARIABLES)
    d, m = 0.7, 3.5
    got = jax.grad(lambda t: f(D=t, M1=m))(d)
    assert got == pytest.approx(-2 * d * np.exp(-(d**2)) * (m - 2) ** 2, rel=1e-14)


def test_constant_expression_broadcasts_to_inputs():
    f = compile_expression("2*pi", ("r",))
    out = f(r=jnp.ones((3, 4)))
    assert out.shape == (3, 4)
    np.testing.assert_allclose(out, 2 * np.pi)


def test_variables_used_and_expression_variables():
    f = compile_expression("K1 + exp(-D) * K1 + pi", PAIR_VARIABLES)
    assert f.used == ("K1", "D")
    assert expression_variables("10*(det - 1)**2 + e*x + exp(y)") == ("det", "x", "y")


def test_compiled_expression_is_hashable_static():
    a = compile_expression("r**2", ("r",))
    b = compile_expression("r**2", ("r",))
    assert a == b and hash(a) == hash(b)
    assert a != compile_expression("r**3", ("r",))
    g = jax.jit(lambda fn, r: fn(r=r), static_argnums=0)
    assert float(g(a, 3.0)) == 9.0


HOSTILE = [
    ("__import__('os').system('x')", "__import__"),
    ("().__class__", "__class__"),
    ("().__class__.__bases__[0].__subclasses__()", "__"),
    ("open('f')", "open"),
    ("a.b", "a.b"),
    ("r.real", "r.real"),
    ("x[0]", "x[0]"),
    ("lambda: 1", "lambda"),
    ("9**9**9", "exponent"),
    ("10**400", "exponent"),
    ("1e308*1e308", "overflows"),
    ("r**100000", "exponent"),
    ("os", "unknown name 'os'"),
    ("exec('1')", "exec"),
    ("eval('1')", "eval"),
    ("getattr(r, 'x')", "getattr"),
    ("sqrt(x=1)", "keyword"),
    ("exp(*r)", "starred"),
    ("exp(r, r)", "argument"),
    ("exp", "must be called"),
    ("'abc'", "'abc'"),
    ("b'abc'", "b'abc'"),
    ("1j", "1j"),
    ("True", "True"),
    ("None", "None"),
    ("r < 1", "comparisons"),
    ("r if D else 1", "conditionals"),
    ("r and D", "conditionals"),
    ("[r for r in D]", "[r for r in D]"),
    ("{r}", "{r}"),
    ("(r, D)", "(r, D)"),
    ("f'{r}'", "f'{r}'"),
    ("r // 2", "operators"),
    ("r % 2", "operators"),
    ("r @ D", "operators"),
    ("~r", "operators"),
    ("r := 1", "parse"),
    ("import os", "parse"),
    ("r; 1", "parse"),
    ("", "empty"),
    ("x" * (MAX_LENGTH + 1), "characters"),
    ("-" * 500 + "r", "nested"),
    ("(" * 300 + "r" + ")" * 300, "parse"),
    ("_r", "unknown name '_r'"),
    ("exp.__call__(r)", "__call__"),
    ("(lambda: 1)()", "lambda"),
]


@pytest.mark.parametrize("text, offending", HOSTILE)
def test_hostile_or_malformed_text_is_refused_naming_field_and_part(text, offending):
    with pytest.raises(ValueError) as info:
        compile_expression(text, PAIR_VARIABLES, field=FIELD)
    message = str(info.value)
    assert message.startswith(f"config error: {FIELD}: ")
    assert offending in message
    assert "\n" not in message


def test_unknown_name_lists_allowed_names():
    with pytest.raises(ValueError, match=r"unknown name 'q' \(allowed: r, D, K1, K2, M1, M2, det"):
        compile_expression("q + r", PAIR_VARIABLES, field=FIELD)


def test_refused_text_never_reaches_python_builtins(monkeypatch):
    marker = "affinebody_marker_never_used"
    seen = []

    def spying(real):
        def wrapper(*args, **kwargs):
            seen.extend(a for a in args if isinstance(a, str) and marker in a)
            return real(*args, **kwargs)

        return wrapper

    for name in ("open", "__import__", "eval", "exec", "print"):
        monkeypatch.setattr(builtins, name, spying(getattr(builtins, name)))
    for call in ("open", "__import__", "eval", "exec", "print"):
        with pytest.raises(ValueError):
            compile_expression(f"{call}('{marker}')", PAIR_VARIABLES)
    assert seen == []


def test_expression_variables_also_refuses_code():
    for text in ("__import__('os')", "a.b", "x[0]", "lambda: 1"):
        with pytest.raises(ValueError, match="config error"):
            expression_variables(text)


def test_declared_names_may_not_shadow_functions_or_be_private():
    with pytest.raises(ValueError, match="clash"):
        compile_expression("exp", ("exp",))
    with pytest.raises(ValueError, match="identifier"):
        compile_expression("r", ("_r",))


def test_unexpected_or_missing_arguments_are_type_errors():
    f = compile_expression("r + D", ("r", "D"))
    with pytest.raises(TypeError, match="unexpected"):
        f(r=1.0, D=1.0, q=2.0)
    with pytest.raises(TypeError, match="missing"):
        f(r=1.0)
