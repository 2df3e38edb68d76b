"""Unit systems of the simulator's files and plots: the one list of names a config may give
as ``system.units`` (:data:`UNIT_SYSTEMS`), the H5MD unit string of each kind of quantity, and
the axis labels of the plots. In ``reduced`` units every number is a ratio to the config's own
scales (length, mass, energy; time sqrt(m l^2 / e)): the files then carry no unit attributes,
which MDAnalysis reads with ``convert_units=False`` (README, Output)."""

from __future__ import annotations

#: Unit systems a config may name (``system.units``): quantity kind -> H5MD unit string.
#: ``reduced`` has none: its numbers are dimensionless ratios (see the module docstring).
UNIT_SYSTEMS: dict[str, dict[str, str]] = {
    "reduced": {},
    "gromacs": {
        "length": "nm",
        "time": "ps",
        "mass": "u",
        "energy": "kJ mol-1",
        "momentum": "u nm ps-1",
        "action": "u nm+2 ps-1",  # pi (conjugate to the dimensionless phi), J, J - J^T
    },
}
#: Axis-label names of the units of each system (plots), by quantity kind.
UNIT_LABELS: dict[str, dict[str, str]] = {
    "reduced": {"length": "σ", "time": "τ", "mass": "m", "energy": "ε",
                "momentum": "m σ/τ", "action": "m σ²/τ"},
    "gromacs": {"length": "nm", "time": "ps", "mass": "u", "energy": "kJ/mol",
                "momentum": "u nm/ps", "action": "u nm²/ps"},
}

__all__ = ["UNIT_LABELS", "UNIT_SYSTEMS"]
