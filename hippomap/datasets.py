"""Dataset readers: g2o pose graphs, timestamp lists and ground-truth CSV files.

Every reader validates as it parses and raises :class:`~hippomap.errors.InputError`
naming the file, the line number and the offending text, so a malformed file is
never silently half-read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class LoopEdge:
    """A non-consecutive g2o edge: pose ``j`` measured in the frame of pose ``i``."""

    i: int
    j: int
    transform: tuple[float, float, float]
    line: int


@dataclass(frozen=True)
class G2OGraph:
    """A 2-D pose graph read from a g2o file.

    ``vertices`` (N, 3) are the file's VERTEX_SE2 poses (ids 0..N-1), ``odometry``
    (N-1, 3) the relative increments of the edges ``i -> i+1`` (in the frame of pose
    ``i``), ``loops`` every other edge (loop-closure proposals).
    """

    vertices: np.ndarray
    odometry: np.ndarray
    loops: list[LoopEdge] = field(default_factory=list)


def _floats(tokens: list[str], path: Path, lineno: int, line: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{path}:{lineno}: malformed number in line {line.strip()!r}") from None
    for v in values:
        if not math.isfinite(v):
            raise InputError(f"{path}:{lineno}: non-finite value {v} in line {line.strip()!r}")
    return values


def _int(token: str, path: Path, lineno: int, line: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise InputError(f"{path}:{lineno}: malformed vertex id {token!r} in line {line.strip()!r}") from None


def read_g2o(path: str | Path) -> G2OGraph:
    """Read VERTEX_SE2 / EDGE_SE2 lines; vertex ids must be 0..N-1 and every
    consecutive pair must be joined by exactly one odometry edge."""
    path = Path(path)
    vertices: dict[int, list[float]] = {}
    odometry: dict[int, list[float]] = {}
    loops: list[LoopEdge] = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            tag = tokens[0]
            if tag == "VERTEX_SE2":
                if len(tokens) != 5:
                    raise InputError(f"{path}:{lineno}: VERTEX_SE2 needs 'id x y theta', got {line.strip()!r}")
                vid = _int(tokens[1], path, lineno, line)
                if vid in vertices:
                    raise InputError(f"{path}:{lineno}: duplicate vertex id {vid}")
                vertices[vid] = _floats(tokens[2:5], path, lineno, line)
            elif tag == "EDGE_SE2":
                if len(tokens) != 12:
                    raise InputError(
                        f"{path}:{lineno}: EDGE_SE2 needs 'i j dx dy dtheta' and 6 information values, got {line.strip()!r}"
                    )
                i = _int(tokens[1], path, lineno, line)
                j = _int(tokens[2], path, lineno, line)
                values = _floats(tokens[3:], path, lineno, line)
                if j == i + 1:
                    if i in odometry:
                        raise InputError(f"{path}:{lineno}: second odometry edge {i} -> {j}")
                    odometry[i] = values[:3]
                else:
                    loops.append(LoopEdge(i, j, (values[0], values[1], values[2]), lineno))
            elif tag in ("FIX", "VERTEX_XY", "EDGE_SE2_XY"):
                continue  # not used by hippomap; tolerated so standard files read
            else:
                raise InputError(f"{path}:{lineno}: unknown g2o tag {tag!r}")
    n = len(vertices)
    if n == 0:
        raise InputError(f"{path}: no VERTEX_SE2 lines")
    missing = sorted(set(range(n)) - set(vertices))
    if missing:
        raise InputError(f"{path}: vertex ids must be 0..{n - 1}; missing {missing[:5]}")
    gaps = [i for i in range(n - 1) if i not in odometry]
    if gaps:
        raise InputError(f"{path}: no odometry edge {gaps[0]} -> {gaps[0] + 1} ({len(gaps)} missing)")
    for e in loops:
        if not (0 <= e.i < n and 0 <= e.j < n):
            raise InputError(f"{path}:{e.line}: edge {e.i} -> {e.j} names a vertex outside 0..{n - 1}")
    verts = np.array([vertices[k] for k in range(n)], dtype=float)
    odo = np.array([odometry[k] for k in range(n - 1)], dtype=float).reshape(-1, 3)
    return G2OGraph(verts, odo, loops)


def _check_increasing(t: np.ndarray, path: Path) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = int(bad[0])
        raise InputError(f"{path}:{k + 2}: timestamps must increase: {t[k + 1]!r} follows {t[k]!r}")


def read_timestamps(path: str | Path) -> np.ndarray:
    """One timestamp per line (seconds), strictly increasing."""
    path = Path(path)
    out: list[float] = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s:
                continue
            out.append(_floats([s], path, lineno, line)[0])
    t = np.array(out, dtype=float)
    _check_increasing(t, path)
    return t


def read_groundtruth_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``t, x, y, theta`` rows (comma separated, optional header) -> (t (M,), poses (M, 3))."""
    path = Path(path)
    rows: list[list[float]] = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            tokens = [t.strip() for t in s.split(",")]
            if lineno == 1 and not _is_number(tokens[0]):
                continue  # header
            if len(tokens) != 4:
                raise InputError(f"{path}:{lineno}: expected 't,x,y,theta', got {s!r}")
            rows.append(_floats(tokens, path, lineno, line))
    if not rows:
        raise InputError(f"{path}: no ground-truth rows")
    arr = np.array(rows, dtype=float)
    _check_increasing(arr[:, 0], path)
    return arr[:, 0], arr[:, 1:4]


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class OdometryDataset:
    """What ``hippomap run-odometry`` needs: a g2o graph, one timestamp per pose, and
    optionally ground truth (timestamps, poses)."""

    graph: G2OGraph
    times: np.ndarray
    groundtruth: tuple[np.ndarray, np.ndarray] | None
    loops_file: Path


def load_odometry_dataset(data_dir: str | Path, loops: str | Path) -> OdometryDataset:
    """Load a Bicocca-style folder: ``loops`` (a g2o file, relative to ``data_dir`` or
    absolute) gives odometry and proposals; ``*timestamps.txt`` one time per pose;
    ``*GT*.csv`` the ground truth if present."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputError(f"data folder {data_dir} does not exist")
    loops_path = Path(loops)
    if not loops_path.is_absolute() and not loops_path.exists():
        loops_path = data_dir / loops_path
    if not loops_path.is_file():
        raise InputError(f"loop/odometry g2o file {loops} not found (looked in {data_dir})")
    graph = read_g2o(loops_path)
    stamps = sorted(data_dir.glob("*timestamps.txt"))
    if stamps:
        times = read_timestamps(stamps[0])
        if len(times) != len(graph.vertices):
            raise InputError(
                f"{stamps[0]} has {len(times)} timestamps but {loops_path.name} has {len(graph.vertices)} poses"
            )
    else:
        times = np.arange(len(graph.vertices), dtype=float)
    gts = sorted(data_dir.glob("*GT*.csv"))
    gt = read_groundtruth_csv(gts[0]) if gts else None
    return OdometryDataset(graph, times, gt, loops_path)
