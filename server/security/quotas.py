"""What a session's config may cost: safe ranges of the overrides, memory per session, per-token quotas.

A writer chooses its sessions' model config (``POST /sessions`` with ``config`` overrides); the
model itself accepts any value its maths allows, so the server bounds what one request can
make it spend. Checked once, when a session is created (sessions stored earlier keep running):

* **Safe ranges** (:data:`SAFE_RANGES`) on every parameter whose value drives memory or time
  per input: cell counts, iteration counts, image and patch sizes, windows counted in steps. Each range holds the
  default with a wide margin (typically 10x); a value outside is refused with 422 naming the field.
  Every other number must be finite, and integers fit in 64 bits; seeds are any value in
  ``[0, 2**63)`` (each distinct spatial seed has its own grid-cell tables, counted below).
* **Memory per session.** The dominant cost is the grid-cell rate tables
  (:func:`grid_table_bytes`): ``n_cells * (6 N^2 + 4 * 65537)`` bytes with
  ``n_cells = n_modules * cells_per_module`` and ``N = area_size_m / resolution_m + 1``
  (uint16 levels, int32 argsort, int32 level histogram; 132 MB at the defaults, 32 cells on
  801 x 801; building them needs about 2 N^2 n_cells bytes more for a moment). Sessions whose
  spatial geometry and seed match share one copy. The rest of a session (map graph, visual
  memory, place field) grows with the inputs, not with the config: a few MB per thousand key
  frames. A config needing more than ``max_session_grid_bytes`` is refused (422).
* **Per-token quotas**: at most ``max_sessions_per_token`` live sessions (429), and the grid-cell
  tables of a token's live sessions, each distinct table counted once, at most
  ``max_token_grid_bytes`` (403). Deleting a session frees its share.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

from hippomap.config import HippomapConfig, SpatialConfig
from hippomap.grid_cells import matrix_size, table_key

from ..settings import ServerSettings

#: rate levels of a grid-cell table (``hippomap.grid_cells.LEVELS``) + 2: the histogram's columns
_HIST_COLUMNS = 65535 + 2
_INT64 = 2**63 - 1

#: ``(section, field) -> (lowest, highest)`` allowed in a session's config (defaults in brackets)
SAFE_RANGES: dict[tuple[str, str], tuple[float, float]] = {
    ("spatial", "n_modules"): (1, 64),  # [8] cells = n_modules x cells_per_module; each a table of N^2
    ("spatial", "cells_per_module"): (1, 64),  # [4]
    ("spatial", "resolution_m"): (1e-4, 0.1),  # [0.0005] N = area/resolution + 1 (memory ~ N^2)
    ("spatial", "area_size_m"): (0.01, 10.0),  # [0.40]
    ("visual", "vgc_offsets_per_axis"): (2, 40),  # [10] offsets^2 visual grid cells per module
    ("visual", "fovea"): (5, 255),  # [31] pixels^2 per fixation
    ("visual", "working_width"): (32, 2048),  # [320] frames are resized to it: pixels per frame
    ("visual", "blur"): (1, 63),  # [3]
    ("visual", "n_fixations"): (3, 100),  # [9] features learned per key frame
    ("visual", "min_fixations"): (1, 100),  # [3]
    ("visual", "max_survivors"): (0, 10_000),  # [5]
    ("visual", "tolerance_px"): (0, 512),  # [8]
    ("visual", "max_prediction_errors"): (0, 1000),  # [2]
    ("visual", "max_resets"): (0, 100),  # [7] recognition attempts per frame
    ("visual", "max_saccades"): (1, 200),  # [18] saccades per attempt
    ("visual", "corner_block"): (3, 63),  # [3]
    ("visual", "min_distance"): (0, 2048),  # [0]
    ("visual", "query_keypoints"): (1, 500),  # [27]
    ("visual", "svc_stride"): (2, 64),  # [4] spatial view cells every stride px: memory ~ 1/stride^2
    ("visual", "index_side"): (2, 64),  # [8]
    ("visual", "index_shortlist"): (1, 5000),  # [64]
    ("visual", "stats_sample"): (8, 10_000),  # [128]
    ("visual", "target_candidates"): (1, 500),  # [16]
    ("visual", "trace_hypotheses"): (1, 100),  # [5]
    ("visual", "verify_saccades"): (0, 100),  # [2]
    ("map", "relax_loops"): (0, 200),  # [10] relaxation sweeps per step (time ~ loops x links)
    ("map", "lsq_iterations"): (1, 100),  # [10] Gauss-Newton iterations per correction
    ("map", "exclude_recent"): (0, 100_000),  # [5]
    ("map", "loop_min_support"): (0, 100_000),
    ("mapper", "keyframe_interval"): (1, 1_000_000),  # [None: by distance and turn]
}
#: most visual grid-cell frequencies (modules) a session may configure (default 9)
MAX_VGC_FREQUENCIES = 32
#: longest JSON form of a session's config overrides, characters
MAX_OVERRIDES_CHARS = 16_384


class ConfigRejected(ValueError):
    """A session config the server will not run: HTTP ``status`` and a message naming the problem."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


def grid_table_bytes(spatial: SpatialConfig) -> int:
    """Bytes of the grid-cell rate tables of ``spatial`` (``RateTables.nbytes``), without building them."""
    size = matrix_size(spatial)
    n_cells = spatial.n_modules * spatial.cells_per_module
    return n_cells * (6 * size * size + 4 * _HIST_COLUMNS)


def session_memory(config: HippomapConfig) -> dict[str, int]:
    """The config-driven memory of one session, bytes: ``grid_tables`` (shared by sessions with the
    same spatial geometry and seed) and ``grid_tables_build_peak`` (extra while they are built)."""
    size = matrix_size(config.spatial)
    n_cells = config.spatial.n_modules * config.spatial.cells_per_module
    return {"grid_tables": grid_table_bytes(config.spatial), "grid_tables_build_peak": 2 * size * size * n_cells}


def _walk(prefix: str, value: Any) -> Iterable[tuple[str, Any]]:
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _walk(f"{prefix}.{k}" if prefix else str(k), v)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _walk(f"{prefix}[{i}]", v)
    else:
        yield prefix, value


def check_config(config: HippomapConfig, settings: ServerSettings) -> None:
    """Refuse (:class:`ConfigRejected`, 422) a config outside the safe ranges or whose grid-cell
    tables exceed ``max_session_grid_bytes``."""
    dumped = config.model_dump()
    for name, value in _walk("", dumped):
        if isinstance(value, bool) or value is None or isinstance(value, str):
            continue
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigRejected(422, f"config {name} must be finite, got {value}")
        if isinstance(value, int) and abs(value) > _INT64:
            raise ConfigRejected(422, f"config {name} must fit in 64 bits, got {value}")
    for section in ("spatial", "visual"):
        seed = dumped[section]["seed"]
        if not 0 <= seed <= _INT64:
            raise ConfigRejected(422, f"config {section}.seed must be in [0, 2**63), got {seed}")
    for (section, field), (lo, hi) in SAFE_RANGES.items():
        value = dumped.get(section, {}).get(field)  # (a field the model no longer has: nothing to bound)
        if value is not None and not lo <= value <= hi:
            raise ConfigRejected(
                422, f"config {section}.{field}={value} is outside the server's safe range [{lo:g}, {hi:g}]"
            )
    n_freq = len(config.visual.vgc_frequencies)
    if not 1 <= n_freq <= MAX_VGC_FREQUENCIES:
        raise ConfigRejected(
            422, f"config visual.vgc_frequencies has {n_freq} entries; the server allows 1 to {MAX_VGC_FREQUENCIES}"
        )
    need = grid_table_bytes(config.spatial)
    if need > settings.max_session_grid_bytes:
        raise ConfigRejected(
            422,
            f"config needs {need / 1e6:.0f} MB of grid-cell tables (spatial.n_modules x "
            f"cells_per_module x (area_size_m / resolution_m)^2); the server allows "
            f"{settings.max_session_grid_bytes / 1e6:.0f} MB per session",
        )


def check_token_quota(config: HippomapConfig, owned: list[HippomapConfig], settings: ServerSettings) -> None:
    """Refuse a new session whose grid-cell tables would take the token's live sessions (``owned``)
    past ``max_token_grid_bytes`` (403); tables shared by several sessions count once."""
    tables = {table_key(c.spatial): grid_table_bytes(c.spatial) for c in owned}
    before = sum(tables.values())
    tables.setdefault(table_key(config.spatial), grid_table_bytes(config.spatial))
    after = sum(tables.values())
    if after > settings.max_token_grid_bytes:
        raise ConfigRejected(
            403,
            f"this token's sessions would need {after / 1e6:.0f} MB of grid-cell tables "
            f"(now {before / 1e6:.0f} MB, limit {settings.max_token_grid_bytes / 1e6:.0f} "
            "MB): reuse a spatial config (geometry and seed) of a session it has, or delete "
            "one first",
        )
