"""Exports of a session's recorded inputs: ground truth as TUM, the inputs as a data folder or a
ROS 2 bag (zipped), so a run recorded by the service can be re-run offline with ``hippomap run``.

The writers live in the model package (:mod:`hippomap.session_export`); the routes here read
the stored inputs page by page (up to the last durable one when the export starts), write the
archive to a temporary file in a worker thread, stream it and delete it.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
from collections.abc import Iterator
from typing import Any

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from hippomap.errors import InputError
from hippomap.inputs import Odometry
from hippomap.session_export import (GROUNDTRUTH_TOPIC, IMAGE_TOPIC, ODOM_TOPIC, EncodedFrame, write_data_zip,
                                     write_rosbag2_zip)

from ..ingest import odometry_from_bytes
from ..sessions import LiveSession
from . import deps

router = APIRouter(tags=["exports"])

#: stored inputs read from the store at a time (a page of frames is the most an export holds in memory)
PAGE = 256


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
    rows = [(o.t, *o.gt) for o in stored_inputs(live, with_frames=False)
            if isinstance(o, Odometry) and o.gt is not None]
    if not rows:
        raise HTTPException(404, f"session {live.id} has no ground truth: none of its odometry readings "
                                 "carried 'gt' [x, y, theta]")
    arr = np.array(rows, dtype=float)
    return arr[:, 0], arr[:, 1:]


def _archive(live: LiveSession, kind: str) -> str:
    """Write the session's inputs as ``kind`` ('data' or 'rosbag2') into a temporary zip; its path."""
    fd, path = tempfile.mkstemp(prefix=f"hippomap-{live.id}-", suffix=".zip")
    try:
        with os.fdopen(fd, "wb") as fh:
            if kind == "data":
                write_data_zip(fh, stored_inputs(live), root=live.id, config=live.record.config or {})
            else:
                write_rosbag2_zip(fh, stored_inputs(live), root=live.id)
    except InputError as exc:
        os.unlink(path)
        raise HTTPException(409, f"session {live.id} cannot be exported: {exc}") from None
    except BaseException:
        os.unlink(path)
        raise
    return path


async def _zip_response(live: LiveSession, kind: str, filename: str) -> FileResponse:
    path = await asyncio.to_thread(_archive, live, kind)
    return FileResponse(path, media_type="application/zip", filename=filename,
                        background=BackgroundTask(os.unlink, path))


def _zip_doc() -> dict[int | str, dict[str, Any]]:
    return {200: {"content": {"application/zip": {}}, "description": "the zip file"},
            409: {"description": "nothing to export (no odometry), or a time a bag cannot hold"}, **deps.ERRORS}


@router.get("/export/data.zip", response_class=FileResponse, responses=_zip_doc(),
            summary="The session's recorded inputs as a data folder (zip) that `hippomap run` reads: frames/, "
                    "frames.csv, odometry.csv, groundtruth.csv when readings carried gt, config.json (overrides)")
async def export_data_zip(live: deps.ReadSession) -> FileResponse:
    return await _zip_response(live, "data", f"{live.id}-data.zip")


@router.get("/export/rosbag2.zip", response_class=FileResponse, responses=_zip_doc(),
            summary=f"The session's recorded inputs as a ROS 2 bag (zip): {IMAGE_TOPIC} "
                    f"(sensor_msgs/CompressedImage), {ODOM_TOPIC} (nav_msgs/Odometry), {GROUNDTRUTH_TOPIC} "
                    "(geometry_msgs/PoseStamped)")
async def export_rosbag2_zip(live: deps.ReadSession) -> FileResponse:
    return await _zip_response(live, "rosbag2", f"{live.id}-rosbag2.zip")
