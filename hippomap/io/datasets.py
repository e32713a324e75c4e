"""Dataset readers: g2o pose graphs, timestamp lists and ground-truth CSV files.

Every reader validates as it parses and raises :class:`~hippomap.errors.InputError`
naming the file, the line number and the offending text, so a malformed file is
never silently half-read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence, cast

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from .rosbag import DecodedFrame


#: the upper triangle of the 3x3 unit information matrix, as g2o writes it (I11 I12 I13 I22 I23 I33)
UNIT_INFORMATION = (1.0, 0.0, 0.0, 1.0, 0.0, 1.0)


@dataclass(frozen=True)
class LoopEdge:
    """A non-consecutive g2o edge: pose ``j`` measured in the frame of pose ``i``, with the
    upper triangle of its information matrix (``I11 I12 I13 I22 I23 I33``, g2o's order)."""

    i: int
    j: int
    transform: tuple[float, float, float]
    line: int
    information: tuple[float, float, float, float, float, float] = UNIT_INFORMATION


@dataclass(frozen=True)
class G2OGraph:
    """A 2-D pose graph read from a g2o file.

    ``vertices`` (N, 3) are the file's VERTEX_SE2 poses (ids 0..N-1), ``odometry``
    (N-1, 3) the relative increments of the edges ``i -> i+1`` (in the frame of pose
    ``i``), ``loops`` every other edge (loop-closure proposals). ``odometry_information``
    (N-1, 6) holds the odometry edges' information (upper triangle, g2o's order), so a
    file written with each link's information (:func:`hippomap.io.exports.write_g2o`) reads
    back with it. Read with ``chain=False``, a graph need not be a chain: a missing
    ``i -> i+1`` edge leaves a NaN row in ``odometry`` and ``odometry_information``.
    """

    vertices: np.ndarray
    odometry: np.ndarray
    loops: list[LoopEdge] = field(default_factory=list)
    odometry_information: np.ndarray | None = None

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every edge as arrays ``(source, target, transform (M, 3), information (M, 6))``:
        the odometry edges present (in order of ``i``), then the loops (file order)."""
        odo = np.flatnonzero(np.isfinite(self.odometry).all(axis=1))
        info = (
            self.odometry_information
            if self.odometry_information is not None
            else np.tile(UNIT_INFORMATION, (len(self.odometry), 1))
        )
        src = np.concatenate([odo, [e.i for e in self.loops]]).astype(np.int64)
        dst = np.concatenate([odo + 1, [e.j for e in self.loops]]).astype(np.int64)
        tr = np.vstack([self.odometry[odo], np.array([e.transform for e in self.loops], dtype=float).reshape(-1, 3)])
        inf = np.vstack([info[odo], np.array([e.information for e in self.loops], dtype=float).reshape(-1, 6)])
        return src, dst, tr, inf


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


def read_g2o(path: str | Path, chain: bool = True) -> G2OGraph:
    """Read VERTEX_SE2 / EDGE_SE2 lines; vertex ids must be 0..N-1 and (``chain``) every
    consecutive pair must be joined by exactly one odometry edge. Each edge's information
    (upper triangle of its 3x3 matrix) is kept. ``chain=False`` reads any pose graph (e.g.
    a cognitive map, whose node ``i + 1`` may hang off an older node after a loop): missing
    ``i -> i+1`` edges are NaN rows of ``odometry``, and a second ``i -> i+1`` edge is a loop."""
    path = Path(path)
    vertices, odometry, loops = _parse_g2o(path, chain)
    return _g2o_graph(path, vertices, odometry, loops, chain)


def _parse_g2o(path: Path, chain: bool) -> tuple[dict[int, list[float]], dict[int, list[float]], list[LoopEdge]]:
    """The lines of a g2o file: vertices by id, odometry edges ``i -> i+1`` by ``i`` (dx dy dtheta and the 6
    information values) and the other edges as loops; each line checked on its own (:func:`read_g2o`)."""
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
                        f"{path}:{lineno}: EDGE_SE2 needs 'i j dx dy dtheta' and 6 information values, "
                        f"got {line.strip()!r}"
                    )
                i = _int(tokens[1], path, lineno, line)
                j = _int(tokens[2], path, lineno, line)
                values = _floats(tokens[3:], path, lineno, line)
                if j == i + 1 and not (i in odometry and not chain):
                    if i in odometry:
                        raise InputError(f"{path}:{lineno}: second odometry edge {i} -> {j}")
                    odometry[i] = values
                else:
                    loops.append(
                        LoopEdge(
                            i,
                            j,
                            (values[0], values[1], values[2]),
                            lineno,
                            (values[3], values[4], values[5], values[6], values[7], values[8]),
                        )
                    )
            elif tag in ("FIX", "VERTEX_XY", "EDGE_SE2_XY"):
                continue  # not used by hippomap; tolerated so standard files read
            else:
                raise InputError(f"{path}:{lineno}: unknown g2o tag {tag!r}")
    return vertices, odometry, loops


def _g2o_graph(
    path: Path,
    vertices: dict[int, list[float]],
    odometry: dict[int, list[float]],
    loops: list[LoopEdge],
    chain: bool,
) -> G2OGraph:
    """The parsed lines as a :class:`G2OGraph`, once the whole file agrees: ids 0..N-1, (``chain``) an odometry
    edge between every consecutive pair, loop edges between existing vertices; missing odometry is NaN."""
    n = len(vertices)
    if n == 0:
        raise InputError(f"{path}: no VERTEX_SE2 lines")
    missing = sorted(set(range(n)) - set(vertices))
    if missing:
        raise InputError(f"{path}: vertex ids must be 0..{n - 1}; missing {missing[:5]}")
    gaps = [i for i in range(n - 1) if i not in odometry]
    if gaps and chain:
        raise InputError(f"{path}: no odometry edge {gaps[0]} -> {gaps[0] + 1} ({len(gaps)} missing)")
    for e in loops:
        if not (0 <= e.i < n and 0 <= e.j < n):
            raise InputError(f"{path}:{e.line}: edge {e.i} -> {e.j} names a vertex outside 0..{n - 1}")
    verts = np.array([vertices[k] for k in range(n)], dtype=float)
    for k in gaps:
        odometry[k] = [math.nan] * 9
    odo = np.array([odometry[k] for k in range(n - 1)], dtype=float).reshape(-1, 9)
    return G2OGraph(verts, odo[:, :3].copy(), loops, odo[:, 3:].copy())


def _check_increasing(t: np.ndarray, path: Path, lines: list[int] | None = None) -> None:
    """Strictly increasing timestamps; ``lines`` maps row index -> file line number."""
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = int(bad[0])
        line = lines[k + 1] if lines is not None else k + 2
        raise InputError(f"{path}:{line}: timestamps must increase: {float(t[k + 1])!r} follows {float(t[k])!r}")


def read_timestamps(path: str | Path) -> np.ndarray:
    """One timestamp per line (seconds), strictly increasing."""
    return _numeric_rows(Path(path), 1, "t", None)[:, 0]


def read_groundtruth_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``t, x, y, theta`` rows (comma separated, optional header) -> (t (M,), poses (M, 3))."""
    arr = _numeric_rows(Path(path), 4, "t,x,y,theta", ",", header_allowed=True)
    return arr[:, 0], arr[:, 1:4]


def _numeric_rows(path: Path, width: int, columns: str, sep: str | None, header_allowed: bool = False) -> np.ndarray:
    """Rows of ``width`` finite numbers (``#`` comments and blank lines skipped, an optional
    non-numeric first line taken as a header); timestamps in column 0 must increase.
    Every error names the file and line."""
    rows: list[list[float]] = []
    lines: list[int] = []
    with path.open() as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            tokens = [t.strip() for t in s.split(sep)] if sep else s.replace(",", " ").split()
            if header_allowed and lineno == 1 and not _is_number(tokens[0]):
                continue
            if len(tokens) != width:
                raise InputError(f"{path}:{lineno}: expected {columns!r}, got {s!r}")
            rows.append(_floats(tokens, path, lineno, line))
            lines.append(lineno)
    if not rows:
        raise InputError(f"{path}: no rows of {columns!r}")
    arr = np.array(rows, dtype=float)
    _check_increasing(arr[:, 0], path, lines)
    return arr


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


# --------------------------------------------------------------------------------------
# Camera + odometry data sets (the documented folder format, TUM RGB-D folders)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameRef:
    """A camera frame on disk, loaded only when needed."""

    t: float
    path: Path

    def load(self):
        """Decode to a :class:`~hippomap.inputs.Frame` (grayscale)."""
        import cv2

        from ..inputs import Frame

        img = cv2.imread(str(self.path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"cannot read image {self.path}")
        return Frame(self.t, img)


@dataclass(frozen=True)
class SensorDataset:
    """Odometry readings, frame references and optional ground truth, each time-sorted; and the
    camera's horizontal field of view when the data set states it (:func:`read_camera_hfov`)."""

    odometry: list  # list[hippomap.inputs.Odometry]
    frames: Sequence[FrameRef | DecodedFrame]  # on disk (folders, TUM) or decoded from a ROS bag
    groundtruth: tuple[np.ndarray, np.ndarray] | None
    source: Path
    camera_hfov_deg: float | None = None

    def events(self):
        """All inputs merged in time order (odometry before a frame of the same time)."""
        import heapq

        odo = ((o.t, 0, k, o) for k, o in enumerate(self.odometry))
        frm = ((f.t, 1, k, f) for k, f in enumerate(self.frames))
        for _, _, _, item in heapq.merge(odo, frm):
            yield item


def _read_csv_rows(path: Path, columns: tuple[str, ...]) -> list[list[Any]]:
    """Rows of a CSV whose header must name ``columns`` (in that order): ``[line number, *cells]``."""
    import csv

    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != columns:
            raise InputError(f"{path}:1: header must be {','.join(columns)!r}, got {header!r}")
        rows: list[list[Any]] = []
        for lineno, row in enumerate(reader, 2):
            if not row or not "".join(row).strip():
                continue
            if len(row) != len(columns):
                raise InputError(f"{path}:{lineno}: expected {len(columns)} columns {columns}, got {row!r}")
            rows.append([lineno, *[c.strip() for c in row]])
        return rows


def read_folder_dataset(folder: str | Path) -> SensorDataset:
    """The project's folder format: ``frames/`` images, ``frames.csv`` (``t,file``),
    ``odometry.csv`` (``t,v,omega`` in m/s, rad/s, or ``t,dx,dy,dtheta``: see
    :func:`read_folder_odometry`), optional ``groundtruth.csv``
    (``t,x,y,theta``), optional camera calibration (``camera.json`` or the simulator's ``sim.json``:
    :func:`read_camera_hfov`). Timestamps must increase within each file."""
    folder = Path(folder)
    for name in ("frames.csv", "odometry.csv"):
        if not (folder / name).is_file():
            raise InputError(f"{folder} is not a hippomap data folder: {name} is missing")
    odometry = read_folder_odometry(folder / "odometry.csv")
    frames: list[FrameRef] = []
    rows = _read_csv_rows(folder / "frames.csv", ("t", "file"))
    for lineno, t, name in rows:
        tf = _floats([t], folder / "frames.csv", lineno, f"{t},{name}")[0]
        path = folder / "frames" / name if not (folder / name).is_file() else folder / name
        if not path.is_file():
            raise InputError(f"{folder / 'frames.csv'}:{lineno}: image {name!r} not found")
        frames.append(FrameRef(tf, path))
    _check_increasing(np.array([f.t for f in frames]), folder / "frames.csv", [r[0] for r in rows])
    gt = read_groundtruth_csv(folder / "groundtruth.csv") if (folder / "groundtruth.csv").is_file() else None
    return SensorDataset(odometry, frames, gt, folder, read_camera_hfov(folder))


def read_camera_hfov(folder: str | Path) -> float | None:
    """The camera's horizontal field of view (degrees) a data folder states, or None: from
    ``camera.json`` (``{"hfov_deg": 60}``, or ``{"intrinsics": {"fx": ..., "width": ...}}``), else
    from the ``intrinsics`` of ``sim.json`` (what ``hippomap simulate`` writes):
    ``hfov = 2 atan(width / 2 / fx)``. A file that is there but unreadable, or a value outside
    (0, 180) degrees, raises :class:`InputError` naming it."""
    import json

    folder = Path(folder)
    for name in ("camera.json", "sim.json"):
        path = folder / name
        if not path.is_file():
            continue
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"{path}: cannot read the camera calibration: {exc}") from None
        if not isinstance(data, dict):
            raise InputError(f"{path}: the camera calibration must be a JSON object")
        try:
            if "hfov_deg" in data:
                hfov = float(data["hfov_deg"])
            elif isinstance(data.get("intrinsics"), dict):
                k = data["intrinsics"]
                hfov = math.degrees(2 * math.atan(float(k["width"]) / 2 / float(k["fx"])))
            else:
                continue
        except (KeyError, TypeError, ValueError, ZeroDivisionError) as exc:
            raise InputError(f"{path}: camera calibration needs hfov_deg or intrinsics fx and width: {exc!r}") from None
        if not (math.isfinite(hfov) and 0 < hfov < 180):
            raise InputError(f"{path}: horizontal field of view must be in (0, 180) degrees, got {hfov!r}")
        return hfov
    return None


def _read_tum_like(path: Path) -> np.ndarray:
    """``t tx ty tz qx qy qz qw`` rows (TUM trajectory files), comments with '#'."""
    return _numeric_rows(path, 8, "t tx ty tz qx qy qz qw", None)


def _tum_to_se2(arr: np.ndarray) -> np.ndarray:
    qx, qy, qz, qw = arr[:, 4], arr[:, 5], arr[:, 6], arr[:, 7]
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy**2 + qz**2))
    return np.column_stack([arr[:, 1], arr[:, 2], yaw])


def read_tum_rgbd(folder: str | Path) -> SensorDataset:
    """A TUM RGB-D folder: ``rgb.txt`` (``t file``), ``groundtruth.txt`` (TUM poses), and
    the wheel odometry as ``odometry.txt`` (TUM poses, e.g. the Pioneer sequences' /pose
    topic exported) or ``odometry.csv`` (``t,v,omega``). The poses' yaw and x-y are used
    (planar robot)."""
    from ..geometry import between
    from ..inputs import Odometry

    folder = Path(folder)
    if not (folder / "rgb.txt").is_file():
        raise InputError(f"{folder} is not a TUM RGB-D folder: rgb.txt is missing")
    frames, lines = [], []
    with (folder / "rgb.txt").open() as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            tokens = s.split()
            if len(tokens) != 2:
                raise InputError(f"{folder / 'rgb.txt'}:{lineno}: expected 't file', got {s!r}")
            t = _floats(tokens[:1], folder / "rgb.txt", lineno, line)[0]
            if not (folder / tokens[1]).is_file():
                raise InputError(f"{folder / 'rgb.txt'}:{lineno}: image {tokens[1]!r} not found")
            frames.append(FrameRef(t, folder / tokens[1]))
            lines.append(lineno)
    _check_increasing(np.array([f.t for f in frames]), folder / "rgb.txt", lines)
    if (folder / "odometry.txt").is_file():
        arr = _read_tum_like(folder / "odometry.txt")
        poses = _tum_to_se2(arr)
        inc = between(poses[:-1], poses[1:])
        odometry = [
            Odometry(float(t), increment=cast("tuple[float, float, float]", tuple(map(float, d))))
            for t, d in zip(arr[1:, 0], inc)
        ]
    elif (folder / "odometry.csv").is_file():
        odometry = read_folder_odometry(folder / "odometry.csv")
    else:
        raise InputError(f"{folder}: no wheel odometry (odometry.txt in TUM format or odometry.csv with t,v,omega)")
    gt = None
    if (folder / "groundtruth.txt").is_file():
        arr = _read_tum_like(folder / "groundtruth.txt")
        gt = (arr[:, 0], _tum_to_se2(arr))
    return SensorDataset(odometry, frames, gt, folder)


def read_folder_odometry(path: Path) -> list:
    """``odometry.csv``: ``t,v,omega`` (velocities, m/s and rad/s, held from the previous row's
    time) or ``t,dx,dy,dtheta`` (relative pose increments in the previous pose's frame, as a
    session fed increments exports them); the header says which."""
    from ..inputs import Odometry

    with path.open(newline="") as fh:
        first = fh.readline()
    columns = (
        ("t", "dx", "dy", "dtheta")
        if [c.strip() for c in first.split(",")] == ["t", "dx", "dy", "dtheta"]
        else ("t", "v", "omega")
    )
    out = []
    rows = _read_csv_rows(path, columns)
    for lineno, *cells in rows:
        values = _floats(cells, path, lineno, ",".join(cells))
        out.append(
            Odometry(values[0], v=values[1], omega=values[2])
            if len(values) == 3
            else Odometry(values[0], increment=(values[1], values[2], values[3]))
        )
    _check_increasing(np.array([o.t for o in out]), path, [r[0] for r in rows])
    return out
