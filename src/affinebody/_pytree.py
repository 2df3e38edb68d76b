"""One pytree convention for the models: frozen dataclasses registered with JAX.

``@dataclass`` makes a class a frozen dataclass and registers it as a JAX pytree (as jax-md's
``dataclasses.py``): fields are leaves (traced under ``jax.jit``, mapped by ``jax.tree.map``)
unless marked ``static_field()`` / ``field(static=True)``, in which case their values go into
the treedef (so they must be hashable, and a change of value means a new compilation).

A field may carry a ``converter``: a one-argument function applied to the value given to the
constructor (validation and normalisation, e.g. ``float`` with a range check). Converters run
before the class's own ``__post_init__`` (for checks across fields); they run again when JAX
rebuilds an instance from its treedef, so they must be idempotent. This module is the one place
that writes to a frozen instance (:func:`initialize`, for values derived from several fields).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

_STATIC = "static"
_CONVERTER = "converter"


def field(*, static: bool = False, converter: Callable[[Any], Any] | None = None,
          **kwargs) -> Any:
    """A dataclass field; ``static=True`` puts it in the treedef, ``converter`` normalises it."""
    metadata = dict(kwargs.pop("metadata", None) or {})
    metadata[_STATIC] = static
    if converter is not None:
        metadata[_CONVERTER] = converter
    return dataclasses.field(metadata=metadata, **kwargs)


def static_field(**kwargs) -> Any:
    """A field whose (hashable) value is part of the treedef: ``field(static=True, ...)``."""
    return field(static=True, **kwargs)


def is_static(f: dataclasses.Field) -> bool:
    """True for a field declared with ``static_field()`` / ``field(static=True)``."""
    return bool(f.metadata.get(_STATIC, False))


def initialize(obj: Any, **values: Any) -> None:
    """Set fields of a frozen dataclass while it is being constructed (``__post_init__`` only),
    for values that depend on several fields (e.g. a default computed from another field)."""
    for name, value in values.items():
        object.__setattr__(obj, name, value)


def dataclass(cls: type | None = None, *, static: bool = False):
    """Frozen dataclass registered as a JAX pytree; ``static=True`` makes every field static.

    Fields marked static (or all fields, with ``static=True``) are metadata of the treedef;
    the others are children. Field converters (:func:`field`) run first in ``__post_init__``.
    """

    def wrap(cls: type) -> type:
        post = cls.__dict__.get("__post_init__")
        if post is None:  # inherited: the user's hook of a decorated base, or a mixin's
            post = getattr(cls, "__pytree_post_init__", None) or getattr(cls, "__post_init__", None)
        cls.__pytree_post_init__ = post

        def __post_init__(self):
            for f in dataclasses.fields(self):
                converter = f.metadata.get(_CONVERTER)
                if converter is not None:
                    initialize(self, **{f.name: converter(getattr(self, f.name))})
            if post is not None:
                post(self)

        cls.__post_init__ = __post_init__
        dc = dataclasses.dataclass(frozen=True)(cls)
        fields = [f for f in dataclasses.fields(dc) if f.init]
        meta = tuple(f.name for f in fields if static or is_static(f))
        data = tuple(f.name for f in fields if f.name not in meta)
        return _register(dc, data, meta)

    return wrap if cls is None else wrap(cls)


def _register(cls: type, data: tuple[str, ...], meta: tuple[str, ...]) -> type:
    """Register ``cls`` as a pytree node: ``data`` fields are the children (keyed by
    ``GetAttrKey``, as ``jax.tree_util.register_dataclass`` keys them), the values of the
    ``meta`` fields the node's auxiliary data; rebuilding calls ``cls(**fields)``.

    Why not ``jax.tree_util.register_dataclass``: in jaxlib 0.10.1 the treedefs of two
    *different* classes registered that way compare equal when their static values are equal
    (``HAffine(H)`` and ``DAlembert(J)``; two potentials with equal parameters), though their
    hashes differ. ``jax.jit``'s cache then returns one class's compiled program for the other
    whenever their keys meet in a hash-table probe, which happens at random from one process
    to the next: a silently wrong flow or force (docs/architecture.md, "The pytree
    convention"; tests/test_contracts.py). A node registered with flatten functions compares
    its class, as it should.
    """

    keys = tuple(jax.tree_util.GetAttrKey(name) for name in data)

    def flatten(obj):
        return (tuple(getattr(obj, name) for name in data),
                tuple(getattr(obj, name) for name in meta))

    def flatten_with_keys(obj):
        children, aux = flatten(obj)
        return tuple(zip(keys, children, strict=True)), aux

    def unflatten(aux, children):
        return cls(**dict(zip(meta, aux, strict=True)), **dict(zip(data, children, strict=True)))

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
    return cls


def is_array_pytree(obj) -> bool:
    """True when ``obj`` can be an argument of a jitted function: a pytree with a hashable
    structure whose leaves are all arrays or numbers (the project's models; a user's model of
    another kind is closed over or called op by op instead)."""
    try:
        hash(jax.tree.structure(obj))
    except TypeError:
        return False
    return all(isinstance(leaf, jax.Array | np.ndarray | np.generic | float | int)
               for leaf in jax.tree.leaves(obj))


def compiled_for_models(fn: Callable) -> Callable:
    """``fn(model, *args)`` compiled once per model structure and argument shapes
    (``jax.jit``, the model an argument) when ``model`` is an array pytree
    (:func:`is_array_pytree`), else ``fn`` itself, op by op.

    For functions that set-up code and checks call on concrete arrays: compiled, their few
    dozen operations are one program instead of one compilation and dispatch each; inside a
    traced function the call is inlined."""
    jitted = jax.jit(fn)

    @functools.wraps(fn)
    def call(model, *args):
        return (jitted if is_array_pytree(model) else fn)(model, *args)

    return call


__all__ = ["compiled_for_models", "dataclass", "field", "initialize", "is_array_pytree",
           "is_static", "static_field"]
