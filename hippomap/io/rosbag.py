"""ROS 1 / ROS 2 bags as hippomap data sets, read with the ``rosbags`` library.

An image topic (``sensor_msgs/Image`` mono8/bgr8/rgb8 or ``sensor_msgs/CompressedImage``)
and an odometry topic (``nav_msgs/Odometry``: the planar pose of each message becomes
the increment from the previous one) are turned into the same time-ordered
:class:`~hippomap.io.datasets.SensorDataset` the other readers produce. Frames are decoded
when the data set is read (bags are small on a robot's time scale; a long bag can be
limited with ``max_frames``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..errors import InputError
from ..extras import requires
from ..geometry import between
from ..inputs import Frame, Odometry
from .datasets import SensorDataset, _check_increasing


@dataclass(frozen=True)
class DecodedFrame:
    """A frame already in memory (same interface as :class:`~hippomap.io.datasets.FrameRef`)."""

    t: float
    image: np.ndarray

    def load(self) -> Frame:
        return Frame(self.t, self.image)


def _image(msg, msgtype: str) -> np.ndarray:
    import cv2

    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"undecodable compressed image ({msg.format})")
        return img
    enc = msg.encoding.lower()
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if enc in ("mono8", "8uc1"):
        return data.reshape(msg.height, msg.step)[:, : msg.width].copy()
    if enc in ("bgr8", "rgb8", "8uc3"):
        img = data.reshape(msg.height, msg.step)[:, : msg.width * 3].reshape(msg.height, msg.width, 3)
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY if enc == "rgb8" else cv2.COLOR_BGR2GRAY)
    raise InputError(f"unsupported image encoding {msg.encoding!r} (mono8, bgr8, rgb8 or compressed)")


def _yaw(q) -> float:
    return float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2)))


def read_rosbag(
    path: str | Path,
    image_topic: str,
    odometry_topic: str,
    max_frames: int | None = None,
    groundtruth_topic: str | None = None,
) -> SensorDataset:
    """Read a ROS 1 (``.bag``) or ROS 2 (folder) bag. Times are the messages' header stamps.
    ``groundtruth_topic`` (optional: ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``,
    e.g. what :func:`hippomap.io.session_export.write_rosbag2` writes) becomes the data set's
    ground truth."""
    with requires("rosbag", "reading a ROS bag"):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise InputError(f"bag {path} does not exist")
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        got = _read_topics(reader, path, image_topic, odometry_topic, groundtruth_topic, max_frames)
    if len(got.poses) < 2:
        raise InputError(f"bag {path}: fewer than two odometry messages on {odometry_topic!r}")
    frames = sorted(got.frames, key=lambda f: f.t)
    _check_increasing(np.array(got.stamps), Path(f"{path}[{odometry_topic}]"))
    _check_increasing(np.array([f.t for f in frames]), Path(f"{path}[{image_topic}]"))
    arr = np.array(got.poses)
    inc = between(arr[:-1], arr[1:])
    odometry = [
        Odometry(float(t), increment=cast("tuple[float, float, float]", tuple(map(float, d))))
        for t, d in zip(got.stamps[1:], inc)
    ]
    gt = None
    if got.gt_t:
        _check_increasing(np.array(got.gt_t), Path(f"{path}[{groundtruth_topic}]"))
        gt = (np.array(got.gt_t), np.array(got.gt_p, dtype=float))
    return SensorDataset(odometry, frames, gt, path)


@dataclass
class _BagMessages:
    """What :func:`read_rosbag` takes from a bag, in the bag's order: the decoded frames, the odometry poses
    and the ground-truth poses (x, y, yaw) with their header stamps."""

    frames: list[DecodedFrame] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)
    gt_t: list[float] = field(default_factory=list)
    gt_p: list[tuple[float, float, float]] = field(default_factory=list)


def _read_topics(
    reader: Any,
    path: Path,
    image_topic: str,
    odometry_topic: str,
    groundtruth_topic: str | None,
    max_frames: int | None,
) -> _BagMessages:
    """The messages of the wanted topics from an open ``rosbags`` reader (the first ``max_frames`` images);
    a missing topic or a topic of the wrong message type is an :class:`InputError`."""
    got = _BagMessages()
    topics = {c.topic: c for c in reader.connections}
    wanted = (image_topic, odometry_topic) + ((groundtruth_topic,) if groundtruth_topic else ())
    for topic in wanted:
        if topic not in topics:
            raise InputError(f"bag {path} has no topic {topic!r}; topics: {sorted(topics)}")
    conns = [c for c in reader.connections if c.topic in wanted]
    for conn, _, raw in reader.messages(connections=conns):
        msg: Any = reader.deserialize(raw, conn.msgtype)  # a ROS message of conn.msgtype
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if conn.topic == image_topic:
            if max_frames is None or len(got.frames) < max_frames:
                got.frames.append(DecodedFrame(t, _image(msg, conn.msgtype)))
        elif conn.topic == groundtruth_topic:
            if not conn.msgtype.endswith(("PoseStamped", "Odometry")):
                raise InputError(
                    f"ground-truth topic {groundtruth_topic!r} carries {conn.msgtype}, not "
                    "geometry_msgs/PoseStamped or nav_msgs/Odometry"
                )
            p = msg.pose if conn.msgtype.endswith("PoseStamped") else msg.pose.pose
            got.gt_t.append(t)
            got.gt_p.append((p.position.x, p.position.y, _yaw(p.orientation)))
        else:
            if not conn.msgtype.endswith("Odometry"):
                raise InputError(f"odometry topic {odometry_topic!r} carries {conn.msgtype}, not nav_msgs/Odometry")
            p = msg.pose.pose
            got.stamps.append(t)
            got.poses.append((p.position.x, p.position.y, _yaw(p.orientation)))
    return got
