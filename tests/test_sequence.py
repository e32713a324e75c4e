"""The old path's sequence (``mapper.sequence_window_m``, off by default: docs/MODEL.md item 114): after a recognition
the map took, the next key frame is searched first among the key frames learned near the one it named, then among
the rest of the gate's."""

from __future__ import annotations

import numpy as np
import pytest

from hippomap import sim
from hippomap.config import HippomapConfig
from hippomap.inputs import Frame, Odometry
from hippomap.map_events import LoopDecided
from hippomap.mapper import Mapper


def test_the_sequence_is_the_candidates_learned_near_the_named_frame_s_path():
    m = Mapper(HippomapConfig.with_overrides({"mapper": {"sequence_window_m": 3.0}}))
    m.frame_path = {f: 0.5 * f for f in range(30)}
    frames = list(range(0, 30, 2))
    assert m._sequence(frames) == []  # no recognition taken yet
    m.sequence_frame = 10  # learned at 5.0 m: the window is 2.0 - 8.0 m
    assert m._sequence(frames) == [4, 6, 8, 10, 12, 14, 16]
    assert m._sequence([]) == []
    m.sequence_frame = 99  # a frame with no path (none learned): no sequence
    assert m._sequence(frames) == []
    m.sequence_frame = 10
    restored = Mapper.from_bytes(m.to_bytes())
    assert restored.sequence_frame == 10 and restored._sequence(frames) == m._sequence(frames)
    off = Mapper(HippomapConfig.with_overrides({"mapper": {"sequence_window_m": None}}))
    off.frame_path, off.sequence_frame = m.frame_path, 10
    assert off._sequence(frames) == []  # the option off
    assert HippomapConfig().mapper.sequence_window_m is None  # off by default (docs/MODEL.md item 114)
    with pytest.raises(ValueError, match="sequence_window_m"):
        HippomapConfig.with_overrides({"mapper": {"sequence_window_m": 0.0}})


def _two_laps(
    window: float | None, prior: float | None = None
) -> tuple[Mapper, list[list[dict]], set[int], np.ndarray]:
    """Two laps of a small loop world (noisy odometry, 5 Hz) mapped with ``sequence_window_m`` = ``window`` and
    ``sequence_prior`` = ``prior``, restored from a snapshot half way: the mapper, its recognitions grouped by key
    frame, the ids of those the map took (did not reject when they were made), and the run's ground truth."""
    world = sim.loop_world(seed=3, size=(8.0, 5.0), laps=2)
    noise = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
    run = sim.simulate(world, None, rate_hz=5.0, seed=1, odometry_noise=noise)
    m = Mapper(HippomapConfig.with_overrides({"mapper": {"sequence_window_m": window, "sequence_prior": prior}}))
    taken: set[int] = set()
    for i in range(len(run)):
        t, v, w = run.odometry[i]
        m.step(Odometry(float(t), v=float(v), omega=float(w)))
        for e in m.observe(Frame(float(t), run.frame(i))):
            if isinstance(e, LoopDecided) and e.decision.status != "rejected":
                taken.add(int(e.decision.hypothesis.meta["recognition"]))
        if i == len(run) // 2:
            m = Mapper.from_bytes(m.to_bytes())  # the sequence survives a snapshot
    groups: dict[float, list[dict]] = {}
    for r in m.recognitions:
        groups.setdefault(r["t"], []).append(r)
    return m, list(groups.values()), taken, run.groundtruth


def test_after_a_taken_recognition_the_next_key_frame_searches_the_old_path_s_sequence_first():
    """A sequence search runs only at a key frame after one whose recognition the map took, among fewer key frames
    than the gate holds, and names a frame learned within the window of the one named before; one that names
    nothing, or that the map rejects, is followed at the same key frame by a search among the gate's other key
    frames. With the option off no sequence search runs; both maps close the loop."""
    window = 3.0
    m, groups, taken, gt = _two_laps(window)
    searches = fallbacks = 0
    for before, group in zip(groups, groups[1:]):
        first = group[0]
        if first["search"] != "sequence":
            continue
        searches += 1
        last = before[-1]  # the recognition the key frame before ended with
        assert last["id"] in taken and last["frame_id"] is not None
        if first["frame_id"] is not None:
            assert abs(m.frame_path[first["frame_id"]] - m.frame_path[last["frame_id"]]) <= window
        if first["id"] in taken:
            assert len(group) == 1
        else:
            assert len(group) >= 2 and group[1]["search"] in ("gated", "global")
            fallbacks += group[1]["search"] == "gated"  # the gate held more key frames than the sequence
    assert searches >= 10 and fallbacks >= 1
    off, off_groups, _, _ = _two_laps(None)
    assert not any(r["search"] == "sequence" for g in off_groups for r in g)
    drift = _end_error(m.odometry_trajectory(), gt)
    assert drift > 0.5
    for mapper in (m, off):  # the loop closed: the end of the second lap lies on the first as in the world
        assert _end_error(mapper.corrected_trajectory(), gt) < 0.3 * drift


def _end_error(est: np.ndarray, gt: np.ndarray) -> float:
    """The largest position error over the last 20 poses of ``est``, both trajectories put in the frame of their
    first pose (where the run starts, the map and the world agree)."""

    def local(p: np.ndarray) -> np.ndarray:
        c, s = np.cos(p[0, 2]), np.sin(p[0, 2])
        d = p[:, :2] - p[0, :2]
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])

    return float(np.hypot(*(local(est) - local(gt))[-20:].T).max())


def test_the_head_start_is_off_by_default_and_checked_against_the_decision_threshold():
    assert HippomapConfig().mapper.sequence_prior is None  # measured, not kept (docs/MODEL.md item 115)
    for bad in (-0.1, 0.9, 1.2):
        with pytest.raises(ValueError, match="sequence_prior"):
            HippomapConfig.with_overrides({"mapper": {"sequence_prior": bad}})
    lower = {"mapper": {"sequence_prior": 0.5}, "visual": {"decision_threshold": 0.5}}
    with pytest.raises(ValueError, match="below visual.decision_threshold"):
        HippomapConfig.with_overrides(lower)
    assert HippomapConfig.with_overrides({"mapper": {"sequence_prior": 0.5}}).mapper.sequence_prior == 0.5


def test_a_primed_sequence_is_one_search_among_every_candidate():
    """With ``sequence_prior`` (docs/MODEL.md item 115) the old path's sequence is primed, not searched first: each
    key frame has one gated search among all the gate's candidates (a global one may follow), the sequence primed
    only after a recognition the map took, never more key frames than the search holds; the loop closes."""
    m, groups, taken, gt = _two_laps(3.0, prior=0.2)
    primed = 0
    for before, group in zip(groups, groups[1:]):
        assert [r["search"] for r in group][:1] in (["gated"], ["global"]) and len(group) <= 2
        first = group[0]
        if "primed" in first:
            primed += 1
            assert before[-1]["id"] in taken and 1 <= first["primed"] <= first["candidates"]
    assert primed >= 10
    drift = _end_error(m.odometry_trajectory(), gt)
    assert drift > 0.5 and _end_error(m.corrected_trajectory(), gt) < 0.3 * drift
