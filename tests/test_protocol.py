"""The binary frame message: one format (hippomap.protocol) that the client packs and the service parses.

The client (``hippomap.client``, which must not import the service) and the service
(``server.formats.protocol``) both take the format from :mod:`hippomap.protocol`. These tests feed what the
client packs to the service's parser, directly and over the service's websocket stream (in-process,
TestClient), and check that a message with a bad magic or a short header is refused with the
error naming the problem.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

import hippomap.client as client
import hippomap.protocol as protocol
import server.formats.protocol as server_protocol
from hippomap.errors import InputError
from server.app import create_app
from server.settings import ServerSettings

TOKEN = "hm_protocol_admin_token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL = {"spatial": {"resolution_m": 0.004}}  # small grid-cell tables: the session is built in milliseconds


def _jpeg(seed: int = 0, w: int = 160, h: int = 120) -> bytes:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (5, 5), 2)
    return cv2.imencode(".jpg", img)[1].tobytes()


def test_client_and_service_share_one_definition():
    """Neither end keeps a copy of the format: both use hippomap.protocol's functions and constants."""
    assert client.pack_frame is protocol.pack_frame
    assert server_protocol.pack_frame is protocol.pack_frame
    assert server_protocol.unpack_frame is protocol.unpack_frame
    assert server_protocol.FRAME_MAGIC is protocol.FRAME_MAGIC == b"HMF1"
    assert server_protocol.FRAME_HEADER is protocol.FRAME_HEADER
    assert protocol.FRAME_HEADER.size == 16 and protocol.FRAME_HEADER.format == "<4sId"
    assert not hasattr(client, "FRAME_MAGIC")  # the client's former copy is gone


@pytest.mark.parametrize("message_id,t", [(0, 0.0), (77, 12.5), (2**32 - 1, 1e9), (2**32 + 5, -3.25)])
def test_client_packed_frame_is_parsed_by_the_service(message_id, t):
    image = _jpeg(message_id % 7)
    data = client.pack_frame(message_id, t, image)
    assert data[:4] == b"HMF1" and len(data) == 16 + len(image)
    assert server_protocol.unpack_frame(data) == (message_id & 0xFFFFFFFF, t, image)


def test_bad_magic_and_short_header_are_refused_naming_the_problem():
    data = client.pack_frame(3, 1.0, b"\xff\xd8\xffjpeg")
    with pytest.raises(InputError, match=r"does not start with the frame magic b'HMF1' \(got b'HMF2'\)"):
        server_protocol.unpack_frame(b"HMF2" + data[4:])
    with pytest.raises(InputError, match="binary message of 15 bytes is shorter than the 16-byte frame header"):
        server_protocol.unpack_frame(data[:15])


def test_client_frames_over_the_service_stream(tmp_path):
    """Over the real websocket endpoint: the client's frame is acknowledged and stored at its time; the
    same frame with a bad magic gets a 422 error naming the magic, and the stream stays open."""
    app = create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=TOKEN))
    image = _jpeg(1)
    with TestClient(app) as c:
        r = c.post("/sessions", json={"name": "protocol", "config": SMALL}, headers=AUTH)
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
            assert json.loads(ws.receive_text())["type"] == "hello"
            ws.send_bytes(b"XXXX" + client.pack_frame(8, 0.75, image)[4:])
            reply = json.loads(ws.receive_text())
            assert reply["type"] == "error" and reply["status"] == 422, reply
            assert "frame magic b'HMF1'" in reply["detail"] and "b'XXXX'" in reply["detail"], reply
            ws.send_bytes(client.pack_frame(9, 0.5, image))
            reply = json.loads(ws.receive_text())
            assert reply["type"] == "ack" and reply["id"] == 9, reply
        stats = c.get(f"/sessions/{sid}/stats", headers=AUTH).json()
        assert stats["last_frame_t"] == 0.5 and stats["inputs_stored"] == 1, stats
