"""Peers for ``bench/bench_maps.py``: OpenRatSLAM (built from its source, run on a data
folder) and GTSAM (robust pose-graph optimisation of the Bicocca g2o proposal files).

Bench-only code: nothing in ``hippomap/`` imports it. GTSAM is imported lazily
(``pip install gtsam``), so the OpenRatSLAM side works without it.
"""

from __future__ import annotations

import csv
import hashlib
import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hippomap.io.datasets import read_folder_odometry

# OpenRatSLAM's PosecellNetwork::PosecellAction (posecell_network.h)
ORS_NO_ACTION, ORS_CREATE_NODE, ORS_CREATE_EDGE, ORS_SET_NODE = 0, 1, 2, 3


def cache_root() -> Path:
    """Where built peers and rendered runs are kept between bench runs."""
    env = os.environ.get("HIPPOMAP_BENCH_CACHE")
    root = Path(env) if env else Path.home() / ".cache" / "hippomap-bench"
    root.mkdir(parents=True, exist_ok=True)
    return root


def _tree_hash(paths: list[Path]) -> str:
    h = hashlib.sha1()
    for p in sorted(paths):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:12]


# --------------------------------------------------------------------------------------
# OpenRatSLAM
# --------------------------------------------------------------------------------------


def build_ors(peer_dir: Path, cache: Path | None = None) -> Path:
    """Build OpenRatSLAM's core + driver (the peer's ``build.sh``) once per source version;
    returns the driver executable."""
    peer_dir = Path(peer_dir)
    if not (peer_dir / "build.sh").is_file():
        raise SystemExit(f"OpenRatSLAM peer not found at {peer_dir} (expected build.sh there)")
    sources = [peer_dir / "driver.cpp", peer_dir / "build.sh", *sorted((peer_dir / "src").rglob("*.[ch]*"))]
    out = (cache or cache_root()) / "ors" / _tree_hash(sources)
    exe = out / "ors_driver"
    if exe.is_file():
        return exe
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    r = subprocess.run(["sh", str(peer_dir / "build.sh"), str(out)], capture_output=True, text=True)
    if r.returncode != 0 or not exe.is_file():
        raise SystemExit(
            f"building OpenRatSLAM failed (needs: apt-get install g++ libboost-dev libopencv-dev "
            f"pkg-config):\n{r.stdout}\n{r.stderr}"
        )
    print(f"built OpenRatSLAM driver in {time.perf_counter() - t0:.0f} s -> {exe}", flush=True)
    return exe


def ors_config_text(peer_dir: Path, width: int, height: int, threshold: float | None) -> str:
    """The peer's stock St Lucia config for this image size (crop scaled from 640x480 when
    the size has no shipped config), with ``vt_match_threshold`` replaced when given."""
    cfgs = Path(peer_dir) / "configs"
    exact = cfgs / f"stlucia_{width}x{height}.ini"
    text = (exact if exact.is_file() else cfgs / "stlucia_640x480.ini").read_text()
    if not exact.is_file():
        sx, sy = width / 640.0, height / 480.0

        def scale(m: re.Match) -> str:
            s = sx if "_x_" in m.group(1) else sy
            return f"{m.group(1)}={int(round(int(m.group(2)) * s))}"

        text = re.sub(r"^(image_crop_[xy]_m(?:in|ax))\s*=\s*(\d+)", scale, text, flags=re.M)
    if threshold is not None:
        text, n = re.subn(r"^vt_match_threshold\s*=.*$", f"vt_match_threshold = {threshold:g}", text, flags=re.M)
        if n != 1:
            raise SystemExit("OpenRatSLAM config has no vt_match_threshold line")
    return text


def stock_threshold(peer_dir: Path, width: int, height: int) -> float:
    m = re.search(r"^vt_match_threshold\s*=\s*([0-9.eE+-]+)", ors_config_text(peer_dir, width, height, None), re.M)
    return float(m.group(1)) if m else float("nan")


def _read_ors_frames(path: Path) -> list[dict[str, float]]:
    """The driver's per-frame CSV. The driver prints each row into a 256-byte buffer; when
    ``vt_err`` is huge (DBL_MAX when no template passed the pre-filter, printed with ``%.6f``
    as 300+ digits) the row is cut inside ``vt_err`` and loses its newline, so the next row is
    glued to it (and so on, when that one is cut too): a line of ``3 k + 10`` fields holds k cut
    rows and one whole row. A cut row keeps ``frame``, ``t``, ``vt_id``; its experience comes
    from the next whole row's ``src_exp`` (the experience current before that row's odometry;
    see the comment on runs of cut rows below), and its action is inferred: a new
    experience is CREATE_NODE, a move to another existing one CREATE_EDGE (the link-count
    check in :func:`run_ors` says whether the rebuilt links match the driver's); its
    ``core_us`` is lost (timing comes from the driver's summary line, which has every frame)."""
    cols = ["frame", "t", "vt_id", "vt_err", "n_vt", "action", "src_exp", "exp_id", "n_exp", "core_us"]
    rows: list[dict[str, float]] = []
    cut: set[int] = set()
    with path.open() as fh:
        next(fh)
        for line in fh:
            f = line.strip().split(",")
            if len(f) == len(cols):
                rows.append({k: float(v) for k, v in zip(cols, f)})
            elif len(f) > len(cols) and (len(f) - len(cols)) % 3 == 0:
                frame = int(f[0])
                k = (len(f) - len(cols)) // 3
                for i in range(k):
                    cut.add(len(rows))
                    rows.append(
                        {
                            "frame": float(frame + i),
                            "t": float(f[3 * i + 1]),
                            "vt_id": float(f[3 * i + 2]),
                            "vt_err": float("inf"),
                            "n_vt": float("nan"),
                            "action": float("nan"),
                            "src_exp": float("nan"),
                            "exp_id": float("nan"),
                            "n_exp": float("nan"),
                            "core_us": float("nan"),
                        }
                    )
                rows.append({"frame": float(frame + k), **{c: float(v) for c, v in zip(cols[1:], f[-9:])}})
            elif f and f[0]:
                raise ValueError(f"{path}: unexpected line {line[:80]!r}")
    # experiences of runs of cut rows a..b, from the whole row after them. Experience ids are
    # handed out consecutively, so n new ids behind that row's experience mean n of the cut
    # rows each made one (the last n); otherwise the run moved to that experience at once.
    k = 0
    max_id = -1
    while k < len(rows):
        if k not in cut:
            max_id = max(max_id, int(rows[k]["exp_id"]))
            k += 1
            continue
        a = k
        while k in cut:
            k += 1
        b = k - 1
        if k < len(rows):
            e = int(rows[k]["exp_id"]) if a == 0 else int(rows[k]["src_exp"])  # frame 1's src_exp is a default 0
        else:
            e = int(rows[a - 1]["exp_id"]) if a > 0 else -1
        prev = int(rows[a - 1]["exp_id"]) if a > 0 else e
        n_new, run = e - max_id, b - a + 1
        if 0 < n_new <= run:
            ids = [prev] * (run - n_new) + list(range(max_id + 1, e + 1))
        else:
            ids = [e] * run
        for i, x in enumerate(ids):
            rows[a + i]["exp_id"] = float(x)
        max_id = max(max_id, *ids)
    seen: set[int] = set()
    for k, row in enumerate(rows):  # actions, forwards
        if k in cut:
            prev = int(rows[k - 1]["exp_id"]) if k > 0 else -1
            e = int(row["exp_id"])
            row["src_exp"] = float(prev)
            if k == 0 or e == prev:
                row["action"] = float(ORS_NO_ACTION)
            elif e not in seen:
                row["action"] = float(ORS_CREATE_NODE)
            else:
                row["action"] = float(ORS_CREATE_EDGE)
        seen.add(int(row["exp_id"]))
    return rows


def ors_loop_links(rows: list[dict[str, float]]) -> tuple[list[tuple[float, int, int]], int, int]:
    """Rebuild OpenRatSLAM's experience-map links from the driver's per-frame actions, as
    ``ExperienceMap`` makes them: CREATE_NODE links the previous experience to the new one
    (not for the very first experience); CREATE_EDGE links two existing experiences unless
    that (unordered) pair is linked already. Returns the loop links (CREATE_EDGE making a
    new link between two different experiences) as (t, src, dest), the number of links in
    all, and the number of self-links."""
    links: list[tuple[float, int, int]] = []
    pairs: set[tuple[int, int]] = set()
    self_links = 0
    for row in rows:
        e, src, action = int(row["exp_id"]), int(row["src_exp"]), int(row["action"])
        pair = (min(src, e), max(src, e))
        if action == ORS_CREATE_NODE and 0 <= src != e:
            pairs.add(pair)
        elif action == ORS_CREATE_EDGE and pair not in pairs:
            pairs.add(pair)
            if src == e:
                self_links += 1
            else:
                links.append((row["t"], src, e))
    return links, len(pairs), self_links


@dataclass
class ORSResult:
    threshold: float
    times: np.ndarray  # (n,) frame times
    poses: np.ndarray  # (n, 3) final experience-map pose of the experience active at each frame
    links: list[tuple[float, int, int]]  # (t, src, dest experience) of every loop link made
    exp_created: dict[int, float]  # experience id -> time it was created
    core_ms: dict[str, float]  # mean, median, first_third, last_third (driver's own figures)
    templates: int
    experiences: int
    wall_s: float
    #: the driver's link count vs the links rebuilt from its per-frame actions (a check)
    link_check: dict[str, int] | None = None


def _frame_times(data_dir: Path) -> np.ndarray:
    """The ``t`` column of a data folder's ``frames.csv`` (the images themselves are not needed)."""
    with open(Path(data_dir) / "frames.csv", newline="") as fh:
        return np.array([float(r["t"]) for r in csv.DictReader(fh)], dtype=float)


def per_frame_odometry(data_dir: Path) -> np.ndarray:
    """``(t, v, omega)`` per camera frame of a data folder: the mean velocities over each frame's interval.

    The OpenRatSLAM driver takes one odometry row per frame (row i driven from frame i-1 to frame i),
    as its ROS nodes see odometry at the camera's rate. A folder with frames at every odometry step
    already has that; one with fewer frames (``hippomap simulate --frame-every N``) has N readings per
    frame, and pairing them row by row would drive the peer along the first N-th of the route. So each
    frame gets the path and the turn of the readings since the previous frame (each reading's
    velocities hold from the reading before it to its own time), divided by the interval: what a robot
    publishing odometry at the frame rate would report. The first frame's velocities are 0 (the driver
    skips them). The readings are read by hippomap's own reader (:func:`read_folder_odometry`); the
    driver needs velocities, so a folder of pose increments is refused."""
    readings = read_folder_odometry(Path(data_dir) / "odometry.csv")
    if any(o.v is None for o in readings):
        raise ValueError(f"{data_dir}: the OpenRatSLAM driver needs odometry velocities (t,v,omega), not increments")
    odo = np.array([(o.t, o.v, o.omega) for o in readings], dtype=float).reshape(-1, 3)
    tf = _frame_times(data_dir)
    t = odo[:, 0]
    dt = np.diff(t, prepend=t[0])
    dist = np.cumsum(odo[:, 1] * dt)  # path and turn at each reading's time, linear in between
    turn = np.cumsum(odo[:, 2] * dt)
    d, a = np.interp(tf, t, dist), np.interp(tf, t, turn)
    span = np.diff(tf, prepend=tf[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(span > 0, np.diff(d, prepend=d[0]) / span, 0.0)
        w = np.where(span > 0, np.diff(a, prepend=a[0]) / span, 0.0)
    return np.column_stack([tf, v, w])


def ors_odometry_file(data_dir: Path, work: Path) -> Path:
    """The odometry CSV the driver gets: the folder's own when it has one reading per frame, else
    :func:`per_frame_odometry` written into ``work``."""
    own = Path(data_dir) / "odometry.csv"
    with open(own) as fh:
        n_odo = sum(1 for _ in fh) - 1
    with open(Path(data_dir) / "frames.csv") as fh:
        n_frames = sum(1 for _ in fh) - 1
    if n_odo == n_frames:
        return own
    out = work / "ors_odometry.csv"
    rows = per_frame_odometry(data_dir)
    with open(out, "w", newline="") as fh:
        fh.write("t,v,omega\n")
        for t, v, w in rows.tolist():
            fh.write(f"{t:.6f},{v!r},{w!r}\n")
    return out


def run_ors(
    exe: Path,
    peer_dir: Path,
    data_dir: Path,
    width: int,
    height: int,
    threshold: float | None,
    work: Path,
    odometry: Path | None = None,
) -> ORSResult:
    """Run the OpenRatSLAM driver on a data folder, with one odometry row per frame: ``odometry``, or
    :func:`ors_odometry_file` when None (a sweep of thresholds makes that file once and passes it)."""
    work.mkdir(parents=True, exist_ok=True)
    tag = "stock" if threshold is None else f"vt{threshold:g}"
    ini = work / f"ors_{tag}.ini"
    ini.write_text(ors_config_text(peer_dir, width, height, threshold))
    prefix = work / f"ors_{tag}"
    if odometry is None:
        odometry = ors_odometry_file(data_dir, work)
    t0 = time.perf_counter()
    r = subprocess.run(
        [str(exe), str(ini), str(data_dir), str(odometry), str(prefix)],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"OpenRatSLAM failed on {data_dir}: {r.stderr[-2000:]}")
    m = re.search(r"^ORS .*$", r.stdout, re.M)
    if not m:
        raise RuntimeError(f"OpenRatSLAM printed no summary line: {r.stdout[-500:]}")
    kv = dict(re.findall(r"(\w+)=([0-9.eE+-]+)", m.group(0)))
    rows = _read_ors_frames(Path(str(prefix) + "_frames.csv"))
    exps: dict[int, tuple[float, float, float]] = {}
    with open(str(prefix) + "_expmap.csv") as fh:
        for row in csv.DictReader(fh):
            exps[int(row["id"])] = (float(row["x_m"]), float(row["y_m"]), float(row["th_rad"]))
    times, poses, created = [], [], {}
    for row in rows:
        e = int(row["exp_id"])
        created.setdefault(e, row["t"])
        if e in exps:
            times.append(row["t"])
            poses.append(exps[e])
    links, n_pairs, self_links = ors_loop_links(rows)
    core = {
        "mean": float(kv["core_ms_per_frame"]),
        "median": float(kv["median_ms"]),
        "first_third": float(kv["first_third_ms"]),
        "last_third": float(kv["last_third_ms"]),
    }
    return ORSResult(
        threshold if threshold is not None else stock_threshold(peer_dir, width, height),
        np.array(times),
        np.array(poses).reshape(-1, 3),
        links,
        created,
        core,
        int(kv["templates"]),
        int(kv["experiences"]),
        wall,
        {"driver_links": int(kv["links"]), "counted_links": n_pairs, "self_links": self_links},
    )


# --------------------------------------------------------------------------------------
# GTSAM on g2o proposal files
# --------------------------------------------------------------------------------------

#: robust kernels applied to the loop-closure factors (odometry factors keep their Gaussian
#: noise). Parameters are in whitened units (sigmas of each edge's own g2o information):
#: GTSAM's customary defaults (Huber 1.345 = 95 % efficiency; Cauchy 1; DCS Phi 1).
KERNELS = {"none": None, "cauchy": 1.0, "dcs": 1.0, "huber": 1.345}
#: sqrt of the chi-square 99 % quantile with 3 degrees of freedom (11.345): the gate on a
#: closure's whitened residual for counting it as used by a robust solution
CHI2_GATE = 3.368


@dataclass
class GtsamResult:
    kernel: str
    poses: np.ndarray  # (n, 3) optimised poses, vertex order
    loops: list[dict[str, Any]]  # per loop factor: i, j, whitened residual, weight, used
    iterations: int
    seconds: float
    error_initial: float
    error_final: float


def _robust(kernel: str, base):
    import gtsam

    k = KERNELS[kernel]
    est = gtsam.noiseModel.mEstimator
    if kernel == "none":
        return None
    if kernel == "cauchy":
        return est.Cauchy.Create(k)
    if kernel == "dcs":
        return est.DCS.Create(k)
    if kernel == "huber":
        return est.Huber.Create(k)
    raise ValueError(kernel)


def run_gtsam(
    g2o_file: Path,
    kernel: str,
    max_iterations: int = 100,
    upto: int | None = None,
    keep: Callable[[int, int], bool] | None = None,
) -> GtsamResult:
    """Levenberg–Marquardt on the g2o graph (Pose2 between factors, noise from each edge's
    information matrix, a tight prior on pose 0), with ``kernel`` on the loop factors.
    Used closures: with no kernel every closure has weight 1 and is used. With a robust
    kernel a closure is used when the final solution agrees with it: its whitened residual
    r (Gaussian whitening by the edge's own information) is within the chi-square gate of
    3 degrees of freedom at 99 % (r <= 3.368), i.e. the map the optimiser settled on holds
    the closure rather than having down-weighted it away. Each closure's r and its final
    robust weight w(r) are kept as well (``weight``; ``w >= 0.5`` is a stricter reading).
    ``upto``: only the poses up to that index and the factors between them (the batch solution a
    back-end could have had online at that pose). ``keep``: only the loop factors (i, j) it accepts (with the
    ground truth: an oracle that applies the true closures alone)."""
    import gtsam

    graph, initial = gtsam.readG2o(str(g2o_file), False)
    if upto is not None:
        prefix = gtsam.Values()
        for key in initial.keys():
            if int(key) <= upto:
                prefix.insert(key, initial.atPose2(key))
        initial = prefix
    g = gtsam.NonlinearFactorGraph()
    loops_meta = []
    for k in range(graph.size()):
        f = graph.at(k)
        i, j = f.keys()
        if upto is not None and max(int(i), int(j)) > upto:
            continue
        if abs(int(i) - int(j)) == 1:
            g.add(f)
            continue
        if keep is not None and not keep(int(i), int(j)):
            continue
        est = _robust(kernel, f.noiseModel())
        model = f.noiseModel() if est is None else gtsam.noiseModel.Robust.Create(est, f.noiseModel())
        g.add(gtsam.BetweenFactorPose2(i, j, f.measured(), model))
        loops_meta.append((int(i), int(j), f, est))
    first = min(int(x) for x in initial.keys())
    g.add(gtsam.PriorFactorPose2(first, initial.atPose2(first), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(g, initial, params)
    result = opt.optimize()
    seconds = time.perf_counter() - t0
    keys = sorted(int(x) for x in initial.keys())
    poses = np.array([[p.x(), p.y(), p.theta()] for p in (result.atPose2(k) for k in keys)])
    loops = []
    for i, j, f, est in loops_meta:
        r = float(np.linalg.norm(f.whitenedError(result)))  # Gaussian whitening of the original factor
        w = 1.0 if est is None else float(est.weight(r))
        used = est is None or r <= CHI2_GATE
        loops.append({"i": i, "j": j, "residual": r, "weight": w, "used": bool(used), "weight_half": bool(w >= 0.5)})
    return GtsamResult(
        kernel, poses, loops, int(opt.iterations()), seconds, float(g.error(initial)), float(g.error(result))
    )


def make_workdir(root: Path, name: str) -> Path:
    """A fresh scratch folder under ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=name + "-", dir=root))


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
