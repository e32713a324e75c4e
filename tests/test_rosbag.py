"""ROS 2 and ROS 1 bags written with rosbags' own writers are read back as data sets."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from hippomap.errors import InputError
from hippomap.geometry import integrate
from hippomap.io.rosbag import read_rosbag

TS = get_typestore(Stores.ROS2_HUMBLE)


def _msgs(n=6):
    T = TS.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    poses = integrate([[0.2, 0.0, 0.1]] * (n - 1))
    out = []
    for k, (x, y, th) in enumerate(poses):
        stamp = Time(sec=100 + k, nanosec=0)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)),
            ),
            covariance=np.zeros(36),
        )
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=np.zeros(36),
        )
        odo = T["nav_msgs/msg/Odometry"](
            header=Header(stamp=stamp, frame_id="odom"), child_frame_id="base", pose=pose, twist=twist
        )
        img = np.full((12, 16), 10 * k, np.uint8)
        ok, jpg = cv2.imencode(".jpg", img)
        header = Header(stamp=Time(sec=100 + k, nanosec=500_000_000), frame_id="cam")
        cimg = T["sensor_msgs/msg/CompressedImage"](
            header=header, format="jpeg", data=np.frombuffer(jpg.tobytes(), np.uint8)
        )
        raw = T["sensor_msgs/msg/Image"](
            header=Header(stamp=Time(sec=100 + k, nanosec=500_000_000), frame_id="cam"),
            height=12,
            width=16,
            encoding="mono8",
            is_bigendian=0,
            step=16,
            data=img.reshape(-1),
        )
        out.append((k, odo, cimg, raw))
    return out, poses


def test_ros2_bag(tmp_path):
    from rosbags.rosbag2 import Writer

    msgs, poses = _msgs()
    with Writer(tmp_path / "bag", version=9) as w:
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS)
        ci = w.add_connection("/cam/compressed", "sensor_msgs/msg/CompressedImage", typestore=TS)
        for k, odo, cimg, _ in msgs:
            w.write(co, (100 + k) * 10**9, TS.serialize_cdr(odo, "nav_msgs/msg/Odometry"))
            w.write(ci, (100 + k) * 10**9 + 5 * 10**8, TS.serialize_cdr(cimg, "sensor_msgs/msg/CompressedImage"))
    ds = read_rosbag(tmp_path / "bag", "/cam/compressed", "/odom")
    assert len(ds.frames) == 6 and len(ds.odometry) == 5
    np.testing.assert_allclose(integrate([o.increment for o in ds.odometry]), poses, atol=1e-9)
    f = ds.frames[3].load()
    assert f.t == pytest.approx(103.5) and abs(int(f.image.mean()) - 30) <= 2
    times = [e.t for e in ds.events()]
    assert times == sorted(times)
    with pytest.raises(InputError, match="has no topic '/nope'"):
        read_rosbag(tmp_path / "bag", "/nope", "/odom")


def test_ros1_bag_raw_images(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    msgs, poses = _msgs(4)
    with Writer(tmp_path / "x.bag") as w:
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ros1)
        ci = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ros1)
        for k, odo, _, raw in msgs:
            w.write(co, (100 + k) * 10**9, ros1.serialize_ros1(_to(ros1, odo), "nav_msgs/msg/Odometry"))
            w.write(ci, (100 + k) * 10**9 + 5 * 10**8, ros1.serialize_ros1(_to(ros1, raw), "sensor_msgs/msg/Image"))
    ds = read_rosbag(tmp_path / "x.bag", "/cam", "/odom")
    assert len(ds.frames) == 4
    assert int(ds.frames[2].load().image[0, 0]) == 20
    np.testing.assert_allclose(integrate([o.increment for o in ds.odometry]), poses, atol=1e-9)


def _to(store, msg):
    """Rebuild a ROS 2 message object with the ROS 1 store's classes (Header gains seq)."""
    import dataclasses

    name = type(msg).__msgtype__ if hasattr(type(msg), "__msgtype__") else None
    cls = store.types[name]
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "seq":
            kwargs[f.name] = 0
            continue
        v = getattr(msg, f.name)
        kwargs[f.name] = _to(store, v) if dataclasses.is_dataclass(v) else v
    return cls(**kwargs)
