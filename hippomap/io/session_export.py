"""A recorded run's inputs written out again: as a data folder and as a ROS 2 bag.

What a mapping session stored (odometry readings, camera frames exactly as received, the
ground truth some readings carry) becomes a data set that ``hippomap run`` reads back, so
a run recorded by the service can be re-run offline:

* :func:`write_data_zip` / :func:`write_data_dir`: the project's data-folder format
  (``frames/``, ``frames.csv`` ``t,file``, ``odometry.csv``, ``groundtruth.csv`` when
  readings carried ``gt``, and ``config.json`` with the session's config overrides).
  Readings sent as velocities give ``odometry.csv`` ``t,v,omega``; a run with any reading
  sent as an increment gives ``t,dx,dy,dtheta`` for all of them (each velocity reading
  turned into the increment the mapper integrated from it), which
  :func:`hippomap.io.datasets.read_folder_odometry` also reads.
* :func:`write_rosbag2`: a ROS 2 bag (``rosbags``' writer) with the frames as
  ``sensor_msgs/CompressedImage`` (the stored JPEG/PNG bytes), the odometry as
  ``nav_msgs/Odometry`` poses (the readings' increments chained from the origin), and the
  ground truth as ``geometry_msgs/PoseStamped``; :func:`hippomap.io.rosbag.read_rosbag` turns
  it back into the same inputs.

Inputs arrive as an iterable of :class:`~hippomap.inputs.Odometry` and
:class:`EncodedFrame` in the order they were recorded; frames are written one at a time,
so a long run never sits in memory (only its odometry table does: a few numbers a reading).
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from ..errors import InputError
from ..extras import requires
from ..geometry import compose
from ..inputs import Odometry

#: topics of the bags written here (pass them to ``hippomap run BAG --image-topic ... --odom-topic ...``)
IMAGE_TOPIC = "/camera/image/compressed"
ODOM_TOPIC = "/odom"
GROUNDTRUTH_TOPIC = "/ground_truth"
#: the bag's first odometry message is the origin pose, this long (or half the first reading's time,
#: if less) before the first reading: the reader takes each message's pose relative to the previous
#: one, so the first reading needs one
ORIGIN_LEAD_S = 1e-3


@dataclass(frozen=True)
class EncodedFrame:
    """A camera frame as recorded: its time and the encoded image (JPEG or PNG bytes)."""

    t: float
    data: bytes

    @property
    def extension(self) -> str:
        """``png`` or ``jpg``, from the magic bytes (anything not PNG was stored as a JPEG)."""
        return "png" if self.data[:8] == b"\x89PNG\r\n\x1a\n" else "jpg"


Input = Odometry | EncodedFrame


def _check(item: Any) -> None:
    if not isinstance(item, (Odometry, EncodedFrame)):
        raise InputError(f"an exported input must be Odometry or EncodedFrame, got {type(item).__name__}")


def increments(readings: list[Odometry]) -> np.ndarray:
    """(N, 3) increments the mapper integrates from ``readings`` (velocity readings over the time
    since the previous reading, exactly :meth:`~hippomap.inputs.Odometry.as_increment`; the first
    velocity reading moves nothing, as in :meth:`hippomap.mapper.Mapper.step`)."""
    out = np.zeros((len(readings), 3))
    for k, o in enumerate(readings):  # one call a reading: the mapper's own arc formula, bit for bit
        if o.increment is not None or k > 0:
            out[k] = o.as_increment(o.t - readings[k - 1].t if k > 0 else 0.0)
    return out


def odometry_csv(readings: list[Odometry]) -> str:
    """``odometry.csv`` of the readings: ``t,v,omega`` when all are velocities, else
    ``t,dx,dy,dtheta`` (see :func:`increments`). Numbers are written to round-trip exactly."""
    if all(o.increment is None for o in readings):
        rows = [f"{o.t!r},{o.v!r},{o.omega!r}" for o in readings]
        return "\n".join(["t,v,omega", *rows]) + "\n"
    inc = increments(readings)
    rows = [f"{o.t!r},{d[0]!r},{d[1]!r},{d[2]!r}" for o, d in zip(readings, inc.tolist())]
    return "\n".join(["t,dx,dy,dtheta", *rows]) + "\n"


def groundtruth_rows(readings: list[Odometry]) -> list[tuple[float, float, float, float]]:
    """``(t, x, y, theta)`` of every reading that carried ground truth."""
    return [(o.t, *o.gt) for o in readings if o.gt is not None]


def groundtruth_csv(readings: list[Odometry]) -> str | None:
    """``groundtruth.csv`` (``t,x,y,theta``) of the readings, or None when none carried ``gt``."""
    rows = groundtruth_rows(readings)
    if not rows:
        return None
    return "\n".join(["t,x,y,theta", *(",".join(repr(float(v)) for v in r) for r in rows)]) + "\n"


def write_data(
    inputs: Iterable[Input], put: Callable[[str, bytes], None], config: dict[str, Any] | None = None
) -> dict[str, int]:
    """Write ``inputs`` as a data folder through ``put(relative_name, content)``: each frame as
    it comes (``frames/NNNNNN.jpg|png``, the bytes as recorded), then ``frames.csv``,
    ``odometry.csv``, ``groundtruth.csv`` (when readings carried ``gt``) and ``config.json``
    (``config``, the overrides to pass as ``hippomap run --config``). Returns the counts."""
    readings: list[Odometry] = []
    frame_rows = ["t,file"]
    for item in inputs:
        _check(item)
        if isinstance(item, Odometry):
            readings.append(item)
            continue
        name = f"{len(frame_rows) - 1:06d}.{item.extension}"
        put(f"frames/{name}", item.data)
        frame_rows.append(f"{item.t!r},{name}")
    if not readings:
        raise InputError("no odometry to export: a data folder needs odometry.csv")
    put("frames.csv", ("\n".join(frame_rows) + "\n").encode())
    put("odometry.csv", odometry_csv(readings).encode())
    gt = groundtruth_csv(readings)
    if gt is not None:
        put("groundtruth.csv", gt.encode())
    if config is not None:
        put("config.json", json.dumps(config, indent=1).encode())
    return {
        "odometry": len(readings),
        "frames": len(frame_rows) - 1,
        "groundtruth": 0 if gt is None else gt.count("\n") - 1,
    }


def write_data_dir(folder: str | Path, inputs: Iterable[Input], config: dict[str, Any] | None = None) -> Path:
    """:func:`write_data` into a folder (created; must not hold a data set already)."""
    folder = Path(folder)
    if (folder / "frames.csv").exists():
        raise InputError(f"{folder} already holds a data set (frames.csv)")
    (folder / "frames").mkdir(parents=True, exist_ok=True)

    def put(name: str, data: bytes) -> None:
        (folder / name).write_bytes(data)

    write_data(inputs, put, config)
    return folder


def _zip_put(zf: zipfile.ZipFile, root: str) -> Callable[[str, bytes], None]:
    def put(name: str, data: bytes) -> None:
        # images are compressed already: stored as they are; the tables deflate well
        method = zipfile.ZIP_STORED if name.startswith("frames/") else zipfile.ZIP_DEFLATED
        zf.writestr(f"{root}/{name}", data, compress_type=method)

    return put


def write_data_zip(
    target: str | Path | IO[bytes], inputs: Iterable[Input], root: str = "data", config: dict[str, Any] | None = None
) -> dict[str, int]:
    """:func:`write_data` into a zip file (a path or a writable binary file), every entry under
    the folder ``root`` (so unzipping gives a folder ``hippomap run`` reads). Returns the counts."""
    _check_root(root)
    with zipfile.ZipFile(target, "w") as zf:
        return write_data(inputs, _zip_put(zf, root), config)


def _check_root(root: str) -> None:
    if not root or root in (".", "..") or "/" in root or "\\" in root:
        raise InputError(f"zip folder name must be a plain name, got {root!r}")


# ---------------------------------------------------------------- ROS 2 bags
def _stamp(t: float) -> tuple[int, int]:
    """(sec, nanosec) of ROS's ``builtin_interfaces/Time`` (sec is a signed 32-bit integer)."""
    ns = round(t * 1e9)
    sec, nsec = divmod(ns, 10**9)
    if not -(2**31) <= sec < 2**31:
        raise InputError(f"time {t!r} s does not fit a ROS time stamp (32-bit seconds)")
    return int(sec), int(nsec)


def _log_ns(t: float) -> int:
    """A message's log time in nanoseconds (a bag orders messages by it: never negative)."""
    if not t > 0:
        raise InputError(f"time {t!r} s cannot be written to a bag: its log times count from 0 (positive times only)")
    return int(round(t * 1e9))


class _BagMessages:
    """Builds the messages of the bags' three kinds from rosbags' ROS 2 Humble types."""

    def __init__(self) -> None:
        with requires("rosbag", "writing a ROS 2 bag"):
            from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types

    def header(self, t: float, frame_id: str) -> Any:
        sec, nsec = _stamp(t)
        return self.T["std_msgs/msg/Header"](
            stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
        )

    def pose(self, x: float, y: float, th: float) -> Any:
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)),
        )

    def odometry(self, t: float, pose: np.ndarray, v: float = 0.0, omega: float = 0.0) -> bytes:
        T = self.T
        vec = T["geometry_msgs/msg/Vector3"]
        msg = T["nav_msgs/msg/Odometry"](
            header=self.header(t, "odom"),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(*pose), covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=vec(x=float(v), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(omega))
                ),
                covariance=np.zeros(36),
            ),
        )
        return bytes(self.ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))

    def image(self, frame: EncodedFrame) -> bytes:
        msg = self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(frame.t, "camera"),
            format="png" if frame.extension == "png" else "jpeg",
            data=np.frombuffer(frame.data, np.uint8),
        )
        return bytes(self.ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))

    def groundtruth(self, t: float, pose: tuple[float, float, float]) -> bytes:
        msg = self.T["geometry_msgs/msg/PoseStamped"](header=self.header(t, "ground_truth"), pose=self.pose(*pose))
        return bytes(self.ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


def write_rosbag2(
    path: str | Path,
    inputs: Iterable[Input],
    image_topic: str = IMAGE_TOPIC,
    odom_topic: str = ODOM_TOPIC,
    groundtruth_topic: str = GROUNDTRUTH_TOPIC,
) -> dict[str, int]:
    """Write ``inputs`` as a ROS 2 bag (a new folder ``path``, SQLite storage). The odometry
    topic carries poses: the origin :data:`ORIGIN_LEAD_S` before the first reading, then the
    readings' increments (:func:`increments`) chained, so that the bag reader's increments
    between consecutive messages are the readings again. Returns the message counts."""
    with requires("rosbag", "writing a ROS 2 bag"):
        from rosbags.rosbag2 import Writer

    path = Path(path)
    if path.exists():
        raise InputError(f"{path} exists already: a ROS 2 bag is written to a new folder")
    mk = _BagMessages()
    counts = {"odometry": 0, "frames": 0, "groundtruth": 0}
    pose = np.zeros(3)
    prev: Odometry | None = None
    with Writer(path, version=9) as w:
        c_img = w.add_connection(image_topic, "sensor_msgs/msg/CompressedImage", typestore=mk.ts)
        c_odo = w.add_connection(odom_topic, "nav_msgs/msg/Odometry", typestore=mk.ts)
        c_gt = w.add_connection(groundtruth_topic, "geometry_msgs/msg/PoseStamped", typestore=mk.ts)
        for item in inputs:
            _check(item)
            if isinstance(item, EncodedFrame):
                w.write(c_img, _log_ns(item.t), mk.image(item))
                counts["frames"] += 1
                continue
            if prev is None:
                t0 = item.t - min(ORIGIN_LEAD_S, item.t / 2)
                w.write(c_odo, _log_ns(t0), mk.odometry(t0, pose))
            if item.increment is not None or prev is not None:
                pose = compose(pose, item.as_increment(item.t - prev.t if prev is not None else 0.0))
            w.write(c_odo, _log_ns(item.t), mk.odometry(item.t, pose, item.v or 0.0, item.omega or 0.0))
            counts["odometry"] += 1
            if item.gt is not None:
                w.write(c_gt, _log_ns(item.t), mk.groundtruth(item.t, item.gt))
                counts["groundtruth"] += 1
            prev = item
    if counts["odometry"] == 0:
        shutil.rmtree(path, ignore_errors=True)
        raise InputError("no odometry to export: a bag needs odometry messages")
    return counts


def zip_folder(folder: str | Path, target: str | Path | IO[bytes], root: str) -> None:
    """Zip every file of ``folder`` under the folder name ``root`` (stored: bag files and images
    are compressed or binary already)."""
    _check_root(root)
    folder = Path(folder)
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_STORED) as zf:
        for f in sorted(p for p in folder.rglob("*") if p.is_file()):
            zf.write(f, f"{root}/{f.relative_to(folder).as_posix()}")


def write_rosbag2_zip(
    target: str | Path | IO[bytes], inputs: Iterable[Input], root: str = "bag", **topics: str
) -> dict[str, int]:
    """:func:`write_rosbag2` into a scratch folder, zipped under the folder name ``root``."""
    _check_root(root)
    with tempfile.TemporaryDirectory(prefix="hippomap-bag-") as tmp:
        counts = write_rosbag2(Path(tmp) / root, inputs, **topics)
        zip_folder(Path(tmp) / root, target, root)
    return counts
