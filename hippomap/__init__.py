"""hippomap: a cognitive map built the way the rat hippocampus is thought to build one.

The model is pure numpy/OpenCV and never imports web code. Public names are loaded
lazily so that ``import hippomap`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "HippomapConfig": "hippomap.config",
    "SpatialConfig": "hippomap.config",
    "VisualConfig": "hippomap.config",
    "MapConfig": "hippomap.config",
    "MapperConfig": "hippomap.config",
    "HippomapError": "hippomap.errors",
    "InputError": "hippomap.errors",
    "GridCells": "hippomap.grid_cells",
    "PlaceCells": "hippomap.place_cells",
    "SpatialPathway": "hippomap.spatial_pathway",
    "PlaceCode": "hippomap.spatial_pathway",
    "CognitiveMap": "hippomap.cognitive_map",
    "LoopHypothesis": "hippomap.cognitive_map",
    "VisualMemory": "hippomap.visual_memory",
    "Recognition": "hippomap.visual_memory",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'hippomap' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


__all__ = sorted(_EXPORTS)
