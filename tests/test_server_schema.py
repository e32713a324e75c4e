"""Schemathesis over the server's OpenAPI document, with ALL its checks: generated requests
(valid and invalid) against every operation of a live server must get no 5xx, only documented
status codes, content types and headers, responses matching their schemas, invalid requests
rejected, valid ones accepted, and ``405`` answers whose ``Allow`` names every method of the path.

Bounded in time: a fixed seed and few examples per operation (about a minute in all). The
``session_id`` path parameter is pinned to a real session that holds data, so the generated
requests reach the handlers instead of stopping at 404. Two operations are told what OpenAPI
cannot say about them:

* ``POST /sessions`` is fuzzed with invalid bodies only: every valid one would build a mapper
  (grid-cell tables of up to hundreds of MB, see the config quotas), which the service tests do;
* ``POST /sessions/{id}/frames`` may answer 422 to a body that is schema-valid (any bytes of an
  image type): whether it decodes to an image of a usable size is beyond the schema; it and
  ``POST /sessions/{id}/odometry`` also answer 422 to a timestamp more than ``max_time_jump_s``
  after the session's newest input, a bound relative to the session's clock (the schema states the
  absolute ones: ``|t|``, speeds, turn rates, increments).
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys

from tests.support.live import LiveServer, stream_items
from tests.support.synthetic import synthetic_inputs

# what a valid request may be answered besides 2xx/3xx (schemathesis's default list) -- plus 422 for frames
ACCEPTED = [200, 201, 204, 401, 403, 404, 409, 429]


def _config(token: str, sid: str) -> str:
    return (
        f'headers = {{ Authorization = "Bearer {token}" }}\n'
        "generation.max-examples = 6\n"
        f'[parameters]\n"path.session_id" = "{sid}"\n'
        # the place-field figures take seconds each: fewer examples keep the run about a minute
        '[[operations]]\ninclude-path-regex = "/png$"\ngeneration.max-examples = 2\n'
        '[[operations]]\ninclude-name = "POST /sessions"\ngeneration.mode = "negative"\n'
        "[[operations]]\n"
        'include-name = ["POST /sessions/{session_id}/frames", "POST /sessions/{session_id}/odometry"]\n'
        f"checks.positive_data_acceptance.expected-statuses = {ACCEPTED + [422]}\n"
    )


def test_schemathesis_all_checks_find_nothing(tmp_path):
    # generous read budget: the fuzzer's requests must reach the handlers, not the rate limit
    srv = LiveServer(
        tmp_path / "data", env={"HIPPOMAP_READ_RATE_PER_S": "5000", "HIPPOMAP_READ_RATE_BURST": "5000"}
    ).start()
    try:
        with srv.client() as c:
            sid = c.create_session("fuzzed", {"mapper": {"keyframe_interval": 5}})["id"]
            asyncio.run(stream_items(srv.url, srv.token, sid, synthetic_inputs(n_odometry=120, frame_every=3)))
            c.wait_processed(sid)
        cfg = tmp_path / "schemathesis.toml"
        cfg.write_text(_config(srv.token, sid))
        cmd = [
            sys.executable,
            "-m",
            "schemathesis.cli",
            "--config-file",
            str(cfg),
            "run",
            f"{srv.url}/openapi.json",
            "--checks",
            "all",
            "--seed",
            "1",
            "--workers",
            "1",
            "--phases",
            "examples,coverage,fuzzing",
            "--request-timeout",
            "20",
            "--no-shrink",
        ]
        # everything but DELETE first (a DELETE would remove the pinned session), then DELETE alone
        for selector in (["--exclude-method", "DELETE"], ["--include-method", "DELETE"]):
            proc = subprocess.run(cmd + selector, capture_output=True, text=True, timeout=240, cwd=tmp_path)
            out = proc.stdout + proc.stderr
            assert proc.returncode == 0, out[-8000:]
            cases = re.search(r"(\d+) generated, (\d+) passed", out)
            assert cases and int(cases.group(1)) == int(cases.group(2)) > 0, out[-3000:]
            tested = int(re.search(r"Tested: (\d+)", out).group(1))
            assert tested >= (20 if selector[0] == "--exclude-method" else 2), out[-3000:]
            if selector[0] == "--exclude-method":  # the session is intact after the fuzzing
                with srv.client() as c:
                    st = c.stats(sid)
                    assert st["error"] is None and st["inputs_stored"] >= 120
    finally:
        srv.stop()
    assert not any("Traceback" in line for line in srv.output), "".join(srv.output)[-4000:]
