"""The comparison benchmark's own logic (no peer is built or run here): parsing the
OpenRatSLAM driver's output, its config for other image sizes, the loop-closure and
loop-link scoring against ground truth, and the per-frame timing of the mapper."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import bench_maps  # noqa: E402
import peers  # noqa: E402
from hippomap.inputs import Frame, Odometry  # noqa: E402

STOCK_INI = """[general]
topic_root=stlucia

[ratslam]
image_crop_x_min=40
image_crop_x_max=600
image_crop_y_min=150
image_crop_y_max=300
vt_match_threshold = 0.085
template_x_size=60
"""


def _fake_peer(tmp_path: Path) -> Path:
    d = tmp_path / "ors"
    (d / "configs").mkdir(parents=True)
    (d / "configs" / "stlucia_640x480.ini").write_text(STOCK_INI)
    return d


def test_ors_config_scales_crop_and_sets_threshold(tmp_path):
    peer = _fake_peer(tmp_path)
    text = peers.ors_config_text(peer, 1280, 960, 0.03)
    assert "image_crop_x_min=80" in text and "image_crop_x_max=1200" in text
    assert "image_crop_y_min=300" in text and "image_crop_y_max=600" in text
    assert "vt_match_threshold = 0.03" in text and "0.085" not in text
    same = peers.ors_config_text(peer, 640, 480, None)
    assert same == STOCK_INI
    assert peers.stock_threshold(peer, 640, 480) == pytest.approx(0.085)


def _row(i, t, exp, action=0, src=-1, us=1000.0):
    return f"{i},{t:.3f},0,0.010000,1,{action},{src},{exp},{exp + 1},{us:.1f}\n"


def test_ors_frames_parser_recovers_the_truncated_first_row(tmp_path):
    # the driver prints vt_err = DBL_MAX with %.6f into a 256-byte buffer: row 0 is cut
    # and its newline lost, so row 1 is glued to it
    row0 = ("0,0.000,0,%.6f,0,0,-1,0,1,3398.7\n" % sys.float_info.max)[:255]
    p = tmp_path / "run_frames.csv"
    p.write_text(
        "frame,t,vt_id,vt_err,n_vt,action,src_exp,exp_id,n_exp,core_us\n"
        + row0
        + _row(1, 0.2, 0, us=1234.5)
        + _row(2, 0.4, 1, action=1, src=0)
        + _row(3, 0.6, 0, action=2, src=1)
    )
    rows = peers._read_ors_frames(p)
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3]
    assert rows[1]["t"] == pytest.approx(0.2) and rows[1]["core_us"] == pytest.approx(1234.5)
    assert [int(r["exp_id"]) for r in rows] == [0, 0, 1, 0]
    assert int(rows[3]["action"]) == peers.ORS_CREATE_EDGE


def _gt_circle(n=200, r=5.0):
    t = np.arange(n) * 0.2
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses = np.column_stack([r * np.cos(a), r * np.sin(a), a + np.pi / 2])
    return t, poses


def test_link_errors_measure_loop_links_against_ground_truth(tmp_path):
    t, gt = _gt_circle()
    idx = [0, 50, 100, 150, 199]
    nodes = [{"id": k, "pose": gt[i].tolist(), "t": float(t[i])} for k, i in enumerate(idx)]

    def rel(a, b):
        from hippomap.geometry import between

        return between(gt[idx[a]], gt[idx[b]])

    links = [{"source": k, "target": k + 1, "transform": rel(k, k + 1).tolist(), "kind": "odometry"} for k in range(4)]
    bad = rel(4, 0) + np.array([0.3, 0.4, 0.0])  # 0.5 m off
    links.append({"source": 4, "target": 0, "transform": bad.tolist(), "kind": "loop"})
    links.append({"source": 3, "target": 1, "transform": rel(3, 1).tolist(), "kind": "prune"})
    p = tmp_path / "map.json"
    p.write_text(json.dumps({"nodes": nodes, "links": links}))
    e = bench_maps.link_errors(p, (t, gt))
    assert e["odometry"]["n"] == 4 and e["odometry"]["max_m"] < 1e-9
    assert e["loop"]["n"] == 1 and e["loop"]["mean_m"] == pytest.approx(0.5)
    assert e["prune"]["n"] == 1 and e["prune"]["max_m"] < 1e-9


def test_ors_scoring_counts_false_links_by_ground_truth_separation():
    t, gt = _gt_circle()
    # experiences: 0 created at t=0 (angle 0), 1 at the opposite side of the circle
    created = {0: 0.0, 1: float(t[100])}
    links = [
        (float(t[199]), 1, 0),  # back at the start, linked to experience 0: true (~0.16 m)
        (float(t[10]), 0, 1),
    ]  # near the start, linked to the far experience: false (~10 m)
    res = peers.ORSResult(
        0.03,
        t,
        gt + np.array([0.05, 0.0, 0.0]),
        links,
        created,
        {"mean": 1.0, "median": 1.0, "first_third": 1.0, "last_third": 1.0},
        3,
        2,
        0.1,
    )
    s = bench_maps.score_ors(res, (t, gt))
    assert s["closures_accepted"] == 2 and s["closures_false"] == 1
    assert s["ate"] == pytest.approx(0.0, abs=1e-6)  # a constant offset is aligned away


def test_ors_revisits_are_closed_only_by_its_true_links():
    """Twice round a 31 m circle: the second lap is one revisit episode. OpenRatSLAM's link made on it to
    the experience of the same place closes it; a false link made there (to the far side) does not."""
    n = 400
    t = np.arange(n) * 0.2
    a = np.linspace(0, 4 * np.pi, n, endpoint=False)
    gt = np.column_stack([5.0 * np.cos(a), 5.0 * np.sin(a), a + np.pi / 2])
    created = {0: float(t[10]), 1: float(t[100])}  # experience 1 is on the far side of the circle
    ms = {"mean": 1.0, "median": 1.0, "first_third": 1.0, "last_third": 1.0}

    def score(links):
        return bench_maps.score_ors(peers.ORSResult(0.03, t, gt, links, created, ms, 3, 2, 0.1), (t, gt))["revisits"]

    true = score([(float(t[210]), 5, 0)])
    assert true["episodes"] == 1 and true["closed"] == 1 and true["recall"] == 1.0 and true["missed"] == []
    false = score([(float(t[210]), 5, 1)])
    assert false["closed"] == 0 and len(false["missed"]) == 1


def test_revisit_lines_total_the_runs_and_name_the_episodes_missed():
    def row(seed, hm_closed, ors_closed, n=2, heading=None):
        missed = [{"length_m": 11.0, "path_m": 406.0, "heading_deg": heading}] * (n - hm_closed)
        return {
            "world": "bicocca",
            "seed": seed,
            "size": "640x480",
            "texture": "procedural",
            "hippomap": {"revisits": {"episodes": n, "closed": hm_closed, "missed": missed}},
            "ors": {"best": {"revisits": {"episodes": n, "closed": ors_closed, "missed": []}}},
        }

    lines = bench_maps.revisit_lines([row(3, 1, 0), row(4, 2, 1)])
    assert "hippomap 3 of 4; ORS best 1 of 4 (2 runs)" in lines[0]
    label = (
        "- hippomap missed (episode length at path, the heading from the earlier pass, and the true links it faded "
        "there with their median error: position, along / beside the key frame's view): "
    )
    assert lines[1] == label + "bicocca 3 640x480 procedural 11 m at 406 m"  # no heading: rows from before it
    lines = bench_maps.revisit_lines([row(3, 1, 0, heading=84.6)])
    assert lines[1] == label + "bicocca 3 640x480 procedural 11 m at 406 m (85°)"
    # the true links faded there, with the median of their errors (explain_missed's why)
    faded = row(3, 1, 0, heading=0.4)
    err = {"m": 1.304, "along_m": 0.677, "beside_m": 0.994, "heading_rad": 0.18}
    faded["hippomap"]["revisits"]["missed"] = [
        {**faded["hippomap"]["revisits"]["missed"][0], "why": {"true_links_faded": 4, "faded_link_error": err}}
    ]
    lines = bench_maps.revisit_lines([faded])
    assert (
        lines[1] == label + "bicocca 3 640x480 procedural 11 m at 406 m (0°) [4 true faded, 1.30 m off: 0.68 / 0.99 m]"
    )
    # none faded, or a row from before the errors were measured: nothing added
    for why in ({"true_links_faded": 0, "faded_link_error": None}, {"true_links_faded": 2}):
        faded["hippomap"]["revisits"]["missed"][0]["why"] = why
        assert bench_maps.revisit_lines([faded])[1] == label + "bicocca 3 640x480 procedural 11 m at 406 m (0°)"
    assert bench_maps.revisit_lines([{**row(3, 1, 0), "hippomap": {}}]) == []  # rows from before it was measured


def test_recognition_lines_count_the_runs_meeting_the_p95_target():
    def row(p95_ms, cpu_p95_ms, n=40):
        return {
            "hippomap": {
                "recognition_ms": {"n": n, "mean": p95_ms / 2, "p95": p95_ms},
                "recognition_cpu_ms": {"n": n, "mean": cpu_p95_ms / 2, "p95": cpu_p95_ms},
            }
        }

    lines = bench_maps.recognition_lines([row(12.0, 11.0), row(18.0, 14.0), row(0.0, 0.0, n=0), {"hippomap": {}}])
    # runs without recognitions (or measured before the field) are left out of the count
    assert lines[0] == (
        "- hippomap recognition p95 (wall clock): median 15.0 ms, max 18.0 ms; runs meeting <= 15 ms: 1/2"
    )
    assert lines[1] == "- hippomap recognition p95 (CPU): median 12.5 ms, max 14.0 ms; runs meeting <= 15 ms: 2/2"
    assert bench_maps.recognition_summary([]) == {"n": 0, "mean": None, "p95": None}
    assert bench_maps.recognition_summary([0.001, 0.003])["mean"] == pytest.approx(2.0)


def test_growth_lines_put_the_peer_s_own_third_ratios_beside_the_target():
    def thirds(first, last):
        return {"mean": (first + last) / 2, "first_third": first, "last_third": last}

    def row(hm, hm_cpu, best, stock=(1.0, 1.0)):
        r = {"hippomap": {"core_ms": thirds(*hm)}}
        if hm_cpu is not None:
            r["hippomap"]["core_cpu_ms"] = thirds(*hm_cpu)
        if best is not None:
            r["ors"] = {"best": {"core_ms": thirds(*best)}, "stock": {"core_ms": thirds(*stock)}}
        return r

    lines = bench_maps.growth_lines(
        [
            row((1.0, 1.1), (1.0, 1.5), (1.0, 2.0)),
            row((1.0, 2.0), (1.0, 1.1), (0.5, 1.0), (1.0, 1.3)),
            row((2.0, 3.0), None, None),
        ]
    )
    assert lines[0] == "- hippomap last third / first third cost: median 1.50, max 2.00; runs meeting <= 1.2: 1/3"
    # CPU times only where they were measured
    assert lines[1] == "- the same on CPU time (less load-dependent): median 1.30, max 1.50; runs meeting <= 1.2: 1/2"
    # the peer's figures on the runs it ran: its own thirds, and hippomap's last third against the best's
    assert (
        lines[2]
        == "- for comparison, ORS best's own last third / first third: median 2.00, max 2.00; runs meeting <= 1.2: 0/2"
    )
    assert (
        lines[3]
        == "- for comparison, ORS stock's own last third / first third: median 1.15, max 1.30; runs meeting <= 1.2: 1/2"
    )
    assert lines[4] == "- hippomap's last third / ORS best's last third: median 1.27, max 2.00; runs <= 1: 1/2"
    assert len(lines) == 5
    # without the peer, only hippomap's lines
    assert len(bench_maps.growth_lines([row((1.0, 1.1), None, None)])) == 1


def test_sim_table_rows_have_the_header_s_columns():
    thirds = {"mean": 2.0, "first_third": 1.0, "last_third": 3.0}
    hm = {
        "odometry_ate": 5.0,
        "ate": 0.2,
        "rpe": 0.1,
        "closures_accepted": 9,
        "closures_false": 0,
        "revisits": {"episodes": 2, "closed": 2, "missed": []},
        "links": {"loop": {"mean_m": 0.1}},
        "core_ms": thirds,
        "recognition_ms": {"n": 30, "mean": 6.0, "p95": 13.0},
    }
    base = {"world": "loop", "seed": 3, "size": "320x240", "texture": "procedural"}
    table = bench_maps.sim_table([{**base, "hippomap": hm}, {**base, "error": "render failed"}])
    n = table[0].count("|")
    assert all(line.count("|") == n for line in table)
    assert "| 6.00 / 13.00 |" in table[2]  # mean / p95 of the recognitions


def test_closure_counts():
    dist = [0.5, 3.0, 7.0, None, 1.0]
    used = [True, True, True, True, False]
    c = bench_maps.count_closures(dist, used)
    assert c == {"proposed": 5, "accepted": 4, "false_2m": 2, "false_5m": 1, "unjudged": 1, "true_rejected": 1}


def test_thirds_separate_early_and_late_cost():
    ms = np.concatenate([np.full(30, 1.0), np.full(30, 2.0), np.full(30, 4.0)])
    s = bench_maps.thirds(ms)
    assert s["first_third"] == pytest.approx(1.0) and s["last_third"] == pytest.approx(4.0)
    assert s["mean"] == pytest.approx(7.0 / 3)


def test_timed_mapper_records_one_time_per_frame():
    m = bench_maps.TimedMapper()
    rng = np.random.default_rng(0)
    n = 6
    for k in range(n):
        t = 0.2 * k
        m.step(Odometry(t, v=0.0 if k == 0 else 0.5, omega=0.1))
        m.observe(Frame(t, rng.integers(0, 255, (60, 80), dtype=np.uint8)))
    assert len(m.frame_seconds) == n and len(m.frame_cpu_seconds) == n
    assert all(s > 0 for s in m.frame_seconds)
    assert len(m.trajectory_times) >= n


def test_timed_mapper_keeps_each_closure_s_highest_weight(short_run):
    """The peak robust weight of every loop decision's link after any input: at least its weight now, NaN
    only for a decision that never had a link, and the benchmark counts the false closures that were used on
    the way from it."""
    from hippomap.cli.run import open_dataset, run_dataset

    m, _ = run_dataset(open_dataset(short_run), None, mapper=bench_maps.TimedMapper())
    peak, now = m.peak_loop_weights, m.cmap.loop_weights()
    assert len(peak) == len(now) == len(m.cmap.loop_decisions) > 0
    assert np.array_equal(np.isnan(peak), np.isnan(now))  # a decision's link stays once made
    linked = ~np.isnan(now)
    assert linked.any() and np.all(peak[linked] >= now[linked])
    # a closure the kernel revised down was, on the way, weighted more than it is now
    assert np.any(peak[linked] > now[linked])
    # how long each was used: never for one that never reached USED_WEIGHT, never longer than the run after
    # it was proposed, and for a while by one used now that was proposed well before the run's end
    sec = m.used_seconds
    assert len(sec) == len(now) and np.all(sec >= 0)
    never = ~(peak >= bench_maps.USED_WEIGHT)
    assert never.any() and np.all(sec[never] == 0)
    end = float(m.trajectory_times[-1])
    proposed = np.array([d.hypothesis.time for d in m.cmap.loop_decisions])
    assert np.all(sec <= end - proposed + 1e-9)
    early_used = (now >= bench_maps.USED_WEIGHT) & (proposed < end - 5.0)
    assert early_used.any() and np.all(sec[early_used] > 0)
    # every recognition's fixations, counted as they are made: those of the recognitions the mapper kept
    assert m.fixations == sum(len(r["steps"]) for r in m.recognitions) > 0


def test_the_false_closures_used_on_the_way_are_summarised_by_distance_weight_and_time():
    assert bench_maps._ever_used_detail([]) == ""
    closures = [
        {"groundtruth_distance_m": 2.95, "peak_weight": 0.57, "used_s": 276.0},
        {"groundtruth_distance_m": 2.25, "peak_weight": 0.80, "used_s": 368.4},
    ]
    assert bench_maps._ever_used_detail(closures) == " (2.25–2.95 m apart, weight up to 0.80, used 276–368 s)"


def test_parse_size_rejects_garbage():
    assert bench_maps.parse_size("640x480") == (640, 480)
    with pytest.raises(argparse.ArgumentTypeError, match="expected WIDTHxHEIGHT"):
        bench_maps.parse_size("640")


def test_sim_cache_key_changes_with_arguments(tmp_path, monkeypatch):
    calls = []

    def fake_run(cmd, **kw):
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True)
        calls.append(cmd)

        class R:
            returncode = 0
            stderr = ""

        return R()

    monkeypatch.setattr(bench_maps.subprocess, "run", fake_run)
    shared = tmp_path / "shared"
    a, ta = bench_maps.simulate("loop", 3, (320, 240), "procedural", shared, None, tmp_path)
    a2, ta2 = bench_maps.simulate("loop", 3, (320, 240), "procedural", shared, None, tmp_path)
    b, _ = bench_maps.simulate("loop", 4, (320, 240), "procedural", shared, None, tmp_path)
    assert a == a2 and ta is not None and ta2 is None  # second call is served from the cache
    assert a != b and len(calls) == 2
    assert "--omega-bias" in calls[0] and calls[0][calls[0].index("--seed") + 1] == "3"
    # another speed or rate is another render, named so, with the simulator's options; the default adds none
    c, _ = bench_maps.simulate("loop", 3, (320, 240), "procedural", shared, None, tmp_path, {"speed": 0.2})
    d, _ = bench_maps.simulate("loop", 3, (320, 240), "procedural", shared, None, tmp_path, {"rate": 10.0})
    assert len({a, c, d}) == 3 and "-s0.2-" in c.name and "-r10-" in d.name
    assert calls[2][calls[2].index("--speed") + 1] == "0.2" and "--rate" not in calls[2]
    assert "--speed" not in calls[0] and "--rate" not in calls[0]
    assert bench_maps.world_label({"world": "loop", "motion": {"speed": 0.2, "rate": 10.0}}) == "loop (0.2 m/s, 10 Hz)"
    assert bench_maps.world_label({"world": "corridor"}) == "corridor"
    # other simulator options: after the noise (so they override it), in the name and the label
    e, _ = bench_maps.simulate("loop", 3, (320, 240), "procedural", shared, None, tmp_path, {"scale-error": 0.05})
    f, _ = bench_maps.simulate(
        "loop", 3, (320, 240), "procedural", shared, None, tmp_path, {"omega-bias": 0.03, "frame-every": 5.0}
    )
    assert len({a, c, d, e, f}) == 5 and "-scale-error0.05-" in e.name and "-omega-bias0.03-frame-every5-" in f.name
    assert calls[4][calls[4].index("--scale-error") + 1] == "0.05"
    assert calls[5][len(calls[5]) - 1 - calls[5][::-1].index("--omega-bias") + 1] == "0.03"  # the last one counts
    assert bench_maps.world_label({"world": "loop", "motion": {"speed": 0.2, "scale-error": 0.05}}) == (
        "loop (0.2 m/s, scale-error 0.05)"
    )


@pytest.mark.parametrize("bad", ["scale=0.05", "scale-error=big", "hfov"])
def test_sim_options_are_checked_by_name_and_number(bad):
    with pytest.raises(argparse.ArgumentTypeError, match="scale-error|hfov|number"):
        bench_maps.parse_sim_option(bad)
    assert bench_maps.parse_sim_option("pixel-noise=8") == ("pixel-noise", 8.0)
    assert bench_maps.parse_sim_option("exposure-change=0.3") == ("exposure-change", 0.3)
    assert bench_maps.motion_args({"exposure-change": 0.3}) == ["--exposure-change", "0.3"]
    assert bench_maps.motion_args({"blocks": bench_maps.parse_sim_option("blocks=3")[1]}) == ["--blocks", "3"]


def test_photo_sim_options_are_refused_with_procedural_walls(capsys):
    """``--sim-option photos=N`` and ``photo-overlay=0`` change photo walls only: asked for beside procedural walls
    the run stops before anything is rendered and names the options; the simulator gets them as integers."""
    with pytest.raises(SystemExit):
        bench_maps.main(["--sim-option", "photos=4", "--sim-option", "photo-overlay=0", "--skip-bicocca"])
    assert "photo-overlay, photos: photo walls only" in capsys.readouterr().err
    motion = dict([bench_maps.parse_sim_option("photos=4"), bench_maps.parse_sim_option("photo-overlay=0")])
    assert bench_maps.motion_args(motion) == ["--photos", "4", "--photo-overlay", "0"]
    assert bench_maps.motion_label(motion) == " (photos 4, photo-overlay 0)"


def test_scale_corrected_ates_are_reported_for_runs_with_a_scale_error():
    hm = {"ate": 0.36, "ate_scaled": 0.09, "scale": 0.956}
    best = {"ate": 0.30, "ate_scaled": 0.20, "scale": 0.97}
    row = {"world": "loop", "seed": 17, "size": "320x240", "texture": "procedural", "hippomap": hm}
    scaled = {**row, "motion": {"scale-error": 0.05}, "ors": {"best": best}}
    lines = bench_maps.sim_scaled_table([scaled, row])
    assert len(lines) == 4 and "0.36 / 0.09 (0.956)" in lines[2] and lines[2].endswith("| 0.45 |")
    assert lines[3].endswith("| n/a | n/a |")  # no peer in that row


def test_ors_loop_links_follow_the_experience_map_rules():
    def r(t, action, src, exp):
        return {"t": t, "action": float(action), "src_exp": float(src), "exp_id": float(exp)}

    N, E = peers.ORS_CREATE_NODE, peers.ORS_CREATE_EDGE
    rows = [
        r(0.2, N, 0, 0),  # the first experience: no link
        r(0.4, N, 0, 1),
        r(0.6, N, 1, 2),
        r(0.8, E, 2, 0),  # a loop link
        r(1.0, E, 0, 2),  # the same pair again: the map makes no new link
        r(1.2, E, 2, 1),  # already linked at creation
        r(1.4, 0, 2, 2),  # no action
        r(1.6, E, 1, 1),
    ]  # a self-link, not a loop closure
    links, n, self_links = peers.ors_loop_links(rows)
    assert links == [(0.8, 2, 0)]
    assert n == 4 and self_links == 1


def test_ors_frames_parser_recovers_a_row_cut_mid_run(tmp_path):
    # when no template passes the pre-filter, vt_err is DBL_MAX mid-run too: that row is cut
    # and glued to the next; its experience is the next row's src_exp
    cut = ("3,0.600,7,%.6f,2,1,1,2,3,999.0\n" % sys.float_info.max)[:255]
    p = tmp_path / "run_frames.csv"
    p.write_text(
        "frame,t,vt_id,vt_err,n_vt,action,src_exp,exp_id,n_exp,core_us\n"
        + _row(0, 0.0, 0)
        + _row(1, 0.2, 0, action=1, src=0)
        + _row(2, 0.4, 1, action=1, src=0)
        + cut
        + _row(4, 0.8, 2, src=2)
        + _row(5, 1.0, 0, action=2, src=2)
    )
    rows = peers._read_ors_frames(p)
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3, 4, 5]
    assert int(rows[3]["exp_id"]) == 2 and int(rows[3]["action"]) == peers.ORS_CREATE_NODE
    assert int(rows[3]["src_exp"]) == 1
    links, n, _ = peers.ors_loop_links(rows)
    assert links == [(1.0, 2, 0)] and n == 3  # 0-1, 1-2 at creation, the loop 2-0


def test_ors_frames_parser_recovers_consecutive_cut_rows(tmp_path):
    big = "%.6f" % sys.float_info.max
    cut3 = ("3,0.600,7," + big + ",2,1,1,2,3,999.0\n")[:255]
    cut4 = ("4,0.800,8," + big + ",3,1,2,3,4,999.0\n")[:255]
    p = tmp_path / "run_frames.csv"
    p.write_text(
        "frame,t,vt_id,vt_err,n_vt,action,src_exp,exp_id,n_exp,core_us\n"
        + _row(0, 0.0, 0)
        + _row(1, 0.2, 0, action=1, src=0)
        + _row(2, 0.4, 1, action=1, src=0)
        + cut3
        + cut4
        + _row(5, 1.0, 3, src=3)
        + _row(6, 1.2, 3, src=3)
    )
    rows = peers._read_ors_frames(p)
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3, 4, 5, 6]
    assert [r["t"] for r in rows] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2])
    # experience ids are consecutive: two new ids (2, 3) behind row 5 mean each cut row made one
    assert [int(r["exp_id"]) for r in rows[3:5]] == [2, 3]
    assert [int(r["action"]) for r in rows[3:5]] == [peers.ORS_CREATE_NODE, peers.ORS_CREATE_NODE]
    links, n, _ = peers.ors_loop_links(rows)
    assert links == [] and n == 3


@pytest.fixture(scope="module")
def short_run(tmp_path_factory) -> Path:
    """Two fast laps of the loop world at 96x72 with drifting odometry, written as a data folder: loops
    close, and some recognitions name a key frame and some none."""
    from hippomap import sim

    world = sim.loop_world(seed=1, laps=2, speed_mps=1.6)
    noise = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
    run = sim.simulate(world, rate_hz=5.0, camera=sim.Camera(width=96, height=72), odometry_noise=noise)
    return run.write(tmp_path_factory.mktemp("short") / "run")


def test_mapper_parts_add_up_to_the_whole_and_see_every_recognition(short_run):
    import bench_mapper_parts

    timer, m = bench_mapper_parts.run(short_run, None)
    frames = len((short_run / "frames.csv").read_text().splitlines()) - 1
    assert len(timer.rows) == frames  # one row per camera frame
    # every recognition the mapper made was timed, with its outcome
    assert len(timer.recognitions) == len(m.recognitions) > 0
    named = sum(r["frame_id"] is not None for r in m.recognitions)
    assert sum(x.named for x in timer.recognitions) == named > 0
    # each record has the recognition's own fixations and outcome, and the search that made it
    assert [x.fixations for x in timer.recognitions] == [r["n_fixations"] for r in m.recognitions]
    assert [x.named for x in timer.recognitions] == [r["frame_id"] is not None for r in m.recognitions]
    assert {x.search for x in timer.recognitions} <= {"gated", "global"}
    assert any(x.search == "gated" for x in timer.recognitions)
    # with ground truth, one that named none says how far from the robot its nearest candidate was learned:
    # inside the loop world (16 x 10 m), never for one that named a key frame; at this speed and size some are
    # made where a candidate was learned nearby and some where none was (futile)
    none = [x.truth_m for x in timer.recognitions if not x.named]
    assert none and all(0 <= d < math.hypot(16.0 + 2.5, 10.0 + 2.5) for d in none)
    assert min(none) <= bench_mapper_parts.FUTILE_M < max(none)
    assert all(np.isnan(x.truth_m) for x in timer.recognitions if x.named)
    # ... and, where some candidate was learned within FUTILE_M, the smallest true heading difference to those
    for x in timer.recognitions:
        near = not x.named and x.truth_m <= bench_mapper_parts.FUTILE_M
        assert (0 <= x.truth_rad <= math.pi) if near else np.isnan(x.truth_rad)
    # bench_maps' own mapper times each recognition too (inside the part timer's wrapper: never longer)
    assert len(m.recognition_seconds) == len(m.recognition_cpu_seconds) == len(m.recognitions)
    assert all(inner <= x.seconds + 1e-9 for inner, x in zip(m.recognition_cpu_seconds, timer.recognitions))
    rec = bench_maps.recognition_summary(m.recognition_seconds)
    assert rec["n"] == len(m.recognitions)
    assert rec["p95"] == pytest.approx(1e3 * np.percentile(m.recognition_seconds, 95))
    n = len(timer.rows)
    whole = bench_mapper_parts.per_frame(timer.rows, 0, n)
    assert all(whole[p] >= 0 for p in bench_mapper_parts.PARTS) and whole["total"] > 0
    # the parts and the rest make the total, over the run and over each third
    for lo, hi in ((0, n), (0, n // 3), (n - n // 3, n)):
        f = bench_mapper_parts.per_frame(timer.rows, lo, hi)
        assert sum(f[p] for p in bench_mapper_parts.PARTS) + f["rest"] == pytest.approx(f["total"])
    # the thirds are means of the frames they cover: weighted, they give the run's mean
    a = n // 3
    first, mid, last = (bench_mapper_parts.per_frame(timer.rows, lo, hi) for lo, hi in ((0, a), (a, n - a), (n - a, n)))
    mean = (first["total"] * a + mid["total"] * (n - 2 * a) + last["total"] * a) / n
    assert mean == pytest.approx(whole["total"])
    # the whole-map solves are timed within the map update and the loop decision that start them, not beside them
    assert 0 < whole["whole solves"] <= whole["map update"] + whole["loop decision"]


def test_mapper_parts_print_a_long_run_by_slices(short_run, capsys):
    """``--slices N`` prints every part, the rest, the total and the whole-map solves per N equal slices of the run:
    each row's slices, weighted by their frames, give the run's mean."""
    import bench_mapper_parts

    bench_mapper_parts.main([str(short_run), "--repeats", "1", "--slices", "4"])
    out = capsys.readouterr().out
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("CPU ms per frame by 4 equal slices"))
    rows = {}
    for line in lines[head + 1 : head + 1 + len(bench_mapper_parts.PARTS) + 3]:
        name, values = line[:18].strip(), [float(v) for v in line[18:].split()]
        rows[name] = values
    assert set(rows) == {*bench_mapper_parts.PARTS, "rest", "total", *bench_mapper_parts.SUBPARTS}
    assert all(len(v) == 4 for v in rows.values())
    run_line = next(line for line in lines if line.startswith("total "))
    run_mean = float(run_line.split()[1])
    frames = len((short_run / "frames.csv").read_text().splitlines()) - 1
    sizes = np.diff(np.linspace(0, frames, 5).astype(int))
    assert float(np.dot(rows["total"], sizes) / frames) == pytest.approx(run_mean, abs=2e-3)


def test_mapper_parts_label_the_searches_that_primed_the_old_path_s_sequence(short_run):
    """With ``mapper.sequence_prior`` the bench labels each recognition that started with the sequence primed
    ``gated, primed``: exactly those whose record counts primed key frames (docs/MODEL.md item 115)."""
    import bench_mapper_parts
    from hippomap.config import HippomapConfig

    cfg = HippomapConfig.with_overrides({"mapper": {"sequence_window_m": 5.0, "sequence_prior": 0.2}})
    timer, m = bench_mapper_parts.run(short_run, cfg)
    assert [x.search == "gated, primed" for x in timer.recognitions] == ["primed" in r for r in m.recognitions]
    assert sum(x.search == "gated, primed" for x in timer.recognitions) > 0
    assert {x.search for x in timer.recognitions} <= {"gated", "gated, primed", "global"}


def test_mapper_parts_tell_a_candidate_facing_away_from_one_that_faces_the_robot():
    """nearest_facing_rad: among the candidates learned within FUTILE_M of the robot's true pose, the smallest
    heading difference (wrapped); nan when none was learned that near or the pose is unknown."""
    import bench_mapper_parts as b

    learned = {0: np.array([1.0, 0.0, 3.0]), 1: np.array([0.5, 0.5, -2.9]), 2: np.array([9.0, 0.0, 0.0]), 3: None}
    now = np.array([0.0, 0.0, 3.1])
    # frames 0 and 1 are near: 0.1 rad and 0.2832 rad (across the +-pi wrap) from the robot; 2 is too far
    assert b.nearest_facing_rad(learned, [0, 1, 2, 3], now) == pytest.approx(0.1)
    assert b.nearest_facing_rad(learned, [1], now) == pytest.approx(2 * math.pi - 6.0)
    # a robot at the same place facing the other way: both near candidates face away (2.9 and 3.0 rad)
    away = b.nearest_facing_rad(learned, [0, 1], np.array([0.0, 0.0, 0.0]))
    assert away == pytest.approx(2.9) and away > b.FUTILE_RAD
    assert math.isnan(b.nearest_facing_rad(learned, [2, 3], now))
    assert math.isnan(b.nearest_facing_rad(learned, [0], None))


def test_mapper_parts_report_prints_the_recognitions_per_search(short_run, capsys):
    import bench_mapper_parts

    timer, _ = bench_mapper_parts.run(short_run, None)
    bench_mapper_parts.report("short", [timer])
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("recognitions by search")]
    assert len(lines) == 3  # one per third
    gated = sum(x.search == "gated" for x in timer.recognitions)
    counts = [int(c) for ln in lines for c in re.findall(r"gated (?:named|none) (\d+):", ln)]
    assert sum(counts) == gated > 0  # every gated recognition is counted once
    # the run has ground truth: the futile recognitions are those that named none far from every candidate
    futile = [int(c) for ln in lines for c in re.findall(r"futile (\d+)", ln)]
    assert sum(futile) == sum(not x.named and x.truth_m > bench_mapper_parts.FUTILE_M for x in timer.recognitions) > 0
    # ... and those facing away: a candidate learned near, but none of the near ones facing the robot's way
    away = [int(c) for ln in lines for c in re.findall(r"facing away (\d+)", ln)]
    assert len(away) == len(futile)
    assert sum(away) == sum(not x.named and x.truth_rad > bench_mapper_parts.FUTILE_RAD for x in timer.recognitions)


def test_looming_bench_scores_named_recognitions_against_ground_truth(short_run):
    import bench_looming
    from hippomap.config import HippomapConfig
    from hippomap.loop_pose import looming_offset

    rows = bench_looming.record(short_run, None)
    assert rows.shape[1] == 5 and len(rows) > 0 and np.all(rows[:, [0, 4]] > 0) and np.all(np.isfinite(rows))
    # the run knows its camera's field of view: the mapper's reading is on the viewing sphere, not the image plane's
    assert np.any(np.abs(np.log(rows[:, 0] / rows[:, 4])) > 1e-6)
    flat = bench_looming.record(short_run, HippomapConfig.with_overrides({"mapper": {"looming_on_sphere": False}}))
    np.testing.assert_array_equal(flat[:, 0], flat[:, 4])
    # most recognitions that name a key frame name one near the robot (the loop's laps lie within 0.5 m)
    assert np.median(np.hypot(rows[:, 1], rows[:, 2])) < 1.0
    # the bench's estimate is the model's looming offset for the same scale
    pts = np.array([[10.0, 10.0], [200.0, 30.0], [120.0, 180.0]])
    for s in (0.7, 1.1, 1.6):
        assert bench_looming.looming_distance(np.array([s]), 3.0)[0] == pytest.approx(looming_offset(pts * s, pts, 3.0))


def _odometry_folder(tmp_path: Path, every: int) -> tuple[Path, np.ndarray]:
    """A data folder's CSVs (no images): readings every 0.2 s, a frame at every ``every``-th reading."""
    rng = np.random.default_rng(7)
    t = np.round(np.arange(31) * 0.2, 6)
    odo = np.column_stack([t, rng.uniform(0.0, 1.0, t.size), rng.uniform(-0.5, 0.5, t.size)])
    d = tmp_path / f"every{every}"
    d.mkdir()
    (d / "odometry.csv").write_text("t,v,omega\n" + "".join(f"{a:.6f},{b!r},{c!r}\n" for a, b, c in odo.tolist()))
    frames = "".join(f"{x:.6f},frames/{i:06d}.png\n" for i, x in enumerate(t[::every].tolist()))
    (d / "frames.csv").write_text("t,file\n" + frames)
    return d, odo


def test_the_peer_gets_one_odometry_row_per_frame_when_frames_are_sparse(tmp_path):
    """With a frame every third reading the driver's rows are the frames' times, each with the path and the
    turn of the readings since the previous frame over its interval; with a frame per reading it gets the
    folder's own file."""
    d, odo = _odometry_folder(tmp_path, 3)
    rows = peers.per_frame_odometry(d)
    assert rows.shape == (11, 3)
    np.testing.assert_allclose(rows[:, 0], odo[::3, 0])
    assert rows[0, 1] == rows[0, 2] == 0.0
    for i in range(1, 11):
        k = slice(3 * i - 2, 3 * i + 1)  # the readings driven from frame i-1 to frame i
        span = rows[i, 0] - rows[i - 1, 0]
        assert rows[i, 1] * span == pytest.approx(float(np.sum(odo[k, 1] * 0.2)))
        assert rows[i, 2] * span == pytest.approx(float(np.sum(odo[k, 2] * 0.2)))
    written = peers.ors_odometry_file(d, tmp_path)
    assert written == tmp_path / "ors_odometry.csv"
    back = np.loadtxt(written, delimiter=",", skiprows=1)
    np.testing.assert_allclose(back, rows, rtol=0, atol=1e-6)
    dense, _ = _odometry_folder(tmp_path, 1)
    assert peers.ors_odometry_file(dense, tmp_path) == dense / "odometry.csv"


def test_familiarity_bench_sees_every_recognition_and_compares_gists(short_run):
    import bench_familiarity as bf

    rows, m = bf.record(short_run)
    # one row per recognition the mapper made, with its own fixations; a named one is right or wrong, one that
    # named none futile or missed, as its candidates' ground-truth places say
    assert len(rows) == len(m.recognitions) > 0
    assert [r["fixations"] for r in rows] == [r["n_fixations"] for r in m.recognitions]
    named = [r["frame_id"] is not None for r in m.recognitions]
    assert [r["kind"] in ("right", "wrong") for r in rows] == named
    assert any(r["kind"] == "right" for r in rows)
    # every gist scored for every recognition with candidates, as a correlation
    keys = set(bf.AREAS) | {bf.GRADIENT}
    scored = [r["familiarity"] for r in rows if r["familiarity"]]
    assert scored and all(set(f) == keys and all(-1.0 <= v <= 1.0 + 1e-6 for v in f.values()) for f in scored)
    # the correlation: 1 for a gist with itself; a gist panned by one cell matches only when shifts are allowed
    rng = np.random.default_rng(0)
    a = rng.random((6, 10)).astype(np.float32)
    b = np.roll(a, 1, axis=1)
    assert bf.correlation(a, a, 0) == pytest.approx(1.0)
    assert bf.correlation(a, b, 0) < 0.9 and bf.correlation(b, a, 2) == pytest.approx(1.0)


def test_solver_bench_records_the_maps_whole_solves_and_feeds_each_link_once(short_run):
    import bench_solvers
    from hippomap.least_squares import graph_cost, solve_lsq
    from hippomap.map_correction import MapCorrection

    whole, optimise = MapCorrection._whole_solve, MapCorrection._optimise
    problems, calls = bench_solvers.record_run(short_run, None)
    # the recorder shadows the methods of its own map only: the class is left as it is
    assert (MapCorrection._whole_solve, MapCorrection._optimise) == (whole, optimise)
    assert problems and calls and all(s >= 0 for _, s in calls)
    for p in problems:
        n, m = len(p.poses), len(p.src)
        assert p.poses.shape == (n, 3) and p.transforms.shape == p.information.shape == (m, 3)
        assert max(p.src.max(), p.dst.max()) < n and np.all(p.information > 0)
    # the map grows between its whole solves, and each one holds at least the nodes' chain
    assert [len(p.poses) for p in problems] == sorted(len(p.poses) for p in problems)
    last = problems[-1]
    n = len(last.poses)
    assert len(last.src) >= n - 1
    batches = bench_solvers.incremental_batches(last.src, last.dst, n)
    # every link once, at the node that completes it, in link order within a node
    assert len(batches) == n
    assert sorted(np.concatenate(batches).tolist()) == list(range(len(last.src)))
    for k, b in enumerate(batches):
        assert np.all(np.maximum(last.src[b], last.dst[b]) == k) and np.all(np.diff(b) > 0)
    # a recorded problem is the map's pose graph: hippomap's solve lowers its cost
    rows = bench_solvers.thirds_by_node(np.array([c[0] for c in calls]), np.array([c[1] for c in calls]), n)
    assert rows[0] >= rows[1] + rows[2] - 1e-12
    before = graph_cost(last.poses, last.src, last.dst, last.transforms, information=last.information)
    q = last.poses.copy()
    solve_lsq(q, last.src, last.dst, last.transforms, 10, 0, 1e-4, information=last.information)
    assert graph_cost(q, last.src, last.dst, last.transforms, information=last.information) <= before


def test_the_old_revision_is_imported_apart_and_its_copy_removed_at_exit(tmp_path):
    """bench_mapper_vs imports the package as it is at a git revision from a temporary copy under a private
    name, beside the working tree's; the copy is removed when the process exits (runs used to leave one per
    run behind)."""
    root = Path(__file__).resolve().parents[1]  # a git checkout: bench_mapper_vs reads the old code with git archive
    code = (
        "import sys; sys.path.insert(0, 'bench'); import bench_mapper_vs as b, hippomap.mapper\n"
        "old = b.load_revision('HEAD')\n"
        "print(old.__file__)\n"
        "print(old.mapper.Mapper is not hippomap.mapper.Mapper, old.__name__.startswith('hippomap_rev_'))\n"
    )
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    where, flags = out.stdout.splitlines()[-2:]
    assert Path(where).resolve().is_relative_to(tmp_path.resolve())  # the copy was made where TMPDIR says
    assert flags == "True True"
    assert not list(tmp_path.glob("hippomap-rev-*")), "the old revision's copy was left behind"


def test_both_revisions_run_with_the_data_set_s_camera_field_of_view():
    """bench_mapper_vs gives each version the camera field of view of the data set, as ``hippomap run`` does
    (without it a recognition's image shift gives no heading and the runs are not the benchmark's), keeps a
    field of view the config sets, and leaves alone the config of a revision without ``dataset_config``."""
    import types

    import bench_mapper_vs
    import hippomap
    from hippomap.config import HippomapConfig

    camera = SimpleNamespace(camera_hfov_deg=62.5)
    cfg = bench_mapper_vs.with_camera(hippomap, None, camera)
    assert cfg.mapper.camera_hfov_deg == 62.5
    assert cfg.model_copy(update={"mapper": HippomapConfig().mapper}) == HippomapConfig()  # nothing else changed
    own = HippomapConfig.model_validate({"mapper": {"camera_hfov_deg": 90.0}, "visual": {"max_resets": 3}})
    assert bench_mapper_vs.with_camera(hippomap, own, camera) is own
    overrides = HippomapConfig.model_validate({"visual": {"max_resets": 3}})  # --config without a field of view
    given = bench_mapper_vs.with_camera(hippomap, overrides, camera)
    assert (given.mapper.camera_hfov_deg, given.visual.max_resets) == (62.5, 3)
    no_camera = SimpleNamespace(camera_hfov_deg=None)
    assert bench_mapper_vs.with_camera(hippomap, None, no_camera).mapper.camera_hfov_deg is None
    old = SimpleNamespace(mapper=SimpleNamespace())
    assert bench_mapper_vs.with_camera(types.ModuleType("hippomap_rev_0000000"), old, camera) is old


def test_unfinished_renders_of_stopped_runs_are_removed_and_running_ones_kept(tmp_path):
    """A run stopped while rendering leaves ``<name>.tmp<pid>`` in the render cache; the next render of the
    same folder removes it when that process is gone, and leaves a render whose process still runs."""
    folder = tmp_path / "sim" / "loop-s1-320x240-procedural-abc"
    folder.parent.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid whose process has exited (and been reaped)
    stale = folder.with_name(folder.name + f".tmp{dead.pid}")
    running = folder.with_name(folder.name + f".tmp{os.getppid()}")
    other = tmp_path / "sim" / ("loop-s2-320x240-procedural-abc" + f".tmp{dead.pid}")  # another render's
    for d in (stale, running, other):
        (d / "frames").mkdir(parents=True)
        (d / "frames" / "000000.png").write_bytes(b"x")
    assert bench_maps.remove_stale_renders(folder) == [stale]
    assert not stale.exists() and running.exists() and other.exists()


def test_paired_timing_alternates_the_two_sides_and_takes_the_median_ratio(short_run, tmp_path, monkeypatch):
    """--time-pairs: each pair times hippomap (the real mapper on the same frames) and the peer at the threshold
    asked, which goes first alternating, and reports every pair's ratio and their median; the sweep keeps which
    of its runs was the stock config, so that the stock one is run again as stock."""
    calls: list[str] = []
    peer_ms = iter([4.0, 1e-3, 2.0])  # a fast, a slow and a middling peer: the median must be the middle pair

    def fake_run_ors(exe, peer_dir, data, width, height, threshold, work, odometry=None):
        calls.append(f"ors {threshold}")
        return argparse.Namespace(core_ms={"mean": next(peer_ms)})

    def counted_run(dataset, cfg, mapper):  # the real mapper on the run's first readings and frames (a short test)
        calls.append("hippomap")
        for item, _ in zip(dataset.events(), range(12)):
            mapper.step(item) if isinstance(item, Odometry) else mapper.observe(Frame(item.t, item.load().image))
        return mapper, {}

    monkeypatch.setattr(peers, "run_ors", fake_run_ors)
    monkeypatch.setattr(bench_maps, "run_dataset", counted_run)
    pt = bench_maps.paired_timing(short_run, None, Path("ors"), Path("peer"), (96, 72), 0.03, tmp_path, 3)
    assert calls == ["hippomap", "ors 0.03", "ors 0.03", "hippomap", "hippomap", "ors 0.03"]
    hm = pt["hippomap_ms"]
    assert len(hm) == 3 and all(0 < x < 1e3 for x in hm)
    assert pt["ors_ms"] == [4.0, 1e-3, 2.0]
    assert pt["ratios"] == pytest.approx([hm[0] / 4.0, hm[1] / 1e-3, hm[2] / 2.0])
    assert pt["ratio_median"] == pytest.approx(sorted(pt["ratios"])[1])
    with pytest.raises(ValueError, match="pairs must be at least 1, got 0"):
        bench_maps.paired_timing(short_run, None, Path("ors"), Path("peer"), (96, 72), 0.03, tmp_path, 0)
    with pytest.raises(SystemExit):
        bench_maps.main(["--time-pairs", "-1", "--skip-sim", "--skip-bicocca"])

    def fake_score(res, gt):
        return {"ate": res.ate, "threshold": res.threshold}

    ates = {None: 0.5, 0.02: 0.9, 0.03: 0.7}
    monkeypatch.setattr(bench_maps, "score_ors", fake_score)
    monkeypatch.setattr(
        peers, "run_ors", lambda exe, pd, data, w, h, th, work, odo=None: argparse.Namespace(ate=ates[th], threshold=th)
    )
    monkeypatch.setattr(peers, "ors_odometry_file", lambda data, work: work / "odo.csv")
    sweep = bench_maps.run_ors_sweep(Path("ors"), Path("peer"), short_run, (96, 72), [0.02, 0.03], tmp_path, None)
    assert sweep["best_is_stock"] and sweep["best"]["ate"] == 0.5
    ates[0.03] = 0.1
    sweep = bench_maps.run_ors_sweep(Path("ors"), Path("peer"), short_run, (96, 72), [0.02, 0.03], tmp_path, None)
    assert not sweep["best_is_stock"] and sweep["best"]["threshold"] == 0.03


def test_closure_bound_ate_ignores_a_rigid_motion_and_counts_an_offset():
    import bench_closure_bound

    rng = np.random.default_rng(3)
    T = np.column_stack([rng.uniform(-5, 5, (40, 2)), rng.uniform(-3, 3, 40)])
    c, s = np.cos(0.7), np.sin(0.7)
    moved = T.copy()
    moved[:, :2] = T[:, :2] @ np.array([[c, s], [-s, c]]) + [3.0, -2.0]
    assert bench_closure_bound.node_ate(moved, T) == pytest.approx(0.0, abs=1e-9)
    bent = T.copy()
    bent[::2, 0] += 0.2  # half the nodes 0.2 m off, the other half on: no rigid motion undoes that
    assert 0.05 < bench_closure_bound.node_ate(bent, T) < 0.2


def test_closure_bound_revisits_are_earlier_places_passed_long_before_and_facing_alike():
    import bench_closure_bound

    # a 10 m straight line driven east, then back west 0.3 m beside it, then east again on it
    x = np.arange(0.0, 10.0, 0.5)
    east = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    west = np.column_stack([x[::-1], np.full_like(x, 0.3), np.full_like(x, np.pi)])
    T = np.vstack([east, west, east])
    path = np.arange(len(T)) * 0.5
    later, earlier = bench_closure_bound.revisit_pairs(T, path, within_m=1.0, within_rad=0.8, after_m=5.0)
    # the way back faces the other way: no revisit; the third pass finds each place of the first
    assert set(later) == set(range(2 * len(x), 3 * len(x)))
    assert np.array_equal(earlier, later - 2 * len(x))


def test_closure_bound_solves_the_map_s_own_graph_back_to_the_map(short_run):
    import bench_closure_bound

    args = argparse.Namespace(iterations=30, revisit_m=1.0, revisit_rad=0.8, revisit_path=30.0)
    r = bench_closure_bound.bound(short_run, None, args)
    assert r["used loop links"] > 0 and r["revisit links"] > 0
    # re-solving the finished graph from the map's poses, with its weights and bias, finishes the map's own solve:
    # no worse, and the same map (an online map stops short of convergence after a late closure, by up to a
    # quarter of its ATE on this run under other visual seeds); true loop links and every revisit give a better one
    assert 0.6 * r["map"] <= r["as is"] <= r["map"] + 0.005
    assert r["true links"] < r["as is"]
    assert r["every revisit"] < r["as is"]


def _square_dataset():
    """Eight poses around a 2 m square (ground truth at times 0..7 s): pose 7 stands 0.5 m short of pose 0 and
    pose 4 at the opposite corner, 2.8 m away; pose 6's time has no ground truth."""
    xy = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 0.5]], float)
    t = np.array([0, 1, 2, 3, 4, 5, 7], float)  # no ground truth near 6 s
    poses = np.c_[xy[[0, 1, 2, 3, 4, 5, 7]], np.zeros(7)]
    return SimpleNamespace(times=np.arange(8, dtype=float), groundtruth=(t, poses)), xy


def test_true_closures_are_those_the_ground_truth_puts_within_two_metres():
    dataset, _ = _square_dataset()
    assert bench_maps.true_closure(dataset, 7, 0)  # 0.5 m apart
    assert not bench_maps.true_closure(dataset, 4, 0)  # 2.83 m apart
    assert not bench_maps.true_closure(dataset, 6, 0)  # no ground truth at pose 6: cannot tell


def test_gtsam_applies_only_the_loop_factors_it_is_told_to_keep(tmp_path):
    """run_gtsam(keep=...): the left-out loop factor neither appears among the loops nor moves the solution; the
    solution equals that of the same graph written without it (the oracle row of the online checkpoints). GTSAM
    comes with the test extra (through the bench extra), so this runs wherever the suite does."""
    dataset, xy = _square_dataset()
    head = [f"VERTEX_SE2 {i} {x:.3f} {y:.3f} 0" for i, (x, y) in enumerate(xy)]
    info = "100 0 0 100 0 1000"
    odo = [
        f"EDGE_SE2 {i} {i + 1} {xy[i + 1, 0] - xy[i, 0]:.3f} {xy[i + 1, 1] - xy[i, 1]:.3f} 0 {info}" for i in range(7)
    ]
    odo[3] = f"EDGE_SE2 3 4 0.2 1.1 0 {info}"  # one odometry step off: the closures pull the square back
    true_loop = f"EDGE_SE2 7 0 0 -0.5 0 {info}"
    false_loop = f"EDGE_SE2 4 0 0 0 0 {info}"  # says the far corner is the start
    both, only = tmp_path / "both.g2o", tmp_path / "only.g2o"
    both.write_text("\n".join([*head, *odo, true_loop, false_loop]) + "\n")
    only.write_text("\n".join([*head, *odo, true_loop]) + "\n")
    kept = peers.run_gtsam(both, "none", keep=lambda i, j: bench_maps.true_closure(dataset, i, j))
    assert [(lp["i"], lp["j"]) for lp in kept.loops] == [(7, 0)]
    np.testing.assert_allclose(kept.poses, peers.run_gtsam(only, "none").poses, atol=1e-9)
    everything = peers.run_gtsam(both, "none")
    assert len(everything.loops) == 2
    assert np.abs(everything.poses - kept.poses).max() > 0.1  # the false closure, applied, moves the map


def test_sim_vpr_sets_split_a_run_into_passes_with_ground_truth_positives(short_run):
    """bench_sim_vpr.build_set: references along the first half of the true path, queries along the second, each
    query's positives the references learned within the radius and facing its way; score() counts the memory's
    acceptances as true, near or false by the same ground truth."""
    import csv

    import bench_sim_vpr as b
    from hippomap.geometry import path_lengths

    ds, truth = b.build_set(short_run, 1.0, 2.0, 1.0, 0.35)
    with open(short_run / "frames.csv") as f:
        files = [short_run / r["file"] for r in csv.DictReader(f)]
    gt = np.loadtxt(short_run / "groundtruth.csv", delimiter=",", skiprows=1, ndmin=2)
    path = path_lengths(gt[:, 1:3])
    at = {p: i for i, p in enumerate(files)}
    ref_i, query_i = [at[p] for p in ds.references], [at[p] for p in ds.queries]
    half = path[-1] / 2
    # two laps: references cover the first lap at 1 m apart, queries the second at 2 m; in time order
    assert ref_i == sorted(ref_i) and query_i == sorted(query_i) and max(ref_i) < min(query_i)
    assert all(path[i] <= half + 0.5 for i in ref_i) and all(path[i] > half - 0.5 for i in query_i)
    assert np.diff(path[ref_i]).min() >= 1.0 and np.diff(path[query_i]).min() >= 2.0
    assert len(ds.references) >= 0.6 * half and truth.shape == (len(ds.queries), len(ds.references), 2)
    # positives are exactly the references within 1 m and 0.35 rad; the second lap passes the first's places
    for q, pos in enumerate(ds.positives):
        assert pos == set(np.flatnonzero((truth[q, :, 0] <= 1.0) & (truth[q, :, 1] <= 0.35)).tolist())
    assert sum(1 for p in ds.positives if p) >= 0.5 * len(ds.queries)
    r = b.score(ds, truth, b.read_visual_config(None, None), 1)
    assert r["with_positive"] == sum(1 for p in ds.positives if p)
    assert r["tp"] > 0 and r["tp"] + r["near"] + r["fp"] <= len(ds.queries)
    # a config override reaches the memory: nothing is accepted with the threshold out of reach (activity stops at 1)
    none = b.score(ds, truth, b.read_visual_config(None, ["decision_threshold=1.0"]), 1)
    assert none["tp"] == none["near"] == none["fp"] == 0
