"""What a session fed some inputs must report, and what it does report, in the same shape.

:func:`offline_reference` runs the same mapper in-process through the service's own queries
and converters; :func:`session_state` asks a live server (through the Python client). The service
tests compare the two.
"""

from __future__ import annotations

from typing import Any

from .synthetic import decoded


def offline_reference(items: tuple, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a session fed ``items`` must report: the same mapper run in-process, through the
    server's own query functions and a JSON round trip (as a client sees it)."""
    import json

    from hippomap.inputs import Odometry as _Odo
    from server.runtime import model

    m = model.new_mapper(model.effective_config(overrides))
    for value in decoded(items):
        (m.step if isinstance(value, _Odo) else m.observe)(value)
    q = model.queries
    out = {
        "map": model.graph(m.answer(q.GraphArrays())),
        "stats": m.answer(q.Stats()),
        "loop_closures": [r["decision"] for r in model.loop_closures(m.answer(q.LoopDecisions()))],
        "loop_weights": [[r["weight"], r["used"]] for r in model.loop_closures(m.answer(q.LoopDecisions()))],
        "recognitions": m.answer(q.Recognitions(-1, 10**9)),
    }
    return json.loads(json.dumps(model.json_safe(out)))


def session_state(client: Any, session_id: str) -> dict[str, Any]:
    """The same things, as the server reports them (after it has processed everything)."""
    client.wait_processed(session_id)
    loops = client.loop_closures(session_id, limit=10_000)
    return {
        "map": client.map(session_id),
        "stats": client.stats(session_id)["mapper"],
        "loop_closures": [r["decision"] for r in loops],
        "loop_weights": [[r["weight"], r["used"]] for r in loops],
        "recognitions": [client.saccades(session_id, r["id"]) for r in client.recognitions(session_id, limit=10_000)],
    }
