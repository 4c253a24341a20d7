"""JSON out of estim: strict JSON, with ``null`` where a number is undefined.

Python's ``json`` writes ``NaN`` and ``Infinity``, which are not JSON (RFC 8259) and which
strict readers (browsers, ``jq``, most languages' parsers) refuse. A fit leaves numbers
undefined on purpose (the standard error of a parameter the data cannot identify, the
correlations involving it); they are written as ``null``.
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["dumps", "dump", "jsonable"]


def jsonable(obj):
    """``obj`` with every non-finite float replaced by ``None`` and NumPy values made plain
    Python (dicts, lists and tuples are walked)."""
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def dumps(obj, **kwargs) -> str:
    """``json.dumps`` of ``jsonable(obj)``, refusing anything that is still not JSON."""
    return json.dumps(jsonable(obj), allow_nan=False, **kwargs)


def dump(obj, f, **kwargs) -> None:
    """``json.dump`` of ``jsonable(obj)`` to the open file ``f``."""
    json.dump(jsonable(obj), f, allow_nan=False, **kwargs)
