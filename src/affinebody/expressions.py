"""Restricted arithmetic expressions for config files, compiled to JAX functions.

A config may give a potential as text, e.g. ``expr = "exp(-D**2) * (M1 - 2)**2"``. The text is
parsed with Python's :mod:`ast` module and *never* evaluated by Python: every node is checked
against a whitelist and turned into a closure over :mod:`jax.numpy`, so a config cannot run code,
touch attributes, import modules or allocate huge integers. The grammar accepted is

    expr   := number | variable | constant | expr op expr | (+|-) expr | (expr)
              | function(expr, ...)
    op     := + - * / **
    constant := pi | e

with the functions listed in :data:`FUNCTIONS`. Everything else (attributes, subscripts, calls of
anything but a whitelisted name, keyword arguments, strings, comparisons, conditionals, lambdas,
comprehensions, names not declared) is refused with a one-line ``ValueError`` naming the config
field and the offending part. Constant sub-expressions are folded in float64 and must stay finite,
so ``9**9**9`` is refused instead of computing a number with 370 million digits.

The compiled function takes the variables as keyword arguments (arrays broadcast together), and
is traceable by ``jax.jit``, ``jax.grad`` and ``jax.vmap``.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import jax.scipy.special as jsp

#: Longest expression text accepted (characters).
MAX_LENGTH = 2000
#: Deepest syntax tree accepted (nested operations).
MAX_DEPTH = 64
#: Largest |exponent| accepted for a literal exponent (``r**12`` fine, ``r**1e6`` a typo).
MAX_LITERAL_EXPONENT = 256

#: Whitelisted functions: name -> (jax function, number of arguments).
FUNCTIONS: Mapping[str, tuple[Callable[..., jax.Array], int]] = {
    "exp": (jnp.exp, 1),
    "log": (jnp.log, 1),
    "log1p": (jnp.log1p, 1),
    "expm1": (jnp.expm1, 1),
    "sqrt": (jnp.sqrt, 1),
    "cbrt": (jnp.cbrt, 1),
    "square": (jnp.square, 1),
    "sin": (jnp.sin, 1),
    "cos": (jnp.cos, 1),
    "tan": (jnp.tan, 1),
    "arcsin": (jnp.arcsin, 1),
    "asin": (jnp.arcsin, 1),
    "arccos": (jnp.arccos, 1),
    "acos": (jnp.arccos, 1),
    "arctan": (jnp.arctan, 1),
    "atan": (jnp.arctan, 1),
    "arctan2": (jnp.arctan2, 2),
    "atan2": (jnp.arctan2, 2),
    "sinh": (jnp.sinh, 1),
    "cosh": (jnp.cosh, 1),
    "tanh": (jnp.tanh, 1),
    "arcsinh": (jnp.arcsinh, 1),
    "asinh": (jnp.arcsinh, 1),
    "arccosh": (jnp.arccosh, 1),
    "acosh": (jnp.arccosh, 1),
    "arctanh": (jnp.arctanh, 1),
    "atanh": (jnp.arctanh, 1),
    "erf": (jsp.erf, 1),
    "erfc": (jsp.erfc, 1),
    "abs": (jnp.abs, 1),
    "min": (jnp.minimum, 2),
    "minimum": (jnp.minimum, 2),
    "max": (jnp.maximum, 2),
    "maximum": (jnp.maximum, 2),
}

#: Named constants.
CONSTANTS: Mapping[str, float] = {"pi": math.pi, "e": math.e}

_BINARY = {
    ast.Add: (jnp.add, "+"),
    ast.Sub: (jnp.subtract, "-"),
    ast.Mult: (jnp.multiply, "*"),
    ast.Div: (jnp.divide, "/"),
    ast.Pow: (jnp.power, "**"),
}
_UNARY = {ast.UAdd: (jnp.positive, "+"), ast.USub: (jnp.negative, "-")}

# Evaluation nodes are closures env -> value; constant nodes also carry their float value.
_Env = Mapping[str, jax.Array]
_Node = tuple[Callable[[_Env], jax.Array], float | None]


def _describe(node: ast.AST, text: str) -> str:
    """The source text of ``node`` (shortened), for error messages."""
    part = ast.get_source_segment(text, node) or type(node).__name__
    return part if len(part) <= 60 else part[:57] + "..."


class _Compiler:
    """Walks a parsed expression, refusing anything outside the grammar."""

    def __init__(self, text: str, variables: tuple[str, ...] | None, field: str):
        self.text = text
        self.variables = variables  # None: any plain identifier counts as a variable
        self.field = field
        self.used: list[str] = []

    def fail(self, message: str) -> ValueError:
        return ValueError(f"config error: {self.field}: {message}")

    def allowed(self) -> str:
        names = list(self.variables or ()) + sorted(CONSTANTS)
        return ", ".join(names)

    def compile(self, node: ast.AST, depth: int = 0) -> _Node:
        """Closure for ``node`` and its folded float value (None unless constant)."""
        if depth > MAX_DEPTH:
            raise self.fail(f"expression nested deeper than {MAX_DEPTH} levels")
        if isinstance(node, ast.Expression):
            return self.compile(node.body, depth + 1)
        if isinstance(node, ast.Constant):
            return self.constant(node)
        if isinstance(node, ast.Name):
            return self.name(node)
        if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            fn, _ = _UNARY[type(node.op)]
            operand, value = self.compile(node.operand, depth + 1)
            if value is not None:  # a constant, as a literal is (exact: a sign)
                return self.literal(-value if isinstance(node.op, ast.USub) else value)
            return (lambda env: fn(operand(env))), None
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            return self.binary(node, depth)
        if isinstance(node, ast.Call):
            return self.call(node, depth)
        hint = self.grammar_hint(node)
        raise self.fail(f"'{_describe(node, self.text)}' is not allowed ({hint})")

    def grammar_hint(self, node: ast.AST) -> str:
        if isinstance(node, ast.Attribute):
            return "no attribute access"
        if isinstance(node, ast.Subscript):
            return "no indexing"
        if isinstance(node, ast.Compare | ast.BoolOp | ast.IfExp):
            return "no comparisons or conditionals"
        if isinstance(node, ast.BinOp | ast.UnaryOp):
            return "operators allowed: + - * / ** and unary + -"
        return "only numbers, variables, + - * / **, parentheses and whitelisted functions"

    def constant(self, node: ast.Constant) -> _Node:
        value = node.value
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(f"'{_describe(node, self.text)}' is not a real number literal")
        try:
            number = float(value)
        except OverflowError:
            raise self.fail(f"number literal '{_describe(node, self.text)}' is too large") from None
        if not math.isfinite(number):
            raise self.fail(f"number literal '{_describe(node, self.text)}' is not finite")
        return self.literal(number)

    @staticmethod
    def literal(number: float) -> _Node:
        """A constant node: no operation on constants is left for run time (Pallas' Triton
        lowering has no rule for some of them, e.g. the negation of a literal in ``-3*r``,
        which the GPU pair kernel that evaluates f would meet)."""
        return (lambda env: jnp.asarray(number, dtype=jnp.float64)), number

    def name(self, node: ast.Name) -> _Node:
        ident = node.id
        if ident in CONSTANTS and (self.variables is None or ident not in self.variables):
            number = CONSTANTS[ident]
            return (lambda env: jnp.asarray(number, dtype=jnp.float64)), number
        known = (
            (not ident.startswith("_") and ident not in FUNCTIONS)
            if self.variables is None
            else ident in self.variables
        )
        if not known:
            if ident in FUNCTIONS:
                raise self.fail(f"function '{ident}' must be called, e.g. {ident}(x)")
            raise self.fail(f"unknown name '{ident}' (allowed: {self.allowed()})")
        if ident not in self.used:
            self.used.append(ident)
        return (lambda env: env[ident]), None

    def binary(self, node: ast.BinOp, depth: int) -> _Node:
        fn, symbol = _BINARY[type(node.op)]
        left, lvalue = self.compile(node.left, depth + 1)
        right, rvalue = self.compile(node.right, depth + 1)
        if symbol == "**" and rvalue is not None and abs(rvalue) > MAX_LITERAL_EXPONENT:
            raise self.fail(
                f"exponent in '{_describe(node, self.text)}' is {rvalue:.6g}; "
                f"|exponent| must be <= {MAX_LITERAL_EXPONENT}"
            )
        folded = None
        if lvalue is not None and rvalue is not None:
            folded = self.fold(node, _float_op(symbol, lvalue, rvalue))
            if symbol != "**":  # correctly rounded in Python as in XLA: the same float
                return self.literal(folded)
        return (lambda env: fn(left(env), right(env))), folded

    def call(self, node: ast.Call, depth: int) -> _Node:
        if not isinstance(node.func, ast.Name):
            raise self.fail(
                f"'{_describe(node, self.text)}' is not allowed: only whitelisted functions "
                f"may be called ({', '.join(sorted(FUNCTIONS))})"
            )
        ident = node.func.id
        if ident not in FUNCTIONS:
            raise self.fail(f"unknown function '{ident}' (allowed: {', '.join(sorted(FUNCTIONS))})")
        if node.keywords:
            raise self.fail(f"'{_describe(node, self.text)}': keyword arguments are not allowed")
        fn, arity = FUNCTIONS[ident]
        if any(isinstance(arg, ast.Starred) for arg in node.args):
            raise self.fail(f"'{_describe(node, self.text)}': starred arguments are not allowed")
        if len(node.args) != arity:
            raise self.fail(
                f"{ident}() takes {arity} argument{'s' if arity > 1 else ''} "
                f"(got {len(node.args)} in '{_describe(node, self.text)}')"
            )
        args = [self.compile(arg, depth + 1)[0] for arg in node.args]
        if arity == 1:
            (arg,) = args
            return (lambda env: fn(arg(env))), None
        return (lambda env: fn(*(a(env) for a in args))), None

    def fold(self, node: ast.AST, value: float | None) -> float:
        if value is None or not math.isfinite(value):
            raise self.fail(
                f"constant '{_describe(node, self.text)}' overflows or is undefined in float64"
            )
        return value


def _float_op(symbol: str, a: float, b: float) -> float | None:
    """``a symbol b`` in float arithmetic; None when it overflows or is undefined."""
    try:
        if symbol == "+":
            return a + b
        if symbol == "-":
            return a - b
        if symbol == "*":
            return a * b
        if symbol == "/":
            return a / b
        result = math.pow(a, b)
        return result
    except (OverflowError, ZeroDivisionError, ValueError):
        return None


def _parse(text: str, field: str) -> tuple[ast.Expression, str]:
    """The syntax tree of ``text`` and the stripped text it was parsed from."""
    if not isinstance(text, str):
        kind = type(text).__name__
        raise ValueError(f"config error: {field}: expression must be a string (got {kind})")
    if len(text) > MAX_LENGTH:
        raise ValueError(
            f"config error: {field}: expression is {len(text)} characters long "
            f"(at most {MAX_LENGTH})"
        )
    if not text.strip():
        raise ValueError(f"config error: {field}: expression is empty")
    stripped = text.strip()
    try:
        return ast.parse(stripped, mode="eval"), stripped
    except (SyntaxError, ValueError, RecursionError, MemoryError) as err:
        detail = getattr(err, "msg", None) or str(err) or type(err).__name__
        raise ValueError(f"config error: {field}: cannot parse '{text[:60]}': {detail}") from None


@dataclass(frozen=True)
class CompiledExpression:
    """A checked expression; call it with the variables as keyword arguments.

    Hashable and comparable by ``(text, variables)``, so it can be a static field of a jitted
    model. ``used`` lists the variables the text actually refers to.
    """

    text: str
    variables: tuple[str, ...]
    field: str = "expr"
    used: tuple[str, ...] = dataclasses.field(init=False, compare=False)
    _evaluate: Callable[[_Env], jax.Array] = dataclasses.field(
        init=False, repr=False, compare=False
    )

    def __post_init__(self):
        for name in self.variables:
            if not (isinstance(name, str) and name.isidentifier() and not name.startswith("_")):
                raise ValueError(f"variable name {name!r} must be an identifier not led by _")
        clash = sorted(set(self.variables) & (set(FUNCTIONS) | set(CONSTANTS)))
        if clash:
            raise ValueError(f"variable names {clash} clash with built-in functions or constants")
        tree, stripped = _parse(self.text, self.field)
        compiler = _Compiler(stripped, tuple(self.variables), self.field)
        try:
            evaluate, _ = compiler.compile(tree)
        except RecursionError:
            raise compiler.fail("expression is nested too deeply") from None
        object.__setattr__(self, "used", tuple(compiler.used))
        object.__setattr__(self, "_evaluate", evaluate)

    def __call__(self, **values) -> jax.Array:
        unknown = sorted(set(values) - set(self.variables))
        if unknown:
            raise TypeError(
                f"{self.field}: unexpected variables {unknown} "
                f"(declared: {', '.join(self.variables)})"
            )
        missing = [name for name in self.used if name not in values]
        if missing:
            raise TypeError(f"{self.field}: missing values for {missing}")
        env = {name: jnp.asarray(value, dtype=jnp.float64) for name, value in values.items()}
        return _broadcast_value(self, env)


@functools.partial(jax.jit, static_argnums=0)
def _broadcast_value(expression: CompiledExpression, env: _Env) -> jax.Array:
    """The value of ``expression`` over the broadcast shape of its variables and of itself:
    one compiled program per expression (equal expressions share it, being equal static
    arguments) and shapes, so that a call on concrete arrays (a quantum potential on its grid,
    a config check) is not compiled and dispatched operation by operation."""
    result = expression._evaluate(env)
    shape = jnp.broadcast_shapes(*(v.shape for v in env.values())) if env else ()
    return jnp.broadcast_to(result, jnp.broadcast_shapes(shape, jnp.shape(result)))


def compile_expression(
    text: str, variables: Sequence[str], *, field: str = "expr"
) -> CompiledExpression:
    """Check ``text`` against the restricted grammar and compile it to a JAX function.

    ``variables`` are the names the text may use (besides ``pi``, ``e`` and :data:`FUNCTIONS`);
    ``field`` names the config entry in error messages, e.g. ``"potential.0.expr"``. The result
    is called with keyword arguments, ``f(r=..., D=...)``; values broadcast together and the
    result has the broadcast shape. Raises ``ValueError`` for anything outside the grammar.
    """
    return CompiledExpression(text, tuple(variables), field)


def expression_variables(text: str, *, field: str = "expr") -> tuple[str, ...]:
    """The variable names ``text`` uses, in order of first appearance (grammar still checked).

    Function names and the constants ``pi``, ``e`` are not variables; names starting with ``_``
    are refused.
    """
    tree, stripped = _parse(text, field)
    compiler = _Compiler(stripped, None, field)
    try:
        compiler.compile(tree)
    except RecursionError:
        raise compiler.fail("expression is nested too deeply") from None
    return tuple(compiler.used)


# --------------------------------------------------------------------------------------------
# Source code of the value and the partial derivatives (compiled CPU kernels)

#: Scalar source of each whitelisted function and of its partial derivatives, keyed by the
#: JAX function (aliases share one entry): ``{0}``, ``{1}`` are the arguments, ``{t}`` the
#: value. The derivatives are JAX's own rules (``jax._src.lax``), kinks included: d|x|/dx = 1
#: at 0, min/max split the derivative evenly between equal arguments.
_SOURCE_RULES: Mapping[Callable[..., jax.Array], tuple[str, tuple[str, ...]]] = {
    jnp.exp: ("np.exp({0})", ("{t}",)),
    jnp.log: ("np.log({0})", ("1.0 / {0}",)),
    jnp.log1p: ("np.log1p({0})", ("1.0 / (1.0 + {0})",)),
    jnp.expm1: ("np.expm1({0})", ("{t} + 1.0",)),
    jnp.sqrt: ("np.sqrt({0})", ("0.5 / {t}",)),
    jnp.cbrt: ("np.cbrt({0})", ("(1.0 / 3.0) / ({t} * {t})",)),
    jnp.square: ("{0} * {0}", ("2.0 * {0}",)),
    jnp.sin: ("np.sin({0})", ("np.cos({0})",)),
    jnp.cos: ("np.cos({0})", ("-np.sin({0})",)),
    jnp.tan: ("np.tan({0})", ("1.0 + {t} * {t}",)),
    jnp.arcsin: ("np.arcsin({0})", ("1.0 / np.sqrt(1.0 - {0} * {0})",)),
    jnp.arccos: ("np.arccos({0})", ("-1.0 / np.sqrt(1.0 - {0} * {0})",)),
    jnp.arctan: ("np.arctan({0})", ("1.0 / (1.0 + {0} * {0})",)),
    jnp.arctan2: ("np.arctan2({0}, {1})", ("{1} / ({0} * {0} + {1} * {1})",
                                          "-{0} / ({0} * {0} + {1} * {1})")),
    jnp.sinh: ("np.sinh({0})", ("np.cosh({0})",)),
    jnp.cosh: ("np.cosh({0})", ("np.sinh({0})",)),
    jnp.tanh: ("np.tanh({0})", ("(1.0 + {t}) * (1.0 - {t})",)),
    jnp.arcsinh: ("np.arcsinh({0})", ("1.0 / np.sqrt({0} * {0} + 1.0)",)),
    jnp.arccosh: ("np.arccosh({0})", ("1.0 / np.sqrt({0} * {0} - 1.0)",)),
    jnp.arctanh: ("np.arctanh({0})", ("1.0 / (1.0 + {0}) / (1.0 - {0})",)),
    jsp.erf: ("math.erf({0})", ("_TWO_OVER_SQRT_PI * np.exp(-({0} * {0}))",)),
    jsp.erfc: ("math.erfc({0})", ("-_TWO_OVER_SQRT_PI * np.exp(-({0} * {0}))",)),
    jnp.abs: ("np.abs({0})", ("(1.0 if {0} >= 0.0 else -1.0)",)),
    jnp.minimum: ("np.minimum({0}, {1})", (
        "((1.0 if {0} == {t} else 0.0) / (2.0 if {1} == {t} else 1.0))",
        "((1.0 if {1} == {t} else 0.0) / (2.0 if {0} == {t} else 1.0))")),
    jnp.maximum: ("np.maximum({0}, {1})", (
        "((1.0 if {0} == {t} else 0.0) / (2.0 if {1} == {t} else 1.0))",
        "((1.0 if {1} == {t} else 0.0) / (2.0 if {0} == {t} else 1.0))")),
}

#: Source of the operators and of their partial derivatives, ``{0} op {1}`` as in
#: :data:`_SOURCE_RULES`; ``**``: JAX's ``lax.pow`` rules (d/dy uses log(x), x = 0 read as 1).
_OPERATOR_RULES: Mapping[str, tuple[str, tuple[str, ...]]] = {
    "+": ("{0} + {1}", ("1.0", "1.0")),
    "-": ("{0} - {1}", ("1.0", "-1.0")),
    "*": ("{0} * {1}", ("{1}", "{0}")),
    "/": ("{0} / {1}", ("1.0 / {1}", "-{0} / ({1} * {1})")),
    "**": ("{0} ** {1}", ("{1} * {0} ** ({1} - 1.0)",
                          "np.log({0} if {0} != 0.0 else 1.0) * {t}")),
    "u-": ("-{0}", ("-1.0",)),
    "u+": ("{0}", ("1.0",)),
}


def _literal(node: ast.AST) -> float | None:
    """The value of a number literal, signs included (``-6``), else None."""
    if isinstance(node, ast.Constant):
        return float(node.value)
    if isinstance(node, ast.UnaryOp):
        value = _literal(node.operand)
        if value is not None:
            return -value if isinstance(node.op, ast.USub) else value
    return None


def _product(power: int) -> str:
    """``{0}`` multiplied ``power`` >= 0 times (``1.0`` for 0)."""
    return " * ".join(["{0}"] * power) or "1.0"


def _integer_power(power: int) -> tuple[str, tuple[str, ...]]:
    """x ** power for a small integer literal as products (a libm pow call costs more than
    f; XLA itself rewrites pow(x, 2) as x * x), and its derivative power * x ** (power - 1),
    JAX's rule for lax.pow; equal to the pow values up to rounding."""
    if power > 0:
        return f"{_product(power)}", (f"{float(power)!r} * {_product(power - 1)}",)
    return (f"1.0 / ({_product(-power)})",
            (f"{float(power)!r} / ({_product(1 - power)})",))


class _SourceWriter:
    """Straight-line source of an accepted expression (one temporary per operation), then
    its reverse sweep: adjoints accumulated from the result back to the variables."""

    def __init__(self):
        self.lines: list[str] = []
        self.steps: list[tuple[str, list[tuple[str, bool]], tuple[str, ...]]] = []
        self.count = 0

    def walk(self, node: ast.AST) -> tuple[str, bool]:
        """(source of the node's value, whether it depends on a variable)."""
        if isinstance(node, ast.Expression):
            return self.walk(node.body)
        if isinstance(node, ast.Constant):
            return f"({float(node.value)!r})", False
        if isinstance(node, ast.Name):
            if node.id in CONSTANTS:  # a variable of that name was refused by the compiler
                return f"({CONSTANTS[node.id]!r})", False
            return f"v_{node.id}", True
        if isinstance(node, ast.UnaryOp):
            rule = _OPERATOR_RULES["u-" if isinstance(node.op, ast.USub) else "u+"]
            return self.operation(rule, [node.operand])
        if isinstance(node, ast.BinOp):
            exponent = _literal(node.right) if isinstance(node.op, ast.Pow) else None
            if exponent is not None and exponent.is_integer() and 1 <= abs(exponent) <= 8:
                return self.operation(_integer_power(int(exponent)), [node.left])
            return self.operation(_OPERATOR_RULES[_BINARY[type(node.op)][1]],
                                  [node.left, node.right])
        fn, _ = FUNCTIONS[node.func.id]  # a call: the compiler allowed only whitelisted ones
        return self.operation(_SOURCE_RULES[fn], node.args)

    def operation(self, rule, operands) -> tuple[str, bool]:
        args = [self.walk(operand) for operand in operands]
        value, partials = rule
        temp = f"_t{self.count}"
        self.count += 1
        self.lines.append(f"{temp} = {value.format(*(a for a, _ in args))}")
        if any(depends for _, depends in args):
            self.steps.append((temp, args, partials))
            return temp, True
        return temp, False


def derivative_source(expression: CompiledExpression, name: str) -> str:
    """Python source of a function ``name(v_x, v_y, ...)`` (one argument per name in
    ``expression.used``, in that order) returning ``(f, df/dx, df/dy, ...)`` for scalar
    float64 arguments, with NumPy's and :mod:`math`'s scalar functions (``np``, ``math``
    and ``_TWO_OVER_SQRT_PI`` are names the surrounding module defines): the form compiled
    by Numba in the host pair kernel (:mod:`affinebody._host_kernels.pair_expression`).

    The partial derivatives come from a reverse sweep over the expression's operations
    (each one's derivative by JAX's rule: the same values as ``jax.grad`` of the compiled
    expression, kinks included, up to rounding)."""
    tree, _ = _parse(expression.text, expression.field)
    writer = _SourceWriter()
    result, depends = writer.walk(tree)
    body = list(writer.lines) + [f"_v = {result}"]
    adjoint = {f"v_{v}": f"_d_{v}" for v in expression.used}
    body += [f"{adjoint[f'v_{v}']} = 0.0" for v in expression.used]
    if depends:
        adjoint[result] = "_a_result"
        body.append("_a_result = 1.0")
        for temp, _, _ in writer.steps:
            if temp != result:
                adjoint[temp] = f"_a{temp}"
                body.append(f"_a{temp} = 0.0")
        for temp, args, partials in reversed(writer.steps):
            for (arg, arg_depends), partial in zip(args, partials, strict=True):
                if arg_depends:
                    local = partial.format(*(a for a, _ in args), t=temp)
                    body.append(f"{adjoint[arg]} += {adjoint[temp]} * ({local})")
    outputs = ", ".join(["_v"] + [f"_d_{v}" for v in expression.used])
    arguments = ", ".join(f"v_{v}" for v in expression.used)
    return "\n".join([f"def {name}({arguments}):"] + [f"    {line}" for line in body]
                     + [f"    return {outputs}", ""])


__all__ = [
    "MAX_DEPTH", "MAX_LENGTH", "MAX_LITERAL_EXPONENT", "CompiledExpression",
    "compile_expression", "derivative_source", "expression_variables",
]
