"""Sample instances of every registered model, for the batteries parametrized over registries.

Kinetic models are built from the parameters they declare (``cls.parameters``): a sampler per
parameter name, so a new model with known parameter names needs nothing here. Potential
families are built from ``POTENTIAL_EXAMPLES`` (one config entry per ``potentials.POTENTIALS``
kind; ``test_contracts`` fails until a new kind has one).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from affinebody import kinetic as K

BODIES = 2


def spd(rng, n, shape=()):
    """Random symmetric positive definite matrices [*shape, n, n] (eigenvalues >= 0.5)."""
    a = rng.standard_normal(shape + (n, n))
    return a @ np.swapaxes(a, -1, -2) / n + 0.5 * np.eye(n)


def bitensor(rng, n, shape=()):
    """Random bi-tensors [*shape, n, n, n, n], symmetric positive definite on pairs."""
    m = rng.standard_normal(shape + (n * n, n * n))
    big = m @ np.swapaxes(m, -1, -2) / (n * n) + 0.5 * np.eye(n * n)
    return big.reshape(shape + (n, n, n, n))


#: One sampler per kinetic parameter name: (rng, n) -> a value with a body axis of BODIES.
#: I, A, B satisfy the positive-definite region of (73), (74) for n <= 3 and keep A and
#: A + nB away from 0 (af-af).
KINETIC_PARAMETERS = {
    "mass": lambda rng, n: np.array([1.0, 2.5]),
    "J": lambda rng, n: spd(rng, n, (BODIES,)),
    "H": lambda rng, n: spd(rng, n, (BODIES,)),
    "L": lambda rng, n: bitensor(rng, n, (BODIES,)),
    "R": lambda rng, n: bitensor(rng, n, (BODIES,)),
    "I": lambda rng, n: np.array([1.5, 1.4]),
    "A": lambda rng, n: np.array([0.7, 0.5]),
    "B": lambda rng, n: np.array([0.4, -0.1]),
}


def kinetic_sample(cls: type[K.AbstractKineticTerm], n: int, rng) -> K.AbstractKineticTerm:
    """An instance of ``cls`` with per-body parameters from ``KINETIC_PARAMETERS``."""
    return cls(**{name: KINETIC_PARAMETERS[name](rng, n) for name in cls.parameters})


def kinetic_zero(cls: type[K.AbstractKineticTerm], n: int) -> K.AbstractKineticTerm:
    """``cls`` with every parameter zero (shapes of the samples): degenerate for every model."""
    rng = np.random.default_rng(0)
    return cls(**{name: np.zeros_like(KINETIC_PARAMETERS[name](rng, n))
                  for name in cls.parameters})


def first_names(registry: dict) -> dict:
    """name -> class for the first name of each class of a registry (aliases dropped)."""
    out: dict = {}
    for name, cls in registry.items():
        if cls not in out.values():
            out[name] = cls
    return out


#: Translational models by their first registered name ("is-af" is d'Alembert's (63)).
TRANSLATIONAL = first_names(K.TRANSLATIONAL_MODELS)

# --------------------------------------------------------------------------------------------
# configurations and group elements for the potentials


def configuration(rng, bodies: int, n: int, spread: float = 0.8):
    """Random centres (compact, at least 0.3 apart) and configurations near the identity with
    det > 0."""
    while True:
        x = rng.uniform(-spread, spread, size=(bodies, n))
        gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.eye(bodies)
        if np.min(gaps) > 0.3:
            break
    phi = np.eye(n) + 0.3 * rng.normal(size=(bodies, n, n))
    phi[np.linalg.det(phi) < 0, 0] *= -1
    return jnp.asarray(x), jnp.asarray(phi)


def random_rotation(rng, n: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(n, n)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def random_linear(rng, n: int) -> np.ndarray:
    """A generic element of GL(n): well conditioned, det far from +-1, either sign."""
    while True:
        a = rng.normal(size=(n, n))
        s = np.linalg.svd(a, compute_uv=False)
        if s[-1] > 0.3 and s[0] < 3 and abs(abs(np.linalg.det(a)) - 1) > 0.2:
            return a


def transform(symmetry: str, rng, x, phi):
    n = phi.shape[-1]
    if symmetry == "translation":
        return x + rng.normal(size=n), phi
    if symmetry == "spatial-euclidean":
        r = random_rotation(rng, n)
        return x @ r.T, r @ phi
    if symmetry == "spatial-affine":
        a = random_linear(rng, n)
        return x @ a.T, a @ phi
    if symmetry == "material-euclidean":
        return x, phi @ random_rotation(rng, n)
    if symmetry == "material-affine":
        return x, phi @ random_linear(rng, n)
    raise AssertionError(symmetry)



#: A config entry of every potential kind, as a function of the dimension n.
POTENTIAL_EXAMPLES = {
    "lennard-jones": lambda n: {"epsilon": 0.7, "sigma": 0.6, "r_cut": 1.9, "r_on": 1.5},
    "morse": lambda n: {"depth": 1.3, "alpha": 1.7, "r0": 1.1, "argument": "D"},
    "gaussian": lambda n: {"amplitude": -1.1, "width": 0.9, "r_cut": 1.9},
    "harmonic-invariants": lambda n: {"stiffness": 0.8, "invariants": "K",
                                      "reference": [2.0 + a for a in range(n)]},
    "pair": lambda n: {"expr": "exp(-D**2) * (M1 - 2)**2", "r_cut": 1.9, "cutoff_on": "D"},
    "dilatation": lambda n: {"stiffness": 2.0, "volume": 1.2, "form": "harmonic"},
    "elastic": lambda n: {"lam": 0.4, "mu": 1.1},
    "external-harmonic": lambda n: {"stiffness": 1.2, "centre": [0.3 * (-1) ** a
                                                                for a in range(n)]},
    "external-linear": lambda n: {"force": [0.0] * (n - 1) + [-9.81]},
    "one-body": lambda n: {"expr": "10*(det - 1)**2"},
}
