"""The mapper's snapshot encoding: its state as bytes and back (:meth:`hippomap.mapper.Mapper.to_bytes`).

A snapshot is an npz archive (no pickle): every numpy array of the nested state of the mapper's
parts under a dotted key, and a JSON header (``__meta__``) holding the rest, with the arrays'
places marked ``{"__array__": key}`` and the format version. A restored snapshot may run with its
config changed (:func:`config_over`, for a run in a saved map).
"""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np

from .config import HippomapConfig
from .errors import InputError

FORMAT_VERSION = 1


def pack(meta: dict[str, Any], arrays: dict[str, Any]) -> bytes:
    """The snapshot of a JSON header ``meta`` (the format version added) and named arrays."""
    # (np.ndarray values typed Any for numpy's savez_compressed(**kwds) stub)
    header = json.dumps({"format": FORMAT_VERSION, **meta}).encode()
    buf = io.BytesIO()
    np.savez_compressed(buf, __meta__=np.frombuffer(header, dtype=np.uint8), **arrays)
    return buf.getvalue()


def unpack(data: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(meta, arrays)`` of a snapshot; InputError when ``data`` is not one or of another format."""
    try:
        npz = np.load(io.BytesIO(data), allow_pickle=False)
        arrays = {k: npz[k] for k in npz.files}
        meta = json.loads(arrays.pop("__meta__").tobytes().decode())
    except Exception as exc:
        raise InputError(f"not a hippomap mapper snapshot: {exc}") from exc
    if meta.get("format") != FORMAT_VERSION:
        raise InputError(f"unsupported snapshot format {meta.get('format')!r}")
    return meta, arrays


def config_over(config: HippomapConfig, overrides: dict[str, Any]) -> HippomapConfig:
    """``config`` changed by nested ``overrides`` (``{"section": {"field": value}}``), validated;
    InputError naming the problem."""
    if not isinstance(overrides, dict):
        raise InputError(f"config overrides must be a mapping of sections, got {type(overrides).__name__}")
    base = config.model_dump()
    for section, values in overrides.items():
        if section not in base:
            raise InputError(f"unknown config section {section!r}; known: {sorted(base)}")
        if not isinstance(values, dict):
            raise InputError(f"config section {section!r} must be a mapping")
        base[section].update(values)
    try:
        return HippomapConfig.model_validate(base)
    except ValueError as exc:
        raise InputError(f"invalid config: {exc}") from None


def split_arrays(obj: Any, prefix: str, arrays: dict[str, np.ndarray]) -> Any:
    """Move numpy arrays out of a nested state into ``arrays``; leave JSON behind."""
    if isinstance(obj, np.ndarray):
        key = f"{prefix}"
        arrays[key] = obj
        return {"__array__": key}
    if isinstance(obj, dict):
        return {str(k): split_arrays(v, f"{prefix}.{k}", arrays) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [split_arrays(v, f"{prefix}.{i}", arrays) for i, v in enumerate(obj)]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def join_arrays(obj: Any, arrays: dict[str, np.ndarray]) -> Any:
    """The inverse of :func:`split_arrays`: put the arrays back into the nested state."""
    if isinstance(obj, dict):
        if set(obj) == {"__array__"}:
            return arrays[obj["__array__"]]
        return {k: join_arrays(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [join_arrays(v, arrays) for v in obj]
    return obj


class Grow:
    """Append-only float array of fixed row width with amortised doubling."""

    def __init__(self, width: int, dtype: Any = float) -> None:
        self.data = np.empty((64, width), dtype=dtype)
        self.n = 0

    def append(self, row: Any) -> None:
        if self.n == len(self.data):
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
        self.data[self.n] = row
        self.n += 1

    @property
    def view(self) -> np.ndarray:
        return self.data[: self.n]

    @classmethod
    def of(cls, arr: np.ndarray) -> "Grow":
        g = cls(arr.shape[1], arr.dtype)
        g.data = np.array(arr, copy=True) if len(arr) else g.data
        g.n = len(arr)
        return g
