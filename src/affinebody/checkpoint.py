"""Atomic checkpoints of a running simulation, for ``affinebody run --resume``.

A checkpoint holds the exact float64 state (x, phi, p, pi) at a step, the step itself, the
number of frames written up to it, the heat a thermostat put in up to it, the sizes of the
neighbour list in use (capacities and cell grid, which reallocations grow), and a hash of the
configuration that produced it. It is written to a temporary file in the same folder, fsync'ed
and then renamed over the previous checkpoint (``os.replace`` is atomic on POSIX), so a run
killed at any moment leaves either the old or the new checkpoint, never a half-written one.
Restarting the same compiled chunk function from this state reproduces the uninterrupted run
bit for bit.
"""

from __future__ import annotations

import io
import os
import tempfile
import zipfile
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from affinebody.state import State

FORMAT_VERSION = 1
#: the prefix of the neighbour-list sizes' entries in the file
_SIZES = "neighbor_sizes."


class CheckpointError(ValueError):
    """A missing, unreadable or mismatched checkpoint."""


@dataclass(frozen=True)
class Checkpoint:
    """Simulation state at ``step`` (time = step * dt) with bookkeeping for resuming."""

    step: int
    state: State
    frames: int
    config_hash: str
    #: the cell matrix [n, n] of a box that a barostat changes (None: the config's box)
    cell: np.ndarray | None = None
    #: heat put in by a thermostat up to ``step`` (0 for NVE runs)
    heat: float = 0.0
    #: the sizes of the run's neighbour list at ``step`` (``neighbors.sizes``: capacities and
    #: grid, grown by reallocations), from which the run and its resumption rebuild the list
    #: there (None: no list, or a checkpoint written before they were kept)
    neighbor_sizes: dict | None = None


def checkpoint_path(output: str | Path) -> Path:
    """Where the checkpoint of output file ``output`` lives: ``OUT.h5.checkpoint.npz``."""
    output = Path(output)
    return output.with_name(output.name + ".checkpoint.npz")


def save_checkpoint(path: str | Path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` atomically (temporary file, fsync, rename)."""
    path = Path(path)
    buffer = io.BytesIO()
    state = checkpoint.state
    np.savez(
        buffer,
        format_version=np.int64(FORMAT_VERSION),
        step=np.int64(checkpoint.step),
        frames=np.int64(checkpoint.frames),
        config_hash=np.asarray(checkpoint.config_hash),
        x=np.asarray(state.x, dtype=np.float64),
        phi=np.asarray(state.phi, dtype=np.float64),
        p=np.asarray(state.p, dtype=np.float64),
        pi=np.asarray(state.pi, dtype=np.float64),
        **({} if checkpoint.cell is None else {"cell": np.asarray(checkpoint.cell,
                                                                   dtype=np.float64)}),
        heat=np.float64(checkpoint.heat),
        **{f"{_SIZES}{name}": np.asarray(value)
           for name, value in (checkpoint.neighbor_sizes or {}).items()},
    )
    with replaced_atomically(path, "wb", durable=True) as handle:
        handle.write(buffer.getvalue())


@contextmanager
def replaced_atomically(path: str | Path, mode: str = "w", durable: bool = False,
                        permissions: int | None = None):
    """An open file (``mode``: "w" text in ASCII, or "wb") whose contents replace ``path``
    only when the block completes: written under a temporary name in the same folder and
    renamed into place (``os.replace``, atomic on POSIX), so an error or a kill leaves the
    previous file, or none, never a part. ``durable``: fsync the file and the folder first.
    ``permissions``: the file's mode bits (default: those of a temporary file, 0o600)."""
    path = Path(path)
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp",
                                             dir=path.parent)
    try:
        with os.fdopen(descriptor, mode, **({} if "b" in mode else {"encoding": "ascii"})) as f:
            yield f
            f.flush()
            if durable:
                os.fsync(f.fileno())
        if permissions is not None:
            os.chmod(temporary, permissions)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    if durable:
        _fsync_directory(path.parent)


def _fsync_directory(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def load_checkpoint(path: str | Path, config_hash: str | None = None,
                    changes: Callable[[], list[str]] | None = None) -> Checkpoint:
    """Read a checkpoint; with ``config_hash``, refuse one written for another configuration.
    ``changes``: called only then, the settings that differ from the run's config (the
    refusal names them, e.g. ``["run.dt = 0.005 -> 0.004"]``)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: run without --resume to start afresh")
    try:
        with np.load(path, allow_pickle=False) as data:
            version = int(data["format_version"])
            if version != FORMAT_VERSION:
                raise CheckpointError(f"{path}: checkpoint format {version} is not supported")
            checkpoint = Checkpoint(
                step=int(data["step"]),
                frames=int(data["frames"]),
                config_hash=str(data["config_hash"]),
                state=State(*(np.array(data[k]) for k in ("x", "phi", "p", "pi"))),
                cell=np.array(data["cell"]) if "cell" in data else None,
                heat=float(data["heat"]) if "heat" in data else 0.0,
                neighbor_sizes={k[len(_SIZES):]: np.array(data[k]) for k in data.files
                                if k.startswith(_SIZES)} or None,
            )
    except CheckpointError:
        raise
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as err:
        # the first sentence only: NumPy's refusal of pickled data goes on to say how to
        # load such a file unsafely, which is no advice for a damaged checkpoint
        detail = str(err).split(". ")[0]
        raise CheckpointError(
            f"{path}: unreadable checkpoint ({type(err).__name__}: {detail}): run without "
            f"--resume to start afresh"
        ) from None
    if config_hash is not None and checkpoint.config_hash != config_hash:
        changed = changes() if changes is not None else []
        what = f" (changed: {'; '.join(changed)})" if changed else ""
        raise CheckpointError(
            f"{path} was written for a different configuration{what}; resume with the same "
            "config (only run.steps / --steps may change), run without --resume, or start a "
            "new run from the output's last frame with [initial] file"
        )
    return checkpoint


__all__ = [
    "FORMAT_VERSION", "CheckpointError", "Checkpoint", "checkpoint_path", "save_checkpoint",
    "load_checkpoint", "replaced_atomically"
]
