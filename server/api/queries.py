"""Queries: the map and its downloads, loop closures, saccade traces, place fields, events, inputs
(and, through :mod:`server.api.exports`, the recorded inputs as a data folder or a ROS 2 bag)."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Path, Query, Request
from fastapi.responses import PlainTextResponse, Response

from hippomap import mapper_queries as mq

from ..formats import views
from ..formats.schemas import Event, LoopClosure, MapGraph, PlaceField, PlaceFieldInfo, RecognitionInfo
from ..runtime import model
from ..runtime.sessions import LiveSession
from . import deps, exports

router = APIRouter(prefix="/sessions/{session_id}", tags=["queries"])

#: the largest id, step or sequence number a query accepts: ids are 64-bit signed integers in the store
MAX_ID = 2**62
Limit = Annotated[int, Query(ge=1, le=10_000, description="most items returned")]
SinceId = Annotated[int, Query(ge=-1, le=MAX_ID, description="only items with a larger id (-1: from the start)")]
TMin = Annotated[float | None, Query(description="only items at or after this time", allow_inf_nan=False)]
TMax = Annotated[float | None, Query(description="only items at or before this time", allow_inf_nan=False)]


def _not_found(what: str) -> HTTPException:
    return HTTPException(404, f"{what} not found")


async def _query(live: LiveSession, query: mq.Query[Any]) -> Any:
    """The answer to a typed mapper query (None while the session is first restored)."""
    return await asyncio.to_thread(live.worker.query, query)


def _binary(media: str) -> dict[int | str, dict[str, Any]]:
    return {200: {"content": {media: {}}, "description": "the file"}, **deps.ERRORS}


# ---------------------------------------------------------------------- map
@router.get("/map", response_model=MapGraph, responses=deps.ERRORS, summary="The cognitive map: nodes and links")
async def get_map(live: deps.ReadSession) -> Any:
    arrays = await _query(live, mq.GraphArrays())
    return model.json_safe(model.graph(arrays)) if arrays is not None else {"nodes": [], "links": []}


async def _arrays(live: LiveSession) -> dict[str, Any]:
    arrays = await _query(live, mq.GraphArrays())
    if arrays is None:
        raise HTTPException(503, "the session is still loading")
    return arrays


@router.get(
    "/map.graphml", response_class=Response, responses=_binary("application/graphml+xml"), summary="The map as GraphML"
)
async def get_map_graphml(live: deps.ReadSession) -> Response:
    text = await asyncio.to_thread(views.graphml, await _arrays(live))
    return Response(
        text,
        media_type="application/graphml+xml",
        headers={"Content-Disposition": f'attachment; filename="{live.id}.graphml"'},
    )


@router.get(
    "/map.g2o",
    response_class=PlainTextResponse,
    responses=_binary("text/plain"),
    summary="The map as a g2o pose graph (VERTEX_SE2 / EDGE_SE2), each edge with the information the map "
    "gives its link (odometric: by length; loop: its information x robust weight)",
)
async def get_map_g2o(live: deps.ReadSession) -> Response:
    arrays = await _query(live, mq.GraphArrays(information=True))
    if arrays is None:
        raise HTTPException(503, "the session is still loading")
    text = await asyncio.to_thread(views.g2o, arrays)
    return PlainTextResponse(text, headers={"Content-Disposition": f'attachment; filename="{live.id}.g2o"'})


@router.get(
    "/trajectory.tum",
    response_class=PlainTextResponse,
    responses=_binary("text/plain"),
    summary="The robot's trajectory in TUM format: on the corrected map, raw odometry, or the ground truth "
    "its odometry readings carried (404 when none did)",
)
async def get_trajectory_tum(
    live: deps.ReadSession,
    source: Literal["map", "odometry", "groundtruth"] = Query("map", description="which trajectory"),
) -> Response:
    if source == "groundtruth":
        res = await asyncio.to_thread(exports.groundtruth, live)
    else:
        res = await _query(live, mq.Trajectory(source))
    text = "" if res is None else await asyncio.to_thread(views.tum, *res)
    return PlainTextResponse(text, headers={"Content-Disposition": f'attachment; filename="{live.id}-{source}.tum"'})


# ------------------------------------------------------------ loop closures
@router.get(
    "/loop-closures",
    response_model=list[LoopClosure],
    responses=deps.ERRORS,
    summary="Loop-closure decisions (accepted, rejected, pending) with links to their saccade traces",
)
async def get_loop_closures(
    live: deps.ReadSession,
    request: Request,
    since_id: SinceId = -1,
    t_min: TMin = None,
    t_max: TMax = None,
    limit: Limit = 1000,
    status: Literal["accepted", "rejected", "pending"] | None = None,
    used: Annotated[
        bool | None,
        Query(description="only closures the map uses (true) or does not use (false: faded, rejected, pending)"),
    ] = None,
) -> Any:
    report = await _query(live, mq.LoopDecisions())
    rows = model.loop_closures(report) if report is not None else []
    base = str(request.base_url).rstrip("/") + f"/sessions/{live.id}/saccades/"
    out = []
    for r in rows:
        if r["id"] <= since_id or (status and r["status"] != status) or (used is not None and r["used"] != used):
            continue
        if (t_min is not None and (r["t"] is None or r["t"] < t_min)) or (
            t_max is not None and (r["t"] is None or r["t"] > t_max)
        ):
            continue
        out.append({**r, "saccades": None if r["recognition"] is None else f"{base}{r['recognition']}"})
        if len(out) >= limit:
            break
    return out


@router.get(
    "/recognitions",
    response_model=list[RecognitionInfo],
    responses=deps.ERRORS,
    summary="Visual recognitions (one per checked key frame), newest last",
)
async def get_recognitions(
    live: deps.ReadSession, request: Request, since_id: SinceId = -1, limit: Limit = 1000
) -> Any:
    recs = model.json_safe(await _query(live, mq.Recognitions(since_id, limit)) or [])
    base = str(request.base_url).rstrip("/") + f"/sessions/{live.id}/saccades/"
    return [
        {
            "id": r["id"],
            "t": r.get("t"),
            "node": r.get("node"),
            "accepted": r.get("accepted"),
            "frame_id": r.get("frame_id"),
            "evidence": r.get("evidence"),
            "n_fixations": r.get("n_fixations"),
            "search": r.get("search"),
            "candidates": r.get("candidates"),
            "primed": r.get("primed"),
            "saccades": f"{base}{r['id']}",
            "image": f"{base}{r['id']}/image",
        }
        for r in recs
    ]


RecId = Annotated[int, Path(ge=0, le=MAX_ID, description="recognition id")]


@router.get(
    "/saccades/{recognition_id}",
    responses=deps.ERRORS,
    summary="A recognition's saccade trace: every fixation, prediction, outcome and the evidence after it",
)
async def get_saccades(live: deps.ReadSession, recognition_id: RecId) -> dict[str, Any]:
    rec = await _query(live, mq.RecognitionById(recognition_id))
    if rec is None:
        raise _not_found(f"recognition {recognition_id}")
    return model.json_safe(rec)


@router.get(
    "/saccades/{recognition_id}/image",
    response_class=Response,
    responses=_binary("image/jpeg"),
    summary="The query frame with the saccade trace drawn, as JPEG",
)
async def get_saccade_image(
    live: deps.ReadSession,
    recognition_id: RecId,
    attempt: str = Query("last", pattern=r"^(last|all|\d{1,4})$", description="'last', 'all' or an attempt number"),
) -> Response:
    rec = await _query(live, mq.RecognitionById(recognition_id))
    if rec is None:
        raise _not_found(f"recognition {recognition_id}")
    rec = model.json_safe(rec)
    frame = await asyncio.to_thread(live.store.frame_at, live.id, float(rec["t"]))
    if frame is None:
        raise _not_found(f"the frame of recognition {recognition_id}")
    att: Any = int(attempt) if attempt.isdigit() else attempt
    jpeg = await asyncio.to_thread(views.saccade_jpeg, frame.data, rec, att)
    return Response(jpeg, media_type="image/jpeg")


# ------------------------------------------------------------- place fields
def _pf_response(rec: Any, fmt: str, spatial: Any = None) -> Any:
    if fmt == "npy":
        return Response(
            views.place_field_npy(rec),
            media_type="application/octet-stream",
            headers={"Content-Disposition": f'attachment; filename="place-field-{rec.step}.npy"'},
        )
    if fmt == "png":
        return Response(views.place_field_png(rec, spatial), media_type="image/png")
    return views.place_field_json(rec)


def _last_field(live: LiveSession) -> Any:
    n = live.store.derived_counts(live.id)[1]  # the newest step with a field is n - 1
    return live.store.place_field(live.id, n - 1) if n else None


async def _current_field(live: LiveSession) -> Any:
    rec = await asyncio.to_thread(_last_field, live)
    if rec is None:
        raise _not_found("place field (no odometry step has produced one yet)")
    return rec


@router.get(
    "/place-field",
    response_model=PlaceField,
    responses=deps.ERRORS,
    summary="The current place field (sparse position matrix) with its place code",
)
async def get_place_field(live: deps.ReadSession) -> Any:
    return await asyncio.to_thread(_pf_response, await _current_field(live), "json")


@router.get(
    "/place-field/npy",
    response_class=Response,
    responses=_binary("application/octet-stream"),
    summary="The current position matrix POS as .npy (uint8 0/1, rows = y)",
)
async def get_place_field_npy(live: deps.ReadSession) -> Response:
    return await asyncio.to_thread(_pf_response, await _current_field(live), "npy")


@router.get(
    "/place-field/png",
    response_class=Response,
    responses=_binary("image/png"),
    summary="The current place field's iteration as PNG: the grid cells' binarised matrices and the "
    "position matrix shrinking to one field (the paper's Fig. 8), axes in metres",
)
async def get_place_field_png(live: deps.ReadSession) -> Response:
    return await asyncio.to_thread(_pf_response, await _current_field(live), "png", live.config.spatial)


@router.get(
    "/place-fields",
    response_model=list[PlaceFieldInfo],
    responses=deps.ERRORS,
    summary="Past place fields: one per odometry step that produced a field",
)
async def list_place_fields(live: deps.ReadSession, since_step: SinceId = -1, limit: Limit = 1000) -> Any:
    rows = await asyncio.to_thread(live.store.place_fields, live.id, since_step, limit, False)
    return [{"step": r.step, "seq": r.seq, "t": r.t} for r in rows]


Step = Annotated[int, Path(ge=0, le=MAX_ID, description="odometry step")]


async def _field(live: LiveSession, step: int) -> Any:
    rec = await asyncio.to_thread(live.store.place_field, live.id, step)
    if rec is None:
        raise _not_found(f"place field of step {step}")
    return rec


@router.get("/place-fields/{step}", response_model=PlaceField, responses=deps.ERRORS, summary="A past place field")
async def get_past_field(live: deps.ReadSession, step: Step) -> Any:
    return await asyncio.to_thread(_pf_response, await _field(live, step), "json")


@router.get(
    "/place-fields/{step}/npy",
    response_class=Response,
    responses=_binary("application/octet-stream"),
    summary="A past position matrix as .npy",
)
async def get_past_field_npy(live: deps.ReadSession, step: Step) -> Response:
    return await asyncio.to_thread(_pf_response, await _field(live, step), "npy")


@router.get(
    "/place-fields/{step}/png",
    response_class=Response,
    responses=_binary("image/png"),
    summary="A past place field's iteration as PNG (as /place-field/png)",
)
async def get_past_field_png(live: deps.ReadSession, step: Step) -> Response:
    return await asyncio.to_thread(_pf_response, await _field(live, step), "png", live.config.spatial)


# ------------------------------------------------------------ events, inputs
@router.get(
    "/events",
    response_model=list[Event],
    responses=deps.ERRORS,
    summary="Everything the mapper reported (nodes, links, recognitions, loop decisions...), in order",
)
async def get_events(
    live: deps.ReadSession,
    since_id: SinceId = -1,
    t_min: TMin = None,
    t_max: TMax = None,
    limit: Limit = 1000,
    type: Annotated[list[str] | None, Query(description="only these event types")] = None,
) -> Any:
    rows = await asyncio.to_thread(live.store.query_events, live.id, type, since_id, t_min, t_max, limit)
    return [{"id": e.id, "seq": e.seq, "type": e.type, "t": e.t, "data": e.data} for e in rows]


@router.get(
    "/inputs",
    responses=deps.ERRORS,
    summary="Stored inputs in order: seq, kind, t (and the odometry values); frames via /frames/{seq}",
)
async def get_inputs(live: deps.ReadSession, since_seq: SinceId = -1, limit: Limit = 1000) -> list[dict[str, Any]]:
    rows = await asyncio.to_thread(live.store.read_inputs, live.id, since_seq, limit, False)
    out = []
    for r in rows:
        item: dict[str, Any] = {"seq": r.seq, "kind": r.kind, "t": r.t}
        if r.kind == "odometry":
            item["odometry"] = json.loads(r.data)
        out.append(item)
    return out


@router.get(
    "/frames/{seq}",
    response_class=Response,
    responses=_binary("image/jpeg"),
    summary="A stored frame, exactly as it was received",
)
async def get_frame(
    live: deps.ReadSession, seq: Annotated[int, Path(ge=0, le=MAX_ID, description="sequence number of the input")]
) -> Response:
    rec = await asyncio.to_thread(live.store.input_by_seq, live.id, seq)
    if rec is None or rec.kind != "frame":
        raise _not_found(f"frame {seq}")
    media = "image/png" if rec.data[:4] == b"\x89PNG" else "image/jpeg"
    return Response(rec.data, media_type=media)


router.include_router(exports.router)  # /export/...: the recorded inputs as a data folder or a ROS 2 bag
