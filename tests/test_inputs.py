"""Input records (odometry, frames) and the camera data-set readers."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from hippomap.errors import InputError
from hippomap.geometry import integrate
from hippomap.inputs import Frame, Odometry, TimeOrder, decode_jpeg
from hippomap.io.datasets import read_folder_dataset, read_tum_rgbd


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"t": float("nan"), "v": 1, "omega": 0}, "odometry t must be finite, got nan"),
        ({"t": 0, "v": float("inf"), "omega": 0}, "odometry v must be finite, got inf"),
        ({"t": 0, "v": 1, "omega": "x"}, "odometry omega must be a number, got 'x'"),
        ({"t": 0, "v": 1}, "needs v and omega"),
        ({"t": 0, "increment": (1, 2)}, "must be (dx, dy, dtheta)"),
        ({"t": 0, "increment": (1, 2, float("-inf"))}, "odometry dtheta must be finite, got -inf"),
        ({"t": 0, "v": 1, "omega": 0, "increment": (1, 2, 3)}, "not both"),
    ],
)
def test_bad_odometry_names_the_value(kwargs, needle):
    with pytest.raises(InputError) as err:
        Odometry(**kwargs)
    assert needle in str(err.value)


def test_velocity_increment_is_the_exact_arc():
    # a quarter circle of radius r = v / omega ends at (r, r) facing +90 degrees
    v, w = 1.0, math.pi / 2
    inc = Odometry(0.0, v=v, omega=w).as_increment(1.0)
    r = v / w
    np.testing.assert_allclose(inc, [r, r, math.pi / 2], atol=1e-12)
    # many small arcs compose to the same end pose as one big arc
    small = integrate([Odometry(0.0, v=v, omega=w).as_increment(0.01)] * 100)[-1]
    np.testing.assert_allclose(small, inc, atol=1e-9)
    np.testing.assert_allclose(Odometry(0.0, v=2.0, omega=0.0).as_increment(0.5), [1.0, 0.0, 0.0], atol=1e-12)
    assert Odometry(0.0, increment=(0.1, 0.2, 0.3)).as_increment(5.0) == (0.1, 0.2, 0.3)


def test_time_order():
    order = TimeOrder("odometry")
    order.check(1.0)
    order.check(2.0)
    with pytest.raises(InputError, match="odometry timestamps must increase: 2.0 follows 2.0"):
        order.check(2.0)


def test_frames_and_jpeg():
    img = (np.random.default_rng(0).random((40, 60)) * 255).astype(np.uint8)
    ok, jpg = cv2.imencode(".jpg", img)
    dec = decode_jpeg(jpg.tobytes())
    assert dec.shape == (40, 60) and np.abs(dec.astype(int) - img).mean() < 30
    with pytest.raises(InputError, match="empty image payload"):
        decode_jpeg(b"")
    with pytest.raises(InputError, match="not a JPEG or PNG"):
        decode_jpeg(b"GIF89a....")
    with pytest.raises(InputError, match="corrupt image payload"):
        decode_jpeg(jpg.tobytes()[:3] + b"\x00" * 50)
    with pytest.raises(InputError, match="must be uint8, got float64"):
        Frame(0.0, img.astype(float))
    with pytest.raises(InputError, match="non-empty"):
        Frame(0.0, np.zeros((0, 5), np.uint8))
    bgr = np.dstack([img, img, img])
    np.testing.assert_array_equal(Frame(1.0, bgr).gray(), img)


def _folder(tmp_path, n=5):
    (tmp_path / "frames").mkdir()
    rows = ["t,file"]
    for k in range(n):
        cv2.imwrite(str(tmp_path / "frames" / f"{k:03d}.png"), np.full((10, 12), k * 20, np.uint8))
        rows.append(f"{k * 0.5 + 0.25},{k:03d}.png")
    (tmp_path / "frames.csv").write_text("\n".join(rows) + "\n")
    odo = ["t,v,omega"] + [f"{k * 0.2},{0.5},{0.1}" for k in range(15)]
    (tmp_path / "odometry.csv").write_text("\n".join(odo) + "\n")
    (tmp_path / "groundtruth.csv").write_text("t,x,y,theta\n0,0,0,0\n1,0.5,0,0.1\n")
    return tmp_path


def test_folder_dataset_events_in_time_order(tmp_path):
    ds = read_folder_dataset(_folder(tmp_path))
    assert len(ds.odometry) == 15 and len(ds.frames) == 5
    times = [e.t for e in ds.events()]
    assert times == sorted(times) and len(times) == 20
    frame = ds.frames[2].load()
    assert frame.image.shape == (10, 12) and int(frame.image[0, 0]) == 40
    assert ds.groundtruth is not None and ds.groundtruth[1].shape == (2, 3)


@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda p: (p / "odometry.csv").write_text("t,v\n0,1\n"), "header must be 't,v,omega'"),
        (
            lambda p: (p / "odometry.csv").write_text("t,v,omega\n0,1,0\n0,1,0\n"),
            "odometry.csv:3: timestamps must increase",
        ),
        (lambda p: (p / "odometry.csv").write_text("t,v,omega\n0,nan,0\n"), "non-finite value nan"),
        (
            lambda p: (p / "frames.csv").write_text("t,file\n0,missing.png\n"),
            "frames.csv:2: image 'missing.png' not found",
        ),
        (lambda p: (p / "frames.csv").unlink(), "frames.csv is missing"),
    ],
)
def test_folder_dataset_errors(tmp_path, edit, needle):
    _folder(tmp_path)
    edit(tmp_path)
    with pytest.raises(InputError) as err:
        read_folder_dataset(tmp_path)
    assert needle in str(err.value)


def test_tum_rgbd_folder(tmp_path):
    (tmp_path / "rgb").mkdir()
    lines = ["# color images"]
    for k in range(3):
        cv2.imwrite(str(tmp_path / "rgb" / f"{k}.png"), np.zeros((8, 8), np.uint8))
        lines.append(f"{10 + k:.6f} rgb/{k}.png")
    (tmp_path / "rgb.txt").write_text("\n".join(lines) + "\n")
    poses = integrate([[0.1, 0, 0.2]] * 4)
    tum = [f"{10 + 0.3 * k} {x} {y} 0 0 0 {math.sin(th / 2)} {math.cos(th / 2)}" for k, (x, y, th) in enumerate(poses)]
    (tmp_path / "odometry.txt").write_text("\n".join(tum) + "\n")
    ds = read_tum_rgbd(tmp_path)
    assert len(ds.frames) == 3 and len(ds.odometry) == 4
    np.testing.assert_allclose(integrate([o.increment for o in ds.odometry]), poses, atol=1e-9)
    (tmp_path / "odometry.txt").unlink()
    with pytest.raises(InputError, match="no wheel odometry"):
        read_tum_rgbd(tmp_path)
