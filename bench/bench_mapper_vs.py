"""Old vs new mapper on the same recorded run, in one process: speed ratios and proof of equal output.

The old code is a pristine copy of the package at a git revision (``--against``, default ``HEAD``)
extracted into a temporary directory under another package name, so both versions run in the same
process on the same decoded frames. Each version runs ``--repeats`` times, alternating, and every run
records

* every place code the spatial pathway returns (global code, heading, centroid, field indices,
  iterations, reset) and every recognition (``Recognition.to_dict()``: frame, evidence, saccade trace,
  correspondences), plus the final corrected trajectory;
* per frame: CPU ms (``time.process_time``: robust on a shared machine) of the odometry ``step`` and of the
  frame's ``observe`` (image decode excluded: frames are decoded once before timing), the ms of each
  ``VisualMemory.recognise`` call and of each spatial-pathway step, and the mean per-frame cost of the first
  and last third of the run.

It exits with status 1 unless every recorded output of the new code equals the old one exactly
(floats compared bit for bit, evidence to 1e-9 absolute). A change of the model that is meant to change
the outputs is measured with ``--expect-changes``: the differences are summarised, the map ATE of both
versions printed when the data set has ground truth, and the exit status is 0. ``--config FILE`` runs
the new code with those config overrides (the old code keeps its defaults). Both versions get the field of
view of the data set's camera where their config leaves it unset, as ``hippomap run`` and ``bench_maps.py`` give it
(``dataset_config``): without it a recognition's image shift gives no heading, and the runs would not be the
benchmark's.

    python -m hippomap simulate loop --out SIM --seed 3 --omega-bias 0.01 --sigma-omega 0.01 --sigma-v 0.02
    python bench/bench_mapper_vs.py SIM --against REV [--repeats 2] [--limit N] [--expect-changes] [--config FILE]
        [--interleave]

``--interleave`` runs the two versions side by side, event by event, instead of one whole run after the
other: a burst of load on a shared machine then falls on both alike.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import io
import math
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import hippomap  # noqa: E402
import hippomap.cli.run  # noqa: E402
import hippomap.config  # noqa: E402
import hippomap.inputs  # noqa: E402
import hippomap.mapper  # noqa: E402


def load_revision(rev: str) -> ModuleType:
    """Import the ``hippomap`` package as it is at git revision ``rev`` under a private name.

    The copy lives in a temporary directory that is removed when the process exits (not before: a module
    of the old package may still be imported on first use during the run)."""
    sha = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", rev], check=True, capture_output=True, text=True
    ).stdout.strip()
    blob = subprocess.run(["git", "-C", str(ROOT), "archive", sha, "hippomap"], check=True, capture_output=True).stdout
    tmp = Path(tempfile.mkdtemp(prefix="hippomap-rev-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(tmp, filter="data")
    name = f"hippomap_rev_{sha}"
    (tmp / "hippomap").rename(tmp / name)
    sys.path.insert(0, str(tmp))
    pkg = importlib.import_module(name)
    for sub in ("inputs", "mapper"):
        importlib.import_module(f"{name}.{sub}")
    pkg.revision = sha  # type: ignore[attr-defined]
    return pkg


def with_camera(pkg: ModuleType, config: Any, dataset: Any) -> Any:
    """``config`` (None: ``pkg``'s defaults) as ``pkg``'s own ``hippomap run`` would run ``dataset``: its
    ``cli.run.dataset_config``, which gives it the camera's field of view where the config leaves it unset; a
    revision without that function gets ``config`` unchanged."""
    try:
        dataset_config = importlib.import_module(f"{pkg.__name__}.cli.run").dataset_config
    except (ImportError, AttributeError):
        return config
    return dataset_config(dataset, config)


def code_record(c: Any) -> tuple:
    if c is None:
        return (None,)
    f = c.field
    return (
        c.x,
        c.y,
        c.theta,
        tuple(c.local),
        tuple(c.origin),
        c.iterations,
        c.reset,
        None if f is None else f.indices.tobytes(),
        None if f is None else tuple(f.cells),
    )


class _Run:
    """One mapper of ``pkg`` fed event by event (:meth:`feed`), timing its parts; :meth:`result` gives
    its outputs and timings."""

    def __init__(self, pkg: ModuleType, config: Any = None):
        self.m = m = pkg.mapper.Mapper(config)
        m.pathway.localise()  # shared grid-cell tables built outside the timing
        self.Odo, self.Frame = pkg.inputs.Odometry, pkg.inputs.Frame
        self.codes: list[tuple] = []
        self.spatial_ms: list[float] = []
        self.rec_ms: list[float] = []
        self.step_ms: list[float] = []
        self.obs_ms: list[float] = []
        self.pending = 0.0
        step_inc, recognise = m.pathway.step_increment, m.memory.recognise

        def timed_step(*a: Any) -> Any:
            t0 = time.process_time()
            c = step_inc(*a)
            self.spatial_ms.append((time.process_time() - t0) * 1e3)
            self.codes.append(code_record(c))
            return c

        def timed_recognise(*a: Any, **k: Any) -> Any:
            t0 = time.process_time()
            r = recognise(*a, **k)
            self.rec_ms.append((time.process_time() - t0) * 1e3)
            return r

        m.pathway.step_increment = timed_step
        m.memory.recognise = timed_recognise

    def feed(self, kind: str, t: float, payload: Any) -> None:
        m = self.m
        if kind == "odo":
            item = self.Odo(t, v=payload[0], omega=payload[1])
            t0 = time.process_time()
            m.step(item)
            self.pending += (time.process_time() - t0) * 1e3
        else:
            item = self.Frame(t, payload)
            t0 = time.process_time()
            m.observe(item)
            self.obs_ms.append((time.process_time() - t0) * 1e3)
            self.step_ms.append(self.pending)
            self.pending = 0.0

    def result(self) -> dict[str, Any]:
        m = self.m
        m.cmap.finish()  # a final solve for both versions alike (untimed; `hippomap run` writes the online map)
        return {
            "codes": self.codes,
            "recognitions": m.recognitions,
            "times": m.trajectory_times,
            "trajectory": m.corrected_trajectory(),
            "stats": m.stats(),
            "step_ms": np.array(self.step_ms),
            "obs_ms": np.array(self.obs_ms),
            "rec_ms": np.array(self.rec_ms),
            "spatial_ms": np.array(self.spatial_ms),
        }


def run_once(pkg: ModuleType, events: list[tuple[str, float, Any]], config: Any = None) -> dict[str, Any]:
    """Feed the events to a fresh ``pkg.mapper.Mapper`` (``config``: its config, default the package's
    defaults); return outputs and timings."""
    r = _Run(pkg, config)
    for e in events:
        r.feed(*e)
    return r.result()


def run_interleaved(
    versions: list[tuple[ModuleType, Any]], events: list[tuple[str, float, Any]]
) -> list[dict[str, Any]]:
    """:func:`run_once` of every ``(package, config)`` at once, in lockstep: each event goes to every
    mapper before the next event, the order turning each time, so that a burst of load on a shared
    machine falls on both versions alike (whole runs one after the other can catch it in one only).
    The two packages share no module state: each keeps its own caches."""
    runs = [_Run(pkg, cfg) for pkg, cfg in versions]
    for i, e in enumerate(events):
        k = i % len(runs)
        for r in runs[k:] + runs[:k]:
            r.feed(*e)
    return [r.result() for r in runs]


def _same(a: Any, b: Any, path: str, diffs: list[str]) -> None:
    if len(diffs) > 10:
        return
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            diffs.append(f"{path}: keys {sorted(a)} != {sorted(b)}")
            return
        for k in a:
            _same(a[k], b[k], f"{path}.{k}", diffs)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            diffs.append(f"{path}: length {len(a)} != {len(b)}")
            return
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]", diffs)
    elif isinstance(a, float) and isinstance(b, float):
        tol = 1e-9 if path.endswith("evidence") else 0.0
        if not (a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol):
            diffs.append(f"{path}: {a!r} != {b!r}")
    elif a != b:
        diffs.append(f"{path}: {a!r} != {b!r}")


def compare(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Differences between two runs' outputs (empty = identical)."""
    diffs: list[str] = []
    _same(old["codes"], new["codes"], "place_codes", diffs)
    _same(old["recognitions"], new["recognitions"], "recognitions", diffs)
    _same(old["stats"], new["stats"], "stats", diffs)
    a, b = old["trajectory"], new["trajectory"]
    if a.shape != b.shape:
        diffs.append(f"corrected trajectory: shape {a.shape} != {b.shape}")
    elif not np.array_equal(a, b):
        d = np.abs(a - b)
        d[:, 2] = np.abs(np.angle(np.exp(1j * (a[:, 2] - b[:, 2]))))  # headings: the wrapped difference
        diffs.append(
            f"corrected trajectory differs: largest change {float(d[:, :2].max()):.3g} m in position, "
            f"{float(d[:, 2].max()):.3g} rad in heading"
        )
    return diffs


def figures(r: dict[str, Any]) -> dict[str, float]:
    per = r["step_ms"] + r["obs_ms"]
    n3 = len(per) // 3
    rec = r["rec_ms"] if r["rec_ms"].size else np.zeros(1)
    return {
        "frame": per.mean(),
        "step": r["step_ms"].mean(),
        "observe": r["obs_ms"].mean(),
        "spatial": r["spatial_ms"].mean(),
        "rec_p50": float(np.median(rec)),
        "rec_p95": float(np.percentile(rec, 95)),
        "rec_mean": rec.mean(),
        "first3": per[:n3].mean(),
        "last3": per[-n3:].mean(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="hippomap data folder (e.g. from `hippomap simulate`)")
    ap.add_argument("--against", default="HEAD", help="git revision of the old code (default HEAD)")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each version, alternating")
    ap.add_argument("--limit", type=int, default=0, help="use only the first N frames (0 = all)")
    ap.add_argument(
        "--expect-changes",
        action="store_true",
        help="a model change: report the differences and both map ATEs instead of failing on them",
    )
    ap.add_argument("--config", help="JSON config overrides for the new code (the old code keeps its defaults)")
    ap.add_argument(
        "--interleave",
        action="store_true",
        help="run old and new side by side, event by event (steadier ratios on a loaded machine)",
    )
    args = ap.parse_args()
    new_config = hippomap.config.HippomapConfig.from_file(args.config) if args.config else None
    old_pkg = load_revision(args.against)
    ds = hippomap.cli.run.open_dataset(args.data)
    old_config = with_camera(old_pkg, None, ds)
    new_config = with_camera(hippomap, new_config, ds)
    events: list[tuple[str, float, Any]] = []
    n_frames = 0
    for it in ds.events():
        if isinstance(it, hippomap.inputs.Odometry):
            if it.increment is not None:
                raise SystemExit("this benchmark replays velocity odometry only")
            events.append(("odo", it.t, (it.v, it.omega)))
        else:
            if args.limit and n_frames >= args.limit:
                break
            events.append(("frame", it.t, it.load().image))
            n_frames += 1
    print(f"{args.data}: {n_frames} frames; old = revision {old_pkg.revision}, new = working tree")
    runs: dict[str, list[dict[str, Any]]] = {"old": [], "new": []}
    for _ in range(args.repeats):
        if args.interleave:
            o, n = run_interleaved([(old_pkg, old_config), (hippomap, new_config)], events)
            runs["old"].append(o)
            runs["new"].append(n)
            continue
        for label, pkg, cfg in (("old", old_pkg, old_config), ("new", hippomap, new_config)):
            runs[label].append(run_once(pkg, events, cfg))
    diffs = []
    for o in runs["old"]:
        for n in runs["new"]:
            diffs += compare(o, n)
    s = runs["new"][0]["stats"]
    print(
        f"{s['keyframes']} key frames, {len(runs['new'][0]['recognitions'])} recognitions, "
        f"{s['loop_closures_accepted']} loop closures accepted, {len(runs['new'][0]['codes'])} place codes"
    )
    rows = [
        ("mapper per frame (step + observe), mean", "frame"),
        ("  odometry step, mean", "step"),
        ("    of which spatial pathway, mean per step", "spatial"),
        ("  frame observe, mean", "observe"),
        ("recognition mean", "rec_mean"),
        ("recognition p50", "rec_p50"),
        ("recognition p95", "rec_p95"),
        ("first third, mean per frame", "first3"),
        ("last third, mean per frame", "last3"),
    ]
    fo = [figures(r) for r in runs["old"]]
    fn = [figures(r) for r in runs["new"]]
    print(f"{'ms':46s} {'old':>8s} {'new':>8s} {'new/old':>8s}   (best of {args.repeats} runs each)")
    for text, key in rows:
        o = min(f[key] for f in fo)
        n = min(f[key] for f in fn)
        print(f"{text:46s} {o:8.3f} {n:8.3f} {n / o:8.2f}")
    for label, fs in (("old", fo), ("new", fn)):
        best = min(fs, key=lambda f: f["frame"])
        print(f"{label}: last third / first third = {best['last3'] / best['first3']:.2f}")
    if ds.groundtruth is not None:
        from hippomap.eval.evaluation import trajectory_metrics

        for label in ("old", "new"):
            r = runs[label][0]
            ate = trajectory_metrics(r["times"], r["trajectory"], *ds.groundtruth)["ate"]["rmse"]
            closures = r["stats"]["loop_closures_accepted"]
            print(f"{label}: map ATE rmse {ate:.3f} m, {closures} loop closures accepted")
    if diffs:
        print("OUTPUTS DIFFER" + (" (expected: a model change):" if args.expect_changes else ":"))
        for d in diffs[:10]:
            print("  ", d)
        return 0 if args.expect_changes else 1
    print("outputs identical: every place code, every recognition (trace, evidence), stats, corrected trajectory")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
