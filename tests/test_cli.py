"""The ``hippomap`` command line: ``--version``, one progress switch for every long command,
help texts without Sphinx markup, and ``simulate``'s realistic odometry noise by default."""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import re
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

from hippomap.cli import build_parser, clean_help, main, plain_text, progress_enabled
from hippomap.sim import cli as sim_cli
from tests.support.streams import FakeTTY

ROOT = Path(__file__).resolve().parents[1]
LONG_COMMANDS = ["run", "run-odometry", "eval-vpr", "simulate", "replay"]
MARKUP = ("``", ":class:", ":func:", ":meth:", ":mod:", ":attr:")


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_version_is_the_package_metadata():
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert out.getvalue().strip() == f"hippomap {version('hippomap')}"
    r = subprocess.run(
        [sys.executable, "-m", "hippomap", "--version"], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert r.returncode == 0 and r.stdout.strip() == f"hippomap {version('hippomap')}"


@pytest.mark.parametrize("command", LONG_COMMANDS)
def test_every_long_command_has_the_same_progress_switch(command):
    sub = _subparsers(build_parser())[command]
    flags = {s for a in sub._actions for s in a.option_strings if "progress" in s or s == "--quiet"}
    assert flags == {"--progress", "--no-progress", "--quiet"}
    assert "--quiet" not in sub.format_help()  # the old spelling is accepted, not advertised
    required = {
        "run": ["d", "--out", "o"],
        "run-odometry": ["d", "--loops", "l", "--out", "o"],
        "eval-vpr": ["d", "--out", "o"],
        "simulate": ["loop", "--out", "o"],
        "replay": ["d", "--server", "http://x"],
    }[command]
    parser = build_parser()
    parse = lambda *extra: parser.parse_args([command, *required, *extra])  # noqa: E731
    assert progress_enabled(parse("--progress")) is True
    assert progress_enabled(parse("--no-progress")) is False
    assert progress_enabled(parse("--quiet")) is False
    assert parse().progress is None  # left to the terminal test below


@pytest.mark.parametrize("tty", [True, False])
def test_progress_defaults_to_whether_stderr_is_a_terminal(monkeypatch, tty):
    monkeypatch.setattr(sys, "stderr", FakeTTY(tty))
    assert progress_enabled(argparse.Namespace(progress=None)) is tty
    assert progress_enabled(argparse.Namespace(progress=not tty)) is (not tty)


def test_simulate_progress_bar_follows_the_switch(tmp_path):
    """The switch reaches the work: a bar on stderr with --progress, none with --no-progress."""
    base = ["simulate", "corridor", "--laps", "1", "--width", "32", "--height", "24", "--frame-every", "20"]
    shown = subprocess.run(
        [sys.executable, "-m", "hippomap", *base, "--out", str(tmp_path / "a"), "--progress"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    hidden = subprocess.run(
        [sys.executable, "-m", "hippomap", *base, "--out", str(tmp_path / "b"), "--no-progress"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert shown.returncode == 0 and hidden.returncode == 0, shown.stderr + hidden.stderr
    assert "frames:" in shown.stderr and "frame/s" in shown.stderr
    assert hidden.stderr == ""


def _all_help_texts() -> dict[str, str]:
    parser = build_parser()
    texts = {"hippomap": parser.format_help()}
    texts.update({name: sub.format_help() for name, sub in _subparsers(parser).items()})
    sim_parser = argparse.ArgumentParser(prog="python -m hippomap.sim", description=sim_cli.__doc__)
    sim_cli._arguments(sim_parser)
    texts["python -m hippomap.sim"] = clean_help(sim_parser).format_help()
    return texts


def test_help_texts_have_no_sphinx_markup():
    texts = _all_help_texts()
    assert {"run", "run-odometry", "eval-vpr", "simulate", "replay", "serve"} <= set(texts)
    for name, text in texts.items():
        for mark in MARKUP:
            assert mark not in text, f"{name} --help shows {mark!r}"


def test_every_subcommand_help_runs():
    """``hippomap COMMAND --help`` as a user runs it: exit 0, usage printed, no markup."""
    for name in _subparsers(build_parser()):
        r = subprocess.run(
            [sys.executable, "-m", "hippomap", name, "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
        )
        assert r.returncode == 0 and r.stdout.startswith(f"usage: hippomap {name}"), r.stderr
        assert not any(mark in r.stdout for mark in MARKUP), r.stdout


def test_simulate_help_describes_what_the_options_do():
    text = " ".join(_all_help_texts()["simulate"].split())
    assert "COMMAND_MODULES" not in text  # commands register through entry points now
    assert "--no-noise" in text and "default 0.02" in text and "default 0.01" in text


def test_plain_text_strips_roles_and_literals():
    assert plain_text("feeds ``x`` to one :class:`~hippomap.mapper.Mapper`") == "feeds x to one Mapper"
    assert plain_text(":func:`hippomap.sim.simulate` and :meth:`A.b`") == "hippomap.sim.simulate and A.b"
    assert plain_text("so::\n\n    code") == "so:\n\n    code"


def _trajectory(folder: Path, name: str) -> np.ndarray:
    with open(folder / name) as f:
        return np.array([[float(x) for x in row] for row in list(csv.reader(f))[1:]])


def _odometry_drift(folder: Path) -> float:
    """Distance between the integrated odometry and the ground truth at the end of the run."""
    from hippomap.geometry import integrate
    from hippomap.sim.motion import arc_increments

    odo, gt = _trajectory(folder, "odometry.csv"), _trajectory(folder, "groundtruth.csv")
    poses = integrate(arc_increments(odo[1:, 1], odo[1:, 2], np.diff(odo[:, 0])), gt[0, 1:])
    return float(np.hypot(*(poses[-1, :2] - gt[-1, 1:3])))


def test_simulate_writes_noisy_odometry_by_default_and_exact_with_no_noise(tmp_path):
    base = [
        "simulate",
        "loop",
        "--laps",
        "1",
        "--width",
        "32",
        "--height",
        "24",
        "--frame-every",
        "50",
        "--no-progress",
    ]
    assert main([*base, "--out", str(tmp_path / "noisy")]) == 0
    assert main([*base, "--out", str(tmp_path / "exact"), "--no-noise"]) == 0
    assert main([*base, "--out", str(tmp_path / "bias"), "--no-noise", "--omega-bias", "0.01"]) == 0
    meta = json.loads((tmp_path / "noisy" / "sim.json").read_text())
    assert meta["config"]["odometry_noise"] == {
        "sigma_v": 0.02,
        "sigma_omega": 0.01,
        "omega_bias": 0.01,
        "scale_error": 0.0,
        "omega_bias_walk": 0.0,
    }
    assert _odometry_drift(tmp_path / "exact") < 1e-6
    assert _odometry_drift(tmp_path / "noisy") > 0.2  # one 52 m lap drifting 0.01 rad/s
    assert _odometry_drift(tmp_path / "bias") > 0.2
    assert json.loads((tmp_path / "bias" / "sim.json").read_text())["config"]["odometry_noise"]["sigma_v"] == 0.0


def test_readme_simulate_then_run_closes_loops_with_the_defaults(tmp_path):
    """The README's path, as written there: ``simulate loop --seed 3`` (default noise) then
    ``run`` (default config). About 25 s on one core: 1,915 steps rendered and mapped."""
    readme = (ROOT / "README.md").read_text()
    assert "hippomap simulate loop --out sim/loop --seed 3\n" in readme
    assert main(["simulate", "loop", "--out", str(tmp_path / "sim"), "--seed", "3", "--no-progress"]) == 0
    assert main(["run", str(tmp_path / "sim"), "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["odometry"]["ate"]["rmse"] > 1.0  # the odometry drifts
    assert m["loop_closures"]["used"] >= 1 and m["loop_closures"]["used_false"] == 0
    assert m["map"]["ate"]["rmse"] < 0.5 * m["odometry"]["ate"]["rmse"]


def _wait_for(srv, pattern: str, timeout: float = 120.0) -> re.Match:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in list(srv.output):
            m = re.search(pattern, line)
            if m:
                return m
        time.sleep(0.1)
    raise AssertionError(f"no line matching {pattern!r} in:\n{''.join(srv.output)}")


def _demo_sessions(srv) -> list[dict]:
    with srv.client() as c:
        return [s for s in c.sessions() if s["name"] == "demo robot"]


def test_serve_demo_reuses_its_session_across_restarts_and_says_when_it_finished(tmp_path):
    """One lap at 1x then 20x real time (a 44 s lap, stopped after 40 inputs, then 2 s of driving; at
    1x a loaded machine cannot finish the lap before the first server stops): a restart mid-run resumes the
    same session where it stopped, the robot says when its lap is done, and a restart after
    that leaves the finished session alone instead of adding another demo session."""
    from hippomap.client import Client, ServerError
    from server.demo import demo_run
    from tests.support.live import LiveServer

    data = tmp_path / "data"
    run = demo_run(10.0, 1, 1)
    n_inputs = len(run.times) + run.n_frames
    with LiveServer(data, args=["--demo", "--demo-laps", "1", "--demo-speed", "1"]) as srv:
        sid = _wait_for(srv, r"demo robot streaming into session (s_\w+)").group(1)
        with srv.client() as c:
            while c.stats(sid)["inputs_stored"] < 40:
                time.sleep(0.1)
    assert not any("finished" in line for line in srv.output)  # stopped mid-lap
    with LiveServer(data, args=["--demo", "--demo-laps", "1", "--demo-speed", "20"]) as srv:
        assert _wait_for(srv, r"demo robot back in its session (s_\w+)").group(1) == sid
        m = _wait_for(srv, r"demo robot finished its 1 lap \((\d+) steps.* in session (s_\w+)")
        assert m.group(2) == sid and int(m.group(1)) == len(run.times)
        viewer = _wait_for(srv, r"viewer: (\S+)/viewer/(s_\w+)/\?token=(hm_\S+)")
        assert viewer.group(2) == sid
        assert [s["id"] for s in _demo_sessions(srv)] == [sid]
        with srv.client() as c:
            st = c.wait_processed(sid)
            stored = c.all_inputs(sid)
            # the demo robot gave its camera's field of view, as a calibrated robot's client does
            assert c.session(sid)["config"]["mapper"]["camera_hfov_deg"] == run.config.camera.hfov_deg
        # the stats show the whole run: every input once, the last at the run's end
        assert st["inputs_stored"] == n_inputs and st["last_odometry_t"] == pytest.approx(float(run.times[-1]))
        assert st["mapper"]["odometry_steps"] == len(run.times) and st["rejected"] == {}
        for kind in ("odometry", "frame"):
            ts = [r["t"] for r in stored if r["kind"] == kind]
            assert ts == sorted(set(ts)) and len(ts) == len(run.times)
        old_viewer = viewer.group(3)
    with LiveServer(data, args=["--demo", "--demo-laps", "1", "--demo-speed", "20"]) as srv:
        assert _wait_for(srv, r"session (s_\w+) already holds its whole run").group(1) == sid
        new_viewer = _wait_for(srv, r"viewer: \S+\?token=(hm_\S+)").group(1)
        assert [s["id"] for s in _demo_sessions(srv)] == [sid]
        with srv.client() as c:
            assert c.stats(sid)["inputs_stored"] == n_inputs
        with Client(srv.url, new_viewer) as v:
            assert v.stats(sid)["inputs_stored"] == n_inputs
        with Client(srv.url, old_viewer) as v, pytest.raises(ServerError) as e:  # the previous start's is revoked
            v.stats(sid)
        assert e.value.status == 401


def test_readme_python_client_example_runs_against_a_live_server(tmp_path):
    """The README's client example, extracted between its markers and run unchanged but for
    the server's address, streams a simulated run and prints the accepted loop closures."""
    from tests.support.live import LiveServer

    readme = (ROOT / "README.md").read_text()
    m = re.search(r"<!-- python-client-example -->\n```python\n(.*?)```\n<!-- /python-client-example -->", readme, re.S)
    assert m, "README.md has no marked Python client example"
    code = m.group(1)
    assert len(code.splitlines()) <= 20
    assert "from hippomap.client import Client, Odometry\n" in code and "hippomap.inputs" not in code
    with LiveServer(tmp_path / "data") as srv:
        assert code.count("http://127.0.0.1:8000") == 1
        script = tmp_path / "example.py"
        script.write_text(code.replace("http://127.0.0.1:8000", srv.url))
        env = {
            **os.environ,
            "HIPPOMAP_TOKEN": srv.token,
            "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p),
        }
        r = subprocess.run(
            [sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300
        )
        assert r.returncode == 0, r.stderr
        sid = re.search(r"^session (s_\w+): \d+ nodes$", r.stdout, re.M).group(1)
        printed = re.findall(r"^loop closure at t = [\d.]+ s: node (\d+) -> node (\d+)$", r.stdout, re.M)
        with srv.client() as c:
            accepted = c.loop_closures(sid, status="accepted")
            assert c.stats(sid)["rejected"] == {}
    used = [lc for lc in accepted if lc["used"]]
    assert len(printed) >= 1
    assert [tuple(map(int, p)) for p in printed] == [tuple(lc["nodes"]) for lc in used]
    assert all(lc["weight"] is None or lc["weight"] >= 0.5 for lc in used)


def test_client_exports_its_public_types():
    import hippomap.client as client
    from hippomap.inputs import Odometry

    assert client.Odometry is Odometry
    assert {"Client", "Stream", "AsyncStream", "Odometry", "ServerError"} <= set(client.__all__)
    assert all(hasattr(client, name) for name in client.__all__)


def test_simulate_noise_options_per_world():
    """Realistic noise for the drawn worlds, none added to Bicocca's real odometry; --no-noise
    zeroes the defaults and explicit options apply on top of either."""
    from hippomap.errors import InputError
    from hippomap.sim import OdometryNoise

    def noise(*argv: str) -> OdometryNoise:
        p = argparse.ArgumentParser()
        sim_cli._arguments(p)
        return sim_cli.odometry_noise(p.parse_args([*argv, "--out", "o"]))

    assert noise("loop") == noise("corridor") == OdometryNoise.realistic() == OdometryNoise(0.02, 0.01, 0.01, 0.0)
    assert noise("bicocca") == noise("loop", "--no-noise") == OdometryNoise()
    assert noise("bicocca", "--omega-bias", "0.01") == OdometryNoise(omega_bias=0.01)
    assert noise("loop", "--sigma-v", "0") == OdometryNoise(0.0, 0.01, 0.01, 0.0)
    with pytest.raises(InputError, match="sigma_v"):
        noise("loop", "--sigma-v", "-1")
