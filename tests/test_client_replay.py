"""The Python client and ``hippomap replay`` against a live server: a recorded data set
(the project's folder format) streamed into a session ends in the state of the offline
mapper; an interrupted replay resumes without duplicates; the synchronous stream facade
acknowledges in order."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re

import httpx
import pytest

from hippomap.client import ServerError
from hippomap.client.replay import add_parser
from hippomap.errors import InputError
from hippomap.io.datasets import read_folder_dataset
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import synthetic_inputs

CONFIG = {"mapper": {"keyframe_interval": 5}}
ITEMS = synthetic_inputs(n_odometry=160, frame_every=3, seed=3)


@pytest.fixture(scope="module")
def server(tmp_path_factory, variant):
    srv = variant.server(tmp_path_factory.mktemp("replay")).start()
    yield srv
    srv.stop()


def write_folder(folder, items):
    """The items as a hippomap data folder (frames/, frames.csv, odometry.csv)."""
    (folder / "frames").mkdir(parents=True)
    frames, odo = ["t,file"], ["t,v,omega"]
    for k, it in enumerate(items):
        if it[0] == "odometry":
            o = it[1]
            odo.append(f"{o.t!r},{o.v!r},{o.omega!r}")
        else:
            name = f"{k:06d}.jpg"
            (folder / "frames" / name).write_bytes(it[2])
            frames.append(f"{it[1]!r},{name}")
    (folder / "frames.csv").write_text("\n".join(frames) + "\n")
    (folder / "odometry.csv").write_text("\n".join(odo) + "\n")
    return folder


def run_replay(*argv):
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["replay", *argv])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = args.func(args)
    return rc, out.getvalue()


def check_viewer_url(server, out, sid):
    """replay printed the viewer URL of the session it streamed into, as the server links it,
    and that page is the session's live viewer for a token that may read the session."""
    url = re.search(r"^viewer: (\S+)", out, re.M).group(1)
    with server.client() as c:
        assert url == c.session(sid)["links"]["viewer"] == f"{server.url}/viewer/{sid}/"
        viewer = c.create_token("viewer", session=sid)["token"]
    page = httpx.get(url, params={"token": viewer}, timeout=60)
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert httpx.get(url, params={"token": "hm_not_a_token"}, timeout=60).status_code in (401, 404)


def test_replay_folder_dataset_matches_offline(server, tmp_path):
    folder = write_folder(tmp_path / "run", ITEMS)
    assert [e.t for e in read_folder_dataset(folder).events()] == [
        it[1].t if it[0] == "odometry" else it[1] for it in ITEMS
    ]
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(CONFIG))
    rc, out = run_replay(
        str(folder), "--server", server.url, "--token", server.token, "--config", str(cfg), "--no-progress"
    )
    assert rc == 0
    sid = re.search(r"session (\S+)", out).group(1)
    assert "all acknowledged" in out and "nodes" in out
    check_viewer_url(server, out, sid)
    with server.client() as c:
        m = c.stats(sid)["mapper"]
        printed = re.search(r"loop closures accepted (\d+) \(used (\d+)\) / rejected (\d+)", out)
        assert printed and tuple(map(int, printed.groups())) == (
            m["loop_closures_accepted"],
            m["loop_closures_used"],
            m["loop_closures_rejected"],
        )
        stored = c.all_inputs(sid)
        assert len(stored) == len(ITEMS)
        frame_seq = next(r["seq"] for r in stored if r["kind"] == "frame")
        assert c.frame(sid, frame_seq) == ITEMS[frame_seq][2]  # the original JPEG bytes
        assert session_state(c, sid) == offline_reference(ITEMS, CONFIG)


def test_interrupted_replay_resumes_without_duplicates(server, tmp_path):
    half = write_folder(tmp_path / "half", ITEMS[:70])
    full = write_folder(tmp_path / "full", ITEMS)
    with server.client() as c:
        sid = c.create_session("resume", CONFIG)["id"]
    into = ("--server", server.url, "--token", server.token, "--session", sid, "--no-progress")
    rc, _ = run_replay(str(half), *into, "--no-wait", "--speed", "50")
    assert rc == 0
    with pytest.raises(InputError, match="--resume"):  # replaying from the start again is refused before sending
        run_replay(str(full), *into)
    with server.client() as c:
        assert len(c.all_inputs(sid)) == 70  # nothing of the refused replay was stored
    rc, out = run_replay(
        str(full),
        *into,
        "--resume",
        "--window",
        "8",
    )
    assert rc == 0 and "skipped 70 already stored" in out
    check_viewer_url(server, out, sid)  # an existing session: its own viewer
    with server.client() as c:
        stored = c.all_inputs(sid)
        assert [r["t"] for r in stored] == [it[1].t if it[0] == "odometry" else it[1] for it in ITEMS]
        assert session_state(c, sid) == offline_reference(ITEMS, CONFIG)


def test_sync_stream_and_client_errors(server):
    with server.client() as c:
        sid = c.create_session("sync", CONFIG)["id"]
        with c.stream(sid, max_in_flight=4) as st:
            assert st.hello["last_seq"] == -1 and st.hello["last_t"] is None
            futs = [
                st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2]) for it in ITEMS[:40]
            ]
            bad = st.send_odometry({"t": 0.0, "v": 0.0, "omega": 0.0})  # before the last input
            st.drain()
        assert [f.result(10)["seq"] for f in futs] == list(range(40))
        with pytest.raises(ServerError) as e:
            bad.result(10)
        assert e.value.status == 409 and "does not follow" in str(e.value.detail)
        assert c.wait_processed(sid)["inputs_stored"] == 40
        with pytest.raises(ServerError) as e:
            c.map("s_missing")
        assert e.value.status == 404
        c.delete_session(sid)
        with pytest.raises(ServerError) as e:
            c.stats(sid)
        assert e.value.status == 404
