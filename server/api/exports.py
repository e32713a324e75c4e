"""Exports of a session's recorded inputs: ground truth as TUM, the inputs as a data folder or a
ROS 2 bag (zipped), so a run recorded by the service can be re-run offline with ``hippomap run``.

The writers live in the model package (:mod:`hippomap.io.session_export`); the routes here read
the stored inputs page by page (up to the last durable one when the export starts), write the
archive to an anonymous temporary file in a worker thread and stream it from there.
"""

from __future__ import annotations

import asyncio
import tempfile
from collections.abc import Iterator
from typing import IO, Any

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.responses import StreamingResponse

from hippomap.errors import InputError
from hippomap.inputs import Odometry
from hippomap.io.session_export import (
    GROUNDTRUTH_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
    EncodedFrame,
    write_data_zip,
    write_rosbag2_zip,
)

from ..formats.ingest import odometry_from_bytes
from ..runtime.sessions import LiveSession
from . import deps

router = APIRouter()  # included by the queries router: its operations are tagged "queries"

#: stored inputs read from the store at a time (a page of frames is the most an export holds in memory)
PAGE = 256
#: bytes of the archive sent at a time
CHUNK = 1 << 20


def stored_inputs(live: LiveSession, with_frames: bool = True) -> Iterator[Odometry | EncodedFrame]:
    """The session's stored inputs in order, up to the last durable one now (call from a thread).
    Without ``with_frames`` only the odometry is read (the store leaves the images out)."""
    last, after = live.stored_seq, -1
    while after < last:
        rows = live.store.read_inputs(live.id, after, min(PAGE, last - after), with_frames)
        if not rows:
            return
        for r in rows:
            if r.seq > last:
                return
            if r.kind == "odometry":
                yield odometry_from_bytes(r.data)
            elif with_frames:
                yield EncodedFrame(r.t, r.data)
        after = rows[-1].seq


def groundtruth(live: LiveSession) -> tuple[np.ndarray, np.ndarray]:
    """``(times, (N, 3) poses)`` of the ground truth the session's readings carried (``gt``);
    HTTPException 404 naming the problem when none did."""
    rows = [
        (o.t, *o.gt) for o in stored_inputs(live, with_frames=False) if isinstance(o, Odometry) and o.gt is not None
    ]
    if not rows:
        raise HTTPException(
            404, f"session {live.id} has no ground truth: none of its odometry readings carried 'gt' [x, y, theta]"
        )
    arr = np.array(rows, dtype=float)
    return arr[:, 0], arr[:, 1:]


def _archive(live: LiveSession, kind: str) -> tuple[IO[bytes], int]:
    """Write the session's inputs as ``kind`` ('data' or 'rosbag2') into an anonymous temporary
    file (gone once closed, whatever happens to the download); the file, rewound, and its size."""
    fh = tempfile.TemporaryFile(prefix=f"hippomap-{live.id}-", suffix=".zip")
    try:
        if kind == "data":
            write_data_zip(fh, stored_inputs(live), root=live.id, config=live.record.config or {})
        else:
            write_rosbag2_zip(fh, stored_inputs(live), root=live.id)
        size = fh.tell()
        fh.seek(0)
    except InputError as exc:
        fh.close()
        raise HTTPException(409, f"session {live.id} cannot be exported: {exc}") from None
    except BaseException:
        fh.close()
        raise
    return fh, size


def _chunks(fh: IO[bytes]) -> Iterator[bytes]:
    try:
        while chunk := fh.read(CHUNK):
            yield chunk
    finally:
        fh.close()


async def _zip_response(live: LiveSession, kind: str, filename: str) -> StreamingResponse:
    fh, size = await asyncio.to_thread(_archive, live, kind)
    return StreamingResponse(
        _chunks(fh),
        media_type="application/zip",  # a sync iterator: read in a thread
        headers={"Content-Disposition": f'attachment; filename="{filename}"', "Content-Length": str(size)},
    )


def _zip_doc() -> dict[int | str, dict[str, Any]]:
    return {
        200: {"content": {"application/zip": {}}, "description": "the zip file"},
        409: {"description": "nothing to export (no odometry), or a time a bag cannot hold"},
        **deps.ERRORS,
    }


@router.get(
    "/export/data.zip",
    response_class=StreamingResponse,
    responses=_zip_doc(),
    summary="The session's recorded inputs as a data folder (zip) that `hippomap run` reads: frames/, "
    "frames.csv, odometry.csv, groundtruth.csv when readings carried gt, config.json (overrides)",
)
async def export_data_zip(live: deps.ReadSession) -> StreamingResponse:
    return await _zip_response(live, "data", f"{live.id}-data.zip")


@router.get(
    "/export/rosbag2.zip",
    response_class=StreamingResponse,
    responses=_zip_doc(),
    summary=f"The session's recorded inputs as a ROS 2 bag (zip): {IMAGE_TOPIC} "
    f"(sensor_msgs/CompressedImage), {ODOM_TOPIC} (nav_msgs/Odometry), {GROUNDTRUTH_TOPIC} "
    "(geometry_msgs/PoseStamped)",
)
async def export_rosbag2_zip(live: deps.ReadSession) -> StreamingResponse:
    return await _zip_response(live, "rosbag2", f"{live.id}-rosbag2.zip")
