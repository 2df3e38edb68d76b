"""What every JSON file and ``--json`` output of affinebody holds: plain, strict JSON.

Python's ``json.dumps`` writes NaN and infinities as the tokens ``NaN`` and ``Infinity``, which
strict readers (jq, JavaScript, most JSON libraries outside Python) refuse; a flagged density, an
unconverged level or a failed sample can hold them. :func:`json_safe` turns them into null (and
NumPy arrays and scalars into lists and Python numbers); :func:`json_text` is the text written.
"""

from __future__ import annotations

import json
import math

import numpy as np


def json_safe(value):
    """Plain JSON data for json.dumps: NumPy arrays and scalars as lists and Python numbers,
    NaN and infinities as null."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_text(value, **options) -> str:
    """``json.dumps`` of :func:`json_safe` (``value``): the text of every JSON file and
    ``--json`` output (``options``: json.dumps's, e.g. indent)."""
    return json.dumps(json_safe(value), **options)


__all__ = ["json_safe", "json_text"]
