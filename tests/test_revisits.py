"""Revisit episodes of a ground truth and the loop-closure recall by place (hippomap/eval/revisits.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.errors import InputError
from hippomap.eval.revisits import describe_missed, explain_missed, revisit_episodes, revisit_recall


def _circle(laps: float, circumference: float = 40.0, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A robot driving ``laps`` times round a circle at 1 m/s: times, poses (x, y, heading)."""
    s = np.arange(0.0, laps * circumference, step)
    r = circumference / (2 * math.pi)
    a = s / r
    return s.copy(), np.column_stack((r * np.sin(a), r - r * np.cos(a), a))


def _out_and_back(length: float = 20.0, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Out along x and back, facing the way it drives (heading 0, then pi)."""
    out, back = np.arange(0.0, length, step), np.arange(length, -step / 2, -step)
    x = np.concatenate((out, back))
    heading = np.concatenate((np.zeros_like(out), np.full_like(back, math.pi)))
    return np.arange(len(x)) * step, np.column_stack((x, np.zeros_like(x), heading))


def test_a_road_that_never_comes_back_has_no_revisit():
    t = np.arange(500) * 0.1
    assert revisit_episodes(t, np.column_stack((t, np.zeros_like(t)))) == []
    assert revisit_recall([], t, np.column_stack((t, np.zeros_like(t))), [1.0])["recall"] is None


def test_the_second_lap_of_a_loop_is_one_episode():
    """Round a 40 m circle twice: the second lap revisits the first from where the robot comes within
    1.5 m of where it was 30 m or more before (38.5 m of path) to the end: one episode."""
    t, p = _circle(2.0)
    (e,) = revisit_episodes(t, p)
    assert e.path_m == pytest.approx(38.5, abs=0.3)
    assert e.path_m + e.length_m == pytest.approx(79.9, abs=0.3)
    assert e.t0 == pytest.approx(e.path_m, abs=0.3) and e.earlier_t < 1.0  # 1 m/s; revisits the start


def test_an_out_and_back_run_revisits_only_where_the_ways_are_30_m_apart():
    """Out 20 m and back, the headings not compared: a point x metres from the start is passed again
    40 - 2x metres of path later, so only the last ~5.75 m (x <= 5 plus the 1.5 m radius) are a revisit."""
    t, p = _out_and_back()
    (e,) = revisit_episodes(t, p, max_heading_rad=None)
    assert e.length_m == pytest.approx(5.75, abs=0.3)
    assert e.path_m + e.length_m == pytest.approx(40.0, abs=0.3)
    assert revisit_episodes(t, p[:, :2]) == [e]  # no headings to compare
    assert revisit_episodes(t, p, min_path_m=45.0, max_heading_rad=None) == []  # nothing 45 m apart


def test_driving_back_the_other_way_is_no_revisit_for_a_forward_camera():
    """On the way back the robot faces the other way: it sees the other side of everything, so by
    default that stretch is not an episode a camera could close."""
    t, p = _out_and_back()
    assert revisit_episodes(t, p) == []
    assert len(revisit_episodes(t, p, max_heading_rad=math.pi)) == 1


def _polyline(corners: list[tuple[float, float]], step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Straight legs through ``corners`` at 1 m/s, facing the way each leg goes: times, poses."""
    pts, heads = [], []
    for (x0, y0), (x1, y1) in zip(corners[:-1], corners[1:]):
        n = int(round(math.hypot(x1 - x0, y1 - y0) / step))
        f = np.arange(n) / n
        pts.append(np.column_stack((x0 + f * (x1 - x0), y0 + f * (y1 - y0))))
        heads.append(np.full(n, math.atan2(y1 - y0, x1 - x0)))
    p = np.column_stack((np.concatenate(pts), np.concatenate(heads)))
    return np.arange(len(p)) * step, p


def test_an_episode_says_how_far_the_robot_faced_from_its_earlier_pass():
    """A second lap faces the way the first did; a later leg that crosses the first at 60 degrees is an
    episode too (within the 90-degree limit), and says it came at 60 degrees: a graze of a crossing."""
    (lap,) = revisit_episodes(*_circle(2.0))
    assert lap.heading_deg is not None and lap.heading_deg < 2.0
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)
    t, p = _polyline([(0, 0), (40, 0), (40, -12 * s), (20 - 12 * c, -12 * s), (20 + 12 * c, 12 * s)])
    (cross,) = revisit_episodes(t, p)
    assert cross.heading_deg == pytest.approx(60.0, abs=0.5)
    assert cross.length_m == pytest.approx(2 * 1.5 / s, abs=0.5)  # within 1.5 m of the first leg
    assert revisit_episodes(t, p, max_heading_rad=math.radians(50)) == []
    assert revisit_episodes(t, p, max_heading_rad=None)[0].heading_deg is None  # headings not compared
    assert revisit_recall([cross], t, p, [])["missed"][0]["heading_deg"] == cross.heading_deg


def test_episodes_shorter_than_the_minimum_are_grazes():
    t, p = _out_and_back()
    assert revisit_episodes(t, p, min_length_m=6.0, max_heading_rad=None) == []


def test_an_episode_is_closed_by_a_closure_on_its_stretch_of_path():
    t, p = _circle(3.0)  # laps 2 and 3 are one episode from 38.5 m of path on
    eps = revisit_episodes(t, p)
    assert len(eps) == 1
    assert revisit_recall(eps, t, p, [60.0])["closed"] == 1
    assert revisit_recall(eps, t, p, [37.0])["closed"] == 1  # within join_m (2 m) before it
    missed = revisit_recall(eps, t, p, [10.0, 35.0])
    assert missed["closed"] == 0 and missed["recall"] == 0.0 and missed["missed"][0]["path_m"] == eps[0].path_m
    assert revisit_recall(eps, t, p, [])["closed"] == 0


def test_a_missed_episode_says_what_the_mapper_did_along_it():
    """Only the recognitions and loop decisions made between the episode's t0 and t1 count: how many
    recognitions ran and among how many key frames, how many named the right place (within 2 m in ground
    truth) or a wrong one, and whether the true links the map accepted are used or faded."""
    missed = [{"t0": 10.0, "t1": 20.0}, {"t0": 50.0, "t1": 60.0}]

    def rec(t, search, n, d):
        return {"t": t, "search": search, "candidates": n, "groundtruth_distance_m": d}

    def row(t, status, d, used, along=None, beside=0.0, heading=0.0):
        r = {"hypothesis": {"time": t}, "status": status, "groundtruth_distance_m": d, "used": used}
        if along is not None:  # hippomap run's link_error_* of an accepted link
            r |= {"link_error_m": math.hypot(along, beside), "link_error_along_m": along}
            r |= {"link_error_beside_m": beside, "link_error_rad": abs(heading)}
        return r

    recs = [rec(5.0, "gated", 9, 0.1), rec(11.0, "gated", 300, 0.5), rec(12.0, "global", 900, None)]
    recs += [rec(13.0, "gated", 310, 1.9), rec(15.0, "gated", 320, 6.0), rec(25.0, "gated", 5, 0.2)]
    loops = [row(5.0, "accepted", 0.1, True, 0.1), row(11.0, "accepted", 0.5, False, 0.6, -0.8, -0.2)]
    loops += [row(13.0, "accepted", 1.9, True, 0.05), row(15.0, "accepted", 6.0, False, 3.0)]
    loops += [row(16.0, "rejected", 0.3, False)]
    explain_missed(missed, recs, loops)
    assert missed[0]["why"] == {
        "recognitions": 4,
        "global_searches": 1,
        "candidates_median": 315.0,  # of 300, 900, 310 and 320
        "named_true": 2,
        "named_false": 1,
        "true_links_used": 1,
        "true_links_faded": 1,
        # the one true link faded (the false one at 6 m and the used one do not count), absolute parts
        "faded_link_error": pytest.approx({"m": 1.0, "along_m": 0.6, "beside_m": 0.8, "heading_rad": 0.2}),
    }
    assert missed[1]["why"]["recognitions"] == 0 and missed[1]["why"]["candidates_median"] is None
    assert missed[1]["why"]["faded_link_error"] is None  # no faded link there


def test_a_missed_episode_gives_the_median_error_of_its_faded_links_and_none_without_ground_truth():
    """Three true links faded along one episode: each part of their error is the median of its absolute
    values; a faded link without a ground-truth error (its times outside the ground truth) is left out, and
    an episode whose faded links have none says None."""
    missed = [{"t0": 0.0, "t1": 10.0}, {"t0": 20.0, "t1": 30.0}]
    loops = []
    for t, along, beside in ((1.0, 1.5, -0.2), (2.0, -0.4, 0.9), (3.0, 0.7, -1.1)):
        loops.append(
            {
                "hypothesis": {"time": t},
                "status": "accepted",
                "groundtruth_distance_m": 1.0,
                "used": False,
                "link_error_m": math.hypot(along, beside),
                "link_error_along_m": along,
                "link_error_beside_m": beside,
                "link_error_rad": 0.1 * t,
            }
        )
    loops.append({"hypothesis": {"time": 4.0}, "status": "accepted", "groundtruth_distance_m": 1.0, "used": False})
    loops.append({"hypothesis": {"time": 21.0}, "status": "accepted", "groundtruth_distance_m": 1.0, "used": False})
    explain_missed(missed, [], loops)
    why = missed[0]["why"]
    assert why["true_links_faded"] == 4
    assert why["faded_link_error"] == pytest.approx(
        {"m": math.hypot(0.7, 1.1), "along_m": 0.7, "beside_m": 0.9, "heading_rad": 0.2}
    )
    assert missed[1]["why"]["true_links_faded"] == 1 and missed[1]["why"]["faded_link_error"] is None


def test_two_separate_revisits_are_counted_apart():
    """Twice round one circle, 100 m straight on, twice round another: two episodes, each closed only by
    a closure made along it."""
    t1, p1 = _circle(2.0)
    line = np.column_stack((np.arange(0.1, 100.0, 0.1), np.zeros(999), np.zeros(999)))
    p = np.vstack((p1, line, p1 + np.array([100.0, 0.0, 0.0])))
    t = np.arange(len(p)) * 0.1
    eps = revisit_episodes(t, p)
    assert len(eps) == 2
    assert eps[0].t0 < 40.0 < 180.0 < eps[1].t0  # one per circle
    r = revisit_recall(eps, t, p, [eps[1].t0 + 5.0])
    assert r["closed"] == 1 and r["recall"] == 0.5 and r["missed"][0]["t0"] == eps[0].t0


@settings(max_examples=30, deadline=None)
@given(
    x=st.floats(-100, 100),
    y=st.floats(-100, 100),
    angle=st.floats(-math.pi, math.pi),
    t0=st.floats(0, 1e9),
)
def test_episodes_do_not_depend_on_where_the_run_lies_or_when_it_starts(x, y, angle, t0):
    t, p = _circle(2.2, circumference=33.0)
    c, s = math.cos(angle), math.sin(angle)
    moved = np.column_stack((x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]))
    a, b = revisit_episodes(t, p), revisit_episodes(t + t0, moved)
    assert len(a) == len(b) == 1
    assert b[0].path_m == pytest.approx(a[0].path_m, abs=1e-6)
    assert b[0].length_m == pytest.approx(a[0].length_m, abs=1e-6)
    assert b[0].t0 - t0 == pytest.approx(a[0].t0, abs=1e-3)


def test_the_ground_truths_rate_does_not_change_the_episodes():
    a = revisit_episodes(*_circle(2.0, step=0.02))
    b = revisit_episodes(*_circle(2.0, step=0.2))
    assert len(a) == len(b) == 1
    assert abs(a[0].path_m - b[0].path_m) < 0.5 and abs(a[0].length_m - b[0].length_m) < 0.5


@pytest.mark.parametrize(
    ("times", "poses", "match"),
    [
        (np.arange(3.0), np.zeros((4, 3)), "N times and N poses"),
        (np.array([0.0, 2.0, 1.0]), np.zeros((3, 3)), "sorted"),
        (np.arange(3.0), np.array([[0.0, 0.0], [np.nan, 0.0], [1.0, 0.0]]), "finite"),
        (np.arange(3.0), np.zeros(3), "N times and N poses"),
    ],
)
def test_bad_input_is_named(times, poses, match):
    with pytest.raises(InputError, match=match):
        revisit_episodes(times, poses)


def test_a_missed_episode_is_described_with_whatever_its_entry_holds():
    """Length at path always; the heading from the earlier pass when measured; the faded true links and their
    median error (position: along / beside the view) only when some faded and their errors are known."""
    e = {"length_m": 14.2, "path_m": 564.8}
    assert describe_missed(e) == "14 m at 565 m"
    e["heading_deg"] = 0.4
    assert describe_missed(e) == "14 m at 565 m (0°)"
    err = {"m": 1.304, "along_m": 0.677, "beside_m": 0.994, "heading_rad": 0.18}
    e["why"] = {"true_links_faded": 4, "faded_link_error": err}
    assert describe_missed(e) == "14 m at 565 m (0°) [4 true faded, 1.30 m off: 0.68 / 0.99 m]"
    for why in ({"true_links_faded": 0, "faded_link_error": None}, {"true_links_faded": 2}):
        assert describe_missed({**e, "why": why}) == "14 m at 565 m (0°)"
