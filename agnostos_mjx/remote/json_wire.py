"""json_numpy's wire format: JSON with numpy arrays, as OpenVLA's and OpenVLA-OFT's
``vla-scripts/deploy.py`` servers read and write it (they call ``json_numpy.patch()``).

An array or numpy scalar travels as the object ``{"__numpy__": base64 of its C-order
bytes, "dtype": its descriptor (numpy.lib.format.dtype_to_descr, e.g. "|u1", "<f4"),
"shape": [...]}``; on the way back an empty shape gives a numpy scalar (json_numpy 2.x's
layout, facts only; this code is ours, no json_numpy dependency).  Object, void and
complex dtypes are refused, as in wire.py.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np

_REFUSED_KINDS = frozenset("VOc")


def _default(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, np.generic)):
        if obj.dtype.kind in _REFUSED_KINDS:
            raise TypeError(f"cannot send arrays of dtype {obj.dtype}")
        arr = np.ascontiguousarray(obj)
        return {"__numpy__": base64.b64encode(arr.tobytes()).decode("ascii"),
                "dtype": arr.dtype.str, "shape": list(np.shape(obj))}
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _hook(obj: dict) -> Any:
    if "__numpy__" in obj:
        dtype = np.dtype(obj["dtype"])
        if dtype.kind in _REFUSED_KINDS:
            raise ValueError(f"refusing arrays of dtype {dtype}")
        flat = np.frombuffer(base64.b64decode(obj["__numpy__"], validate=True), dtype)
        shape = obj["shape"]
        return flat.reshape(shape) if shape else flat[0]
    return obj


def dumps(obj: Any) -> str:
    """`obj` (dicts, lists, str, numbers, numpy arrays and scalars) as JSON text."""
    return json.dumps(obj, default=_default, separators=(",", ":"))


def loads(text: str | bytes) -> Any:
    """The inverse of `dumps` (arrays come back read-only, backed by the decoded bytes)."""
    return json.loads(text, object_hook=_hook)
