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

#: Boltzmann's constant in each system's energy unit per kelvin, where the system has one
#: (k_B = 1 in the configs: a temperature is given as kT in energy units).
BOLTZMANN: dict[str, float] = {"gromacs": 0.0083144626181532}  # kJ/mol/K (CODATA 2018)
#: kT above this many kelvin is taken for a temperature given in kelvin by mistake (warned of):
#: no affine body model is meant for a plasma
PLAUSIBLE_KELVIN = 5000.0


def kelvin(units: str, kT: float) -> float | None:
    """The temperature in kelvin of kT in the energy unit of ``units``; None for reduced units,
    which have no kelvin."""
    return kT / BOLTZMANN[units] if units in BOLTZMANN else None


__all__ = ["UNIT_LABELS", "UNIT_SYSTEMS", "BOLTZMANN", "PLAUSIBLE_KELVIN", "kelvin"]
