"""affinebody: classical and quantum mechanics of affinely-rigid bodies.

The main entry points, importable from the package (loaded on first use, so that
``import affinebody`` and the command line start quickly)::

    from affinebody import State, KineticEnergy, HamiltonianSystem, run

- configurations and states: :class:`State` (x, phi, p, pi with leading batch axes),
  :class:`Space` (free space or a periodic box);
- models: :class:`KineticEnergy` with the translational and internal models of
  :mod:`affinebody.kinetic` (registries ``kinetic.MODELS``, ``kinetic.TRANSLATIONAL_MODELS``),
  the potentials of :mod:`affinebody.potentials` (:func:`total_potential`, pair and one-body
  terms from expressions in the paper's invariants);
- mechanics: :class:`HamiltonianSystem` (H = T + V on a configuration group), the integrators
  (registry ``integrators.INTEGRATORS``), and the run driver :func:`run` -> :class:`Trajectory`;
- the tool: :func:`load_config` / :func:`build` (TOML -> system and state),
  :func:`run_simulation` (config -> H5MD with checkpoints), :func:`read_trajectory`,
  :func:`run_sweep` (ensembles on Dask);
- quantum: :func:`solve_spectrum` (energy levels of one body, sector by sector).

The layers and what each module holds: docs/architecture.md.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: Public name -> (module, attribute): the package's API, imported on first access.
_API = {
    "State": ("affinebody.state", "State"),
    "Space": ("affinebody.space", "Space"),
    "KineticEnergy": ("affinebody.kinetic", "KineticEnergy"),
    "total_potential": ("affinebody.potentials", "total_potential"),
    "HamiltonianSystem": ("affinebody.system", "HamiltonianSystem"),
    "get_integrator": ("affinebody.integrators", "get_integrator"),
    "run": ("affinebody.simulate", "run"),
    "Trajectory": ("affinebody.simulate", "Trajectory"),
    "IntegrationStopped": ("affinebody.simulate", "IntegrationStopped"),
    "load_config": ("affinebody.config", "load_config"),
    "parse_config": ("affinebody.config", "parse_config"),
    "build": ("affinebody.config", "build"),
    "run_simulation": ("affinebody.runner", "run_simulation"),
    "read_trajectory": ("affinebody.h5md", "read_trajectory"),
    "run_sweep": ("affinebody.sweep", "run_sweep"),
    "solve_spectrum": ("affinebody.quantum.spectra", "solve"),
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        module, attribute = _API[name]
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value  # the next access is a plain attribute
        return value
    raise AttributeError(f"module 'affinebody' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
