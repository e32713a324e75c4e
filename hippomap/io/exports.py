"""Exports of trajectories and maps: TUM (read by evo), g2o, JSON graph, and a map plot.

All functions take plain arrays so they serve the offline runs and the server alike.
2-D poses are (x, y, theta) rows; TUM files carry them as z = 0 and a yaw quaternion.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..extras import requires


def _as_poses(poses: Any, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains non-finite values")
    return arr


def to_evo(times: Any, poses: Any, name: str = "trajectory"):
    """(N,) times and (N, 3) poses -> evo ``PoseTrajectory3D`` (z = 0, yaw quaternion)."""
    with requires("eval", "an evo trajectory"):
        from evo.core.trajectory import PoseTrajectory3D

    t = np.asarray(times, dtype=float)
    p = _as_poses(poses, name)
    if t.shape != (len(p),):
        raise InputError(f"{name}: {len(t)} timestamps for {len(p)} poses")
    xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
    half = p[:, 2] / 2
    quat_wxyz = np.column_stack([np.cos(half), np.zeros(len(p)), np.zeros(len(p)), np.sin(half)])
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=quat_wxyz, timestamps=t)


def from_evo(traj) -> tuple[np.ndarray, np.ndarray]:
    """evo trajectory -> (times, (N, 3) poses); the yaw is taken from the quaternion."""
    q = traj.orientations_quat_wxyz
    yaw = np.arctan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2] ** 2 + q[:, 3] ** 2))
    return np.asarray(traj.timestamps, dtype=float), np.column_stack([traj.positions_xyz[:, :2], yaw])


def write_tum(path: str | Path, times: Any, poses: Any) -> Path:
    """Write a TUM trajectory file (``t x y z qx qy qz qw``) through evo's writer."""
    with requires("eval", "writing a TUM file"):
        from evo.tools import file_interface

    path = Path(path)
    file_interface.write_tum_trajectory_file(path, to_evo(times, poses, path.name))
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file through evo's reader -> (times, (N, 3) poses)."""
    with requires("eval", "reading a TUM file"):
        from evo.tools import file_interface

    return from_evo(file_interface.read_tum_trajectory_file(str(path)))


def link_transforms(d: Any, heading: Any, facing: Any) -> np.ndarray:
    """Relative SE(2) transforms (dx, dy, dtheta) of links stored the [ORS] way."""
    d, heading, facing = (np.asarray(a, dtype=float) for a in (d, heading, facing))
    return np.column_stack([d * np.cos(heading), d * np.sin(heading), facing])


def link_information(cmap: Any) -> np.ndarray:
    """(M, 3) diagonal information (x, y, θ) the map gives each link when it solves, times its
    robust weight (:meth:`~hippomap.cognitive_map.CognitiveMap.weighted_link_information`). This
    is what :func:`write_g2o` writes on each edge."""
    return np.asarray(cmap.weighted_link_information(), dtype=float)


def write_g2o(
    path: str | Path,
    poses: Any,
    sources: Any,
    targets: Any,
    transforms: Any,
    information: Any | None = None,
    coupling: Any | None = None,
) -> Path:
    """Write nodes as VERTEX_SE2 and links as EDGE_SE2. ``information`` (M, 3) is each link's
    diagonal information (x, y, θ; e.g. :func:`link_information`), written as the upper
    triangle ``ix 0 0 iy 0 iθ`` that g2o reads; None writes unit information. ``coupling`` (M,),
    m⁻¹ (``CognitiveMap.link_coupling``): a coupled link's heading information weighs heading +
    coupling · y, so its matrix is ``ix 0 0 (iy + c² iθ) (c iθ) iθ``."""
    p = _as_poses(poses, "poses")
    src = np.asarray(sources, dtype=int)
    dst = np.asarray(targets, dtype=int)
    tr = _as_poses(np.asarray(transforms, dtype=float).reshape(-1, 3), "transforms")
    if not (len(src) == len(dst) == len(tr)):
        raise InputError("sources, targets and transforms must have the same length")
    if information is None:
        info = np.ones((len(src), 3))
    else:
        info = np.asarray(information, dtype=float)
        if info.shape != (len(src), 3):
            raise InputError(f"information must have shape ({len(src)}, 3), got {info.shape}")
        bad = np.flatnonzero(~(np.isfinite(info).all(axis=1) & (info > 0).all(axis=1)))
        if len(bad):
            raise InputError(
                f"link {int(bad[0])} has information {info[bad[0]].tolist()}: every value must be finite and > 0"
            )
    c = np.zeros(len(src)) if coupling is None else np.asarray(coupling, dtype=float)
    if c.shape != (len(src),) or not np.all(np.isfinite(c) & (c >= 0)):
        raise InputError(f"coupling must be {len(src)} finite values >= 0, one per link, got shape {c.shape}")
    lines = [f"VERTEX_SE2 {i} {x:.9f} {y:.9f} {th:.9f}" for i, (x, y, th) in enumerate(p)]
    for a, b, (dx, dy, dth), (ix, iy, ith), k in zip(src.tolist(), dst.tolist(), tr, info.tolist(), c.tolist()):
        iyy, iyt = (iy, 0) if k == 0 else (iy + k * k * ith, k * ith)
        lines.append(f"EDGE_SE2 {a} {b} {dx:.9f} {dy:.9f} {dth:.9f} {ix!r} 0 0 {iyy!r} {iyt!r} {ith!r}")
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def graph_dict(
    poses: Any, place_codes: Any, frames: Any, times: Any, sources: Any, targets: Any, transforms: Any, kinds: Any
) -> dict[str, Any]:
    """The map as a JSON-ready dict: nodes {id, pose, place_code, frame, t} and links."""
    p = _as_poses(poses, "poses")
    pc = _as_poses(place_codes, "place_codes")
    frames = np.asarray(frames).tolist()
    times = np.asarray(times, dtype=float).tolist()
    tr = np.asarray(transforms, dtype=float).reshape(-1, 3)
    nodes = [
        {
            "id": i,
            "pose": p[i].tolist(),
            "place_code": pc[i].tolist(),
            "frame": None if frames[i] is None or frames[i] < 0 else int(frames[i]),
            "t": times[i],
        }
        for i in range(len(p))
    ]
    links = [
        {"source": int(a), "target": int(b), "transform": tr[k].tolist(), "kind": str(kind)}
        for k, (a, b, kind) in enumerate(zip(np.asarray(sources).tolist(), np.asarray(targets).tolist(), list(kinds)))
    ]
    return {"nodes": nodes, "links": links}


def write_json(path: str | Path, data: Any) -> Path:
    path = Path(path)
    path.write_text(json.dumps(data, indent=1))
    return path


def plot_map(
    path: str | Path,
    odometry: Any,
    corrected: Any,
    groundtruth: Any | None = None,
    loops: Any | None = None,
    title: str = "hippomap",
) -> Path:
    """PNG of raw odometry vs corrected map (vs ground truth when given); ``loops`` are
    (M, 2, 2) segments drawn between the two ends of each accepted loop closure."""
    with requires("viz", "the map plot"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    odo = _as_poses(odometry, "odometry")
    cor = _as_poses(corrected, "corrected")
    if groundtruth is not None:
        gt = _as_poses(groundtruth, "groundtruth")
        ax.plot(gt[:, 0], gt[:, 1], color="0.55", lw=2.5, label="ground truth")
    ax.plot(odo[:, 0], odo[:, 1], color="tab:red", lw=1, label="raw odometry")
    ax.plot(cor[:, 0], cor[:, 1], color="tab:blue", lw=1, label="hippomap map")
    if loops is not None and len(loops):
        seg = np.asarray(loops, dtype=float)
        for s in seg:
            ax.plot(s[:, 0], s[:, 1], color="tab:green", lw=0.8)
        ax.plot([], [], color="tab:green", lw=0.8, label=f"loop closures ({len(seg)})")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def align_to(ref_times: Any, ref_poses: Any, times: Any, poses: Any) -> np.ndarray | None:
    """``ref`` (e.g. ground truth) rigidly aligned onto ``(times, poses)`` for plotting;
    None when the two cannot be matched by timestamp."""
    with requires("eval", "aligning the ground truth onto the map"):
        from evo.core import sync

    try:
        ref, est = sync.associate_trajectories(
            to_evo(ref_times, ref_poses, "ref"), to_evo(times, poses, "est"), max_diff=0.1
        )
        ref.align(est, correct_scale=False)
    except Exception:
        return None
    return from_evo(ref)[1]


def export_map(
    out_dir: str | Path,
    cmap: Any,
    times: Any,
    odometry: Any,
    corrected: Any,
    decisions: list[dict[str, Any]],
    groundtruth: tuple[Any, Any] | None = None,
    loop_segments: Any | None = None,
    title: str = "hippomap",
) -> Path:
    """Write a run's exports: ``map.tum`` (corrected trajectory), ``odometry.tum`` (raw),
    ``map.g2o``, ``map.json`` (graph), ``loop_closures.json`` and ``map.png`` (with the
    ground truth aligned onto the map when given)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    links = cmap.links
    write_tum(out / "map.tum", times, corrected)
    write_tum(out / "odometry.tum", times, odometry)
    write_g2o(
        out / "map.g2o",
        cmap.poses,
        links["source"],
        links["target"],
        links["transform"],
        link_information(cmap),
        cmap.link_coupling(),
    )
    write_json(
        out / "map.json",
        graph_dict(
            cmap.poses,
            cmap.place_codes,
            cmap.frames,
            cmap.times,
            links["source"],
            links["target"],
            links["transform"],
            links["kind"],
        ),
    )
    write_json(out / "loop_closures.json", decisions)
    if len(np.asarray(times)):
        gt = align_to(*groundtruth, times, corrected) if groundtruth is not None else None
        plot_map(out / "map.png", odometry, corrected, gt, loop_segments, title=title)
    return out
