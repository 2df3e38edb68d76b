"""The potential kinds a config file can name (``[[potential]] kind = ...``), their parameters,
and :func:`build_potential`, which builds one with one-line ValueError messages."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from affinebody.potentials.library import (
    Dilatation,
    ExternalHarmonic,
    ExternalLinear,
    Gaussian,
    HarmonicInvariants,
    LennardJones,
    Morse,
    OneBodyPotential,
    PairPotential,
    StVenantKirchhoff,
)
from affinebody.potentials.terms import Cutoff


@dataclass(frozen=True)
class PotentialFamily:
    """A potential kind a config file can name: its parameters (name -> description)."""

    name: str
    kind: str  # "one-body" or "pair"
    summary: str
    parameters: Mapping[str, str]
    required: tuple[str, ...]
    build: Callable[[dict[str, Any], int, tuple[float, ...] | None], Any] = dataclasses.field(
        repr=False
    )


_CUTOFF_PARAMETERS = {
    "r_cut": "cut-off distance (optional; no cut-off if absent; required in a periodic box)",
    "r_on": "start of the C^2 switch (default 0.9 * r_cut)",
    "cutoff_on": "'r' or 'D': the variable the cut-off applies to (default: the argument, or r)",
}


def _cutoff_from(params: dict[str, Any], default: str) -> Cutoff | None:
    r_cut = params.pop("r_cut", None)
    r_on = params.pop("r_on", None)
    variable = params.pop("cutoff_on", default)
    if r_cut is None:
        if r_on is not None:
            raise ValueError("r_on given without r_cut")
        return None
    return Cutoff(r_cut, r_on, variable)


def _family_pair(cls):
    def build(params, n, box):
        argument = params.get("argument", "r")
        cutoff = _cutoff_from(params, argument if isinstance(argument, str) else "r")
        return cls(**params, cutoff=cutoff, box=box)

    return build


def _build_harmonic_invariants(params, n, box):
    cutoff = _cutoff_from(params, "r")
    return HarmonicInvariants(**params, cutoff=cutoff, box=box)


def _build_pair_expression(params, n, box):
    cutoff = _cutoff_from(params, "r")
    return PairPotential.from_expression(
        params.pop("expr"), n, cutoff=cutoff, box=box, field=params.pop("_field")
    )


def _build_one_body_expression(params, n, box):
    return OneBodyPotential.from_expression(params.pop("expr"), n, field=params.pop("_field"))


def _simple(cls):
    return lambda params, n, box: cls(**params)


_ARGUMENT = "'r' (default) or 'D' (affine distance (75), spatially affine invariant)"

POTENTIALS: dict[str, PotentialFamily] = {
    family.name: family
    for family in (
        PotentialFamily(
            "lennard-jones",
            "pair",
            "4 eps ((sigma/s)^12 - (sigma/s)^6), s = r or D",
            {
                "epsilon": "well depth (> 0)",
                "sigma": "length (> 0); minimum at 2^(1/6) sigma",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("epsilon", "sigma"),
            _family_pair(LennardJones),
        ),
        PotentialFamily(
            "morse",
            "pair",
            "depth ((1 - exp(-alpha (s - r0)))^2 - 1), s = r or D",
            {
                "depth": "well depth (> 0)",
                "alpha": "inverse width (> 0)",
                "r0": "position of the minimum (> 0)",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("depth", "alpha", "r0"),
            _family_pair(Morse),
        ),
        PotentialFamily(
            "gaussian",
            "pair",
            "amplitude exp(-s^2 / (2 width^2)), s = r or D",
            {
                "amplitude": "height (negative: attractive)",
                "width": "length (> 0)",
                "argument": _ARGUMENT,
                **_CUTOFF_PARAMETERS,
            },
            ("amplitude", "width"),
            _family_pair(Gaussian),
        ),
        PotentialFamily(
            "harmonic-invariants",
            "pair",
            "(k/2) sum_a (X_a - X0_a)^2, X = M_a (30) or K_a (28)",
            {
                "stiffness": "k (> 0)",
                "invariants": "'M' (default, affine) or 'K' (Euclidean)",
                "reference": "list of n reference values X0 (default n each)",
                **_CUTOFF_PARAMETERS,
            },
            ("stiffness",),
            _build_harmonic_invariants,
        ),
        PotentialFamily(
            "pair",
            "pair",
            "any expression in r, D, det, K1..Kn, M1..Mn (77)",
            {"expr": "expression, e.g. 'exp(-D**2) * (M1 - 2)**2'", **_CUTOFF_PARAMETERS},
            ("expr",),
            _build_pair_expression,
        ),
        PotentialFamily(
            "dilatation",
            "one-body",
            "sum_K f(det phi_K), eqs. (80), (81)",
            {
                "stiffness": "k (> 0)",
                "volume": "reference det v0 (> 0, default 1)",
                "form": "'log' (default): k/2 ln(|det|/v0)^2; 'harmonic': k/2 (det - v0)^2",
            },
            ("stiffness",),
            _simple(Dilatation),
        ),
        PotentialFamily(
            "elastic",
            "one-body",
            "St Venant-Kirchhoff lam/2 (Tr E)^2 + mu Tr(E^2), E of (32)",
            {"lam": "first Lame constant (lam + 2 mu / n > 0)", "mu": "shear modulus (> 0)"},
            ("lam", "mu"),
            _simple(StVenantKirchhoff),
        ),
        PotentialFamily(
            "external-harmonic",
            "one-body",
            "(k/2) |x - centre|^2 on every body",
            {"stiffness": "k (> 0)", "centre": "list of n numbers (default the origin)"},
            ("stiffness",),
            _simple(ExternalHarmonic),
        ),
        PotentialFamily(
            "external-linear",
            "one-body",
            "-force . x on every body (uniform field)",
            {"force": "list of n numbers"},
            ("force",),
            _simple(ExternalLinear),
        ),
        PotentialFamily(
            "one-body",
            "one-body",
            "any expression in x1..xn, det, trG, K1..Kn, I1..In, E1..En",
            {"expr": "expression, e.g. '10*(det - 1)**2'"},
            ("expr",),
            _build_one_body_expression,
        ),
    )
}


def build_potential(
    kind: str,
    params: Mapping[str, Any],
    *,
    n: int,
    box: Sequence[float] | None = None,
    field: str = "potential",
):
    """The potential a config names: ``kind`` from :data:`POTENTIALS` with ``params``.

    ``box`` (periodic box edges) applies to pair families only. Errors are one-line
    ``ValueError`` messages starting ``config error: <field>:``.
    """
    family = POTENTIALS.get(kind)
    if family is None:
        raise ValueError(
            f"config error: {field}.kind: unknown potential {kind!r} "
            f"(choose from {', '.join(POTENTIALS)})"
        )
    unknown = sorted(set(params) - set(family.parameters))
    if unknown:
        raise ValueError(
            f"config error: {field}: unknown parameter(s) {', '.join(unknown)} for {kind!r} "
            f"(allowed: {', '.join(family.parameters)})"
        )
    missing = [name for name in family.required if name not in params]
    if missing:
        raise ValueError(f"config error: {field}: {kind!r} needs {', '.join(missing)}")
    if box is not None and family.kind != "pair":
        box = None  # one-body terms do not see the box
    args = dict(params)
    if "expr" in family.parameters:
        args["_field"] = f"{field}.expr"
    try:
        return family.build(args, n, None if box is None else tuple(box))
    except ValueError as err:
        message = str(err)
        if message.startswith("config error"):
            raise
        raise ValueError(f"config error: {field}: {message}") from None
    except TypeError as err:
        raise ValueError(f"config error: {field}: {err}") from None


__all__ = ["POTENTIALS", "PotentialFamily", "build_potential"]
