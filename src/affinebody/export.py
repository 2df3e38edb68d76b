"""Export of trajectories to extended XYZ for OVITO (ellipsoids from the two-polar decomposition).

A body of drawing radius r is the image of the ball |u| <= r under phi. With the two-polar
decomposition phi = L D R^T (paper, last section; :func:`affinebody.polar.two_polar`), L, R in
SO(n) and D = diag(exp q), the image is the ellipsoid with semi-axes r * exp(q_a) along the
columns of L (R^T maps the ball onto itself; for det phi < 0 the extra reflection does too).
So each frame line carries

- ``species:S:1``           :data:`SPECIES` ("body"), a name OVITO takes for no element,
- ``pos:R:3``               x (2D: z = 0),
- ``aspherical_shape:R:3``  r * singular values of phi (2D: a thin third axis ``thickness * r``),
- ``orientation:R:4``       the unit quaternion (x, y, z, w) of L, det L = +1, w >= 0,
- ``deform:R:9``            phi embedded in 3x3 (2D: phi (+) 1), column by column:
                            phi[0,0], phi[1,0], phi[2,0], phi[0,1], ...

which OVITO's extended-XYZ reader maps to Position, Aspherical Shape, Orientation and
Deformation Gradient. OVITO orders the nine components of a Deformation Gradient column by
column (XX, YX, ZX, XY, YY, ZY, XZ, YZ, ZZ; component "YX" is row y, column x), hence the
column order here: OVITO's Deformation Gradient of a body is its phi (files exported by
earlier versions had phi row by row, which OVITO read as phi^T). A periodic box becomes
``Lattice=`` with ``pbc=``, per frame.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the command line reads SPECIES from here for its help: no JAX, no h5py
    from affinebody import h5md

PROPERTIES = "species:S:1:pos:R:3:aspherical_shape:R:3:orientation:R:4:deform:R:9"
#: The species column of every body. OVITO's XYZ reader gives a type whose name begins with a
#: capitalised element symbol that element's colour, radius and mass ("B", "Body", "Bq", "C1"
#: are boron, boron, boron and carbon; "B" had made every body boron), and a lower-case name
#: none: "body" is drawn by its aspherical_shape alone, in a colour of OVITO's own.
SPECIES = "body"


def quaternion_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of 3x3 rotations [..., 3, 3] (Shepperd's method).

    Picks the numerically largest of 4w^2, 4x^2, 4y^2, 4z^2 to divide by, so it is accurate for
    every rotation, including half-turns.
    """
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m, axis1=-2, axis2=-1)
    choice = np.argmax(np.concatenate([np.diagonal(m, axis1=-2, axis2=-1), trace[..., None]], -1),
                       axis=-1)
    w = np.sqrt(np.maximum(1.0 + trace, 0.0)) / 2  # case "trace largest": divide by 4w
    q = np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1],
         4 * w * w],
        axis=-1,
    ) / np.maximum(4 * w, 1e-300)[..., None]
    for i in range(3):  # case "m_ii largest": divide by s = 4 q_i
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(np.maximum(1.0 + m[..., i, i] - m[..., j, j] - m[..., k, k], 0.0))
        safe = np.maximum(s, 1e-300)
        part = np.empty(m.shape[:-2] + (4,))
        part[..., i] = s / 4
        part[..., j] = (m[..., j, i] + m[..., i, j]) / safe
        part[..., k] = (m[..., k, i] + m[..., i, k]) / safe
        part[..., 3] = (m[..., k, j] - m[..., j, k]) / safe
        q = np.where((choice == i)[..., None], part, q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """3x3 rotation of unit quaternions (x, y, z, w), [..., 4] -> [..., 3, 3]."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def embed3(matrix: np.ndarray) -> np.ndarray:
    """n x n matrices (n = 1, 2 or 3) as 3 x 3: the axes beyond n get a 1 on the diagonal."""
    matrix = np.asarray(matrix, dtype=np.float64)
    n = matrix.shape[-1]
    if n == 3:
        return matrix
    out = np.zeros(matrix.shape[:-2] + (3, 3))
    out[..., :n, :n] = matrix
    for a in range(n, 3):
        out[..., a, a] = 1.0
    return out


def ellipsoids(phi: np.ndarray, radius: np.ndarray, thickness: float = 0.05):
    """Semi-axes [..., 3], orientation quaternions [..., 4] and 3x3 deform [..., 3, 3] of bodies.

    ``phi`` [..., N, n, n] with n = 1, 2 or 3, ``radius`` [N]. Uses phi = L diag(exp q) R^T
    (:func:`affinebody.polar.two_polar`, L in SO(n)); the quaternion is that of L (embedded as
    a rotation about z for n = 2, the identity for n = 1). The axes beyond n are thin:
    ``thickness`` x the radius.
    """
    from affinebody.polar import two_polar

    phi = np.asarray(phi, dtype=np.float64)
    n = phi.shape[-1]
    if n not in (1, 2, 3):
        raise ValueError(f"export needs n = 1, 2 or 3 (got n = {n})")
    radius = np.asarray(radius, dtype=np.float64)
    if n == 1:  # phi = |phi| sign(phi): L = 1
        bad = ~np.isfinite(phi[..., 0, 0]) | (phi[..., 0, 0] == 0)
        if np.any(bad):
            raise ValueError(f"phi is singular or not finite at batch index "
                             f"{tuple(int(i) for i in np.argwhere(bad)[0])}")
        axes, rotation = np.abs(phi[..., 0]) * radius[:, None], np.ones(phi.shape)
    else:
        decomposition = two_polar(phi)
        rotation = np.asarray(decomposition.L)
        axes = np.exp(np.asarray(decomposition.q)) * radius[:, None]
    thin = thickness * np.broadcast_to(radius[:, None], axes.shape[:-1] + (3 - n,))
    return (np.concatenate([axes, thin], -1), quaternion_from_rotation(embed3(rotation)),
            embed3(phi))


def deform_columns(deform: np.ndarray) -> np.ndarray:
    """3x3 matrices [..., 3, 3] as the nine ``deform`` columns [..., 9], column by column (the
    component order of OVITO's Deformation Gradient)."""
    deform = np.asarray(deform, dtype=np.float64)
    return np.swapaxes(deform, -1, -2).reshape(deform.shape[:-2] + (9,))


def _lattice(box: np.ndarray | None, n: int) -> str:
    if box is None:
        return ""
    edges = np.zeros(3)
    edges[:n] = np.asarray(box, dtype=np.float64)[:n]
    edges[n:] = 1.0
    cell = np.diag(edges).ravel()
    pbc = " ".join("T" if a < n else "F" for a in range(3))
    return f'Lattice="{" ".join(f"{v:.17g}" for v in cell)}" pbc="{pbc}" '


def write_xyz(
    trajectory: h5md.Trajectory,
    path: str | Path,
    *,
    every: int = 1,
    thickness: float = 0.05,
    species: str = SPECIES,
) -> int:
    """Write every ``every``-th frame of ``trajectory`` as extended XYZ; returns frames written.
    ``species``: the species column of every body, one word (default :data:`SPECIES`)."""
    if not species or species.split() != [species] or not species.isascii():
        raise ValueError(f"--species must be one word of ASCII characters, such as {SPECIES!r} "
                         f"(got {species!r})")
    if every < 1:
        raise ValueError(f"--every must be >= 1 (got {every})")
    if not (math.isfinite(thickness) and thickness > 0):
        raise ValueError(f"--thickness must be a finite number > 0, a fraction of the radius "
                         f"such as 0.05 (got {thickness})")
    n = trajectory.n
    frames = range(0, trajectory.frames, every)
    boxes = trajectory.boxes
    target = Path(path).resolve()
    if target.exists() and not target.is_file():  # a device or a pipe: written as it goes
        with open(target, "w", encoding="ascii") as out:
            _write_frames(trajectory, out, frames, boxes, n, thickness, species)
        return len(frames)
    # a file: written under a temporary name and renamed into place once complete, so a frame
    # that cannot be exported (a singular phi) leaves no partial file, and a previous export
    # to the same name intact
    from affinebody.checkpoint import replaced_atomically

    mask = os.umask(0)
    os.umask(mask)
    with replaced_atomically(target, "w", permissions=0o666 & ~mask) as out:
        _write_frames(trajectory, out, frames, boxes, n, thickness, species)
    return len(frames)


def _write_frames(trajectory: h5md.Trajectory, out, frames: range, boxes, n: int,
                  thickness: float, species: str) -> None:
    """The extended XYZ lines of ``frames`` to the open text file ``out``."""
    for frame in frames:  # one frame in memory at a time (open_trajectory reads lazily)
        lattice = _lattice(trajectory.box if boxes is None else boxes[frame], n)
        x, phi = trajectory.configuration(frame)
        try:
            axes, quat, deform = ellipsoids(phi, trajectory.radius, thickness)
        except ValueError as err:  # a singular phi: say which frame
            raise ValueError(f"frame {frame} (step {int(trajectory.step[frame])}): "
                             f"{err}") from None
        position = np.zeros((trajectory.bodies, 3))
        position[:, :n] = x
        out.write(f"{trajectory.bodies}\n")
        out.write(
            f"{lattice}Properties={PROPERTIES} "
            f"Time={trajectory.time[frame]:.17g} Step={int(trajectory.step[frame])}\n"
        )
        rows = np.concatenate(
            [position, axes, quat, deform_columns(deform)], axis=-1)
        fmt = species + " " + " ".join(["%.17g"] * rows.shape[1])
        np.savetxt(out, rows, fmt=fmt)


__all__ = [
    "PROPERTIES", "SPECIES", "quaternion_from_rotation", "rotation_from_quaternion", "embed3",
    "ellipsoids", "deform_columns", "write_xyz"
]
