"""Serialisers of query answers: map downloads, place fields, saccade images.

Pure functions from the plain data of :mod:`server.runtime.model` to bytes or text; they run in
worker threads (never on the event loop) because some encode images.
"""

from __future__ import annotations

import io
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime import model
from .images import encode_jpeg, encode_png


def graphml(arrays: dict[str, np.ndarray]) -> str:
    """The map as GraphML (networkx writer): node pose/place code/frame/time, link transform/kind.
    A value that is not a finite number (e.g. the place code of a node made before the first
    odometry step) is left out of that node: GraphML's "no data", never ``nan``."""
    import networkx as nx

    g = nx.MultiDiGraph()
    for i, (p, c, f, t) in enumerate(zip(arrays["poses"], arrays["place_codes"], arrays["frames"], arrays["times"])):
        attrs = {
            "x": float(p[0]),
            "y": float(p[1]),
            "theta": float(p[2]),
            "place_x": float(c[0]),
            "place_y": float(c[1]),
            "place_theta": float(c[2]),
            "frame": int(f),
            "t": float(t),
        }
        g.add_node(i, **{k: v for k, v in attrs.items() if not isinstance(v, float) or math.isfinite(v)})
    for a, b, tr, kind in zip(arrays["source"], arrays["target"], arrays["transform"], arrays["kind"]):
        g.add_edge(int(a), int(b), dx=float(tr[0]), dy=float(tr[1]), dtheta=float(tr[2]), kind=str(kind))
    return "\n".join(nx.generate_graphml(g)) + "\n"


def g2o(arrays: dict[str, np.ndarray]) -> str:
    """The map as g2o VERTEX_SE2/EDGE_SE2 lines (``hippomap.io.exports.write_g2o``), each edge with
    ``arrays["information"]`` (M, 3) when given (``hippomap.io.exports.link_information``, with the
    links' ``arrays["coupling"]``), else unit."""
    from hippomap.io.exports import write_g2o

    info, coupling = arrays.get("information"), arrays.get("coupling")
    with tempfile.TemporaryDirectory() as tmp:
        path = write_g2o(
            Path(tmp) / "map.g2o",
            arrays["poses"].reshape(-1, 3),
            arrays["source"],
            arrays["target"],
            arrays["transform"].reshape(-1, 3),
            None if info is None else np.asarray(info).reshape(-1, 3),
            None if coupling is None or info is None else np.asarray(coupling).reshape(-1),
        )
        return path.read_text()


def tum(times: np.ndarray, poses: np.ndarray) -> str:
    """A trajectory as a TUM file (``hippomap.io.exports.write_tum``, evo's writer)."""
    from hippomap.io.exports import write_tum

    if len(times) == 0:
        return ""
    with tempfile.TemporaryDirectory() as tmp:
        return write_tum(Path(tmp) / "trajectory.tum", times, poses).read_text()


def place_field_json(rec: Any) -> dict[str, Any]:
    meta, idx = model.place_field_from_blob(rec.data)
    return {"step": rec.step, "seq": rec.seq, "t": rec.t, **meta, "indices": idx.tolist()}


def place_field_npy(rec: Any) -> bytes:
    """The dense position matrix POS as a .npy file (uint8 0/1, rows = y)."""
    meta, idx = model.place_field_from_blob(rec.data)
    buf = io.BytesIO()
    np.save(buf, model.place_field_dense(meta, idx), allow_pickle=False)
    return buf.getvalue()


def place_field_png(rec: Any, spatial: Any = None) -> bytes:
    """The place cells' iteration that formed the field, drawn like the paper's Fig. 8
    (:mod:`hippomap.viz.place_field_figure`), given the session's ``SpatialConfig``; without it, the
    position matrix alone (white = field, y up like the map)."""
    meta, idx = model.place_field_from_blob(rec.data)
    if spatial is not None:
        from hippomap.grid_cells import GridCells
        from hippomap.iteration_record import record_stored_field
        from hippomap.viz.place_field_figure import place_field_png as figure_png

        record = record_stored_field(GridCells(spatial).tables, spatial, idx)
        x, y, _ = meta.get("place_code", (0.0, 0.0, 0.0))
        title = (
            f"Place field of odometry step {rec.step} (t = {rec.t:.2f} s): place code ({x:.3f}, {y:.3f}) m"
            " — grid-cell windows multiplied until one field remains (Eq. 9-10, Fig. 8)"
        )
        return figure_png(record, title=title)
    return encode_png(np.flipud(model.place_field_dense(meta, idx)) * np.uint8(255))


def saccade_jpeg(frame_bytes: bytes, rec: dict[str, Any], attempt: Any = "last") -> bytes:
    """The query frame with its saccade trace drawn (the model's ``draw_trace``), as JPEG."""
    import cv2

    from hippomap.inputs import decode_jpeg

    img = cv2.imdecode(np.frombuffer(frame_bytes, np.uint8), cv2.IMREAD_COLOR)
    if img is None:  # stored frames were validated, but be safe
        img = decode_jpeg(frame_bytes)
    return encode_jpeg(model.draw_saccades(img, rec, attempt))
