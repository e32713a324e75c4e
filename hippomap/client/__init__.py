"""Python client of the hippomap server (``hippomap serve``): HTTP via httpx, streaming via websockets.

    from hippomap.client import Client, Odometry
    with Client("http://127.0.0.1:8000", token="hm_...") as c:     # or $HIPPOMAP_TOKEN
        s = c.create_session(name="lab", config={"mapper": {"keyframe_interval": 10}})
        c.send_odometry(s["id"], [Odometry(0.1, v=0.2, omega=0.0)])
        c.send_frame(s["id"], 0.15, jpeg_bytes)                    # or a uint8 image array
        with c.stream(s["id"]) as st:                              # websocket, pipelined
            st.send_odometry(Odometry(0.2, v=0.2, omega=0.0))      # -> Future of the ack
            st.send_frame(0.25, jpeg_bytes)
            st.drain()                                             # every ack received
        c.wait_processed(s["id"]); print(c.map(s["id"]))

The token defaults to ``$HIPPOMAP_TOKEN``, then to the admin token a local ``hippomap serve``
saved in ``./hippomap-data/admin.token``. An acknowledgement means the input is stored
durably on the server. A rejected input raises
:class:`ServerError` with the server's status and message. The web libraries (httpx,
websockets: ``pip install 'hippomap[client]'``) are imported lazily, so ``import hippomap`` never
pulls them in, and a missing one raises :class:`~hippomap.extras.MissingExtraError` naming the extra.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import threading
import time
from concurrent.futures import Future
from typing import Any, Iterable

import numpy as np

from ..errors import HippomapError
from ..extras import requires
from ..inputs import Odometry
from ..protocol import pack_frame  # the frame format the server unpacks (one definition)

#: the client's public names: ``from hippomap.client import Client, Odometry`` is all a robot needs
__all__ = ["AsyncStream", "Client", "Odometry", "ServerError", "Stream", "default_token", "encode_image"]


class ServerError(HippomapError):
    """The server refused a request or an input: ``status`` is the HTTP status code."""

    def __init__(self, status: int, detail: Any) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail


def odometry_reading(o: Odometry | dict[str, Any]) -> dict[str, Any]:
    """The JSON form of one odometry reading."""
    if isinstance(o, dict):
        return o
    d: dict[str, Any] = (
        {"t": o.t, "increment": list(o.increment)}
        if o.increment is not None
        else {"t": o.t, "v": o.v, "omega": o.omega}
    )
    gt = getattr(o, "gt", None)
    if gt is not None:
        d["gt"] = list(gt)
    return d


def encode_image(image: bytes | np.ndarray, quality: int = 90) -> bytes:
    """Bytes pass through; a uint8 image array is JPEG-encoded."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        return bytes(image)
    import cv2

    ok, buf = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise HippomapError("could not JPEG-encode the image")
    return buf.tobytes()


def default_token() -> str | None:
    """``$HIPPOMAP_TOKEN``, else the admin token a local ``hippomap serve`` saved in its data
    folder (``$HIPPOMAP_DATA_DIR`` or ``./hippomap-data``), else None."""
    from pathlib import Path

    token = os.environ.get("HIPPOMAP_TOKEN")
    if token:
        return token
    path = Path(os.environ.get("HIPPOMAP_DATA_DIR") or "hippomap-data") / "admin.token"
    try:
        return path.read_text().strip() or None
    except OSError:
        return None


def _ws_url(base: str, session_id: str) -> str:
    base = base.rstrip("/")
    if base.startswith("https://"):
        base = "wss://" + base[len("https://") :]
    elif base.startswith("http://"):
        base = "ws://" + base[len("http://") :]
    return f"{base}/sessions/{session_id}/stream"


def _detail(resp: Any) -> Any:
    try:
        return resp.json().get("detail", resp.text)
    except (ValueError, AttributeError):
        return resp.text


class Client:
    """Synchronous HTTP client; :meth:`stream` opens a websocket stream."""

    def __init__(self, url: str, token: str | None = None, timeout: float = 30.0) -> None:
        with requires("client", "the HTTP client"):
            import httpx

        self.url = url.rstrip("/")
        self.token = token or default_token()
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        self._http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _req(self, method: str, path: str, **kw: Any) -> Any:
        resp = self._http.request(method, path, **kw)
        if resp.status_code >= 400:
            raise ServerError(resp.status_code, _detail(resp))
        return resp

    def _json(self, method: str, path: str, body: Any = None, **kw: Any) -> Any:
        if body is not None:  # json.dumps keeps NaN/Infinity, so the server (not httpx) judges them
            kw["content"] = json.dumps(body).encode()
            kw["headers"] = {**kw.get("headers", {}), "Content-Type": "application/json"}
        return self._req(method, path, **kw).json()

    @staticmethod
    def _params(**kw: Any) -> dict[str, Any]:
        return {k: v for k, v in kw.items() if v is not None}

    # ------------------------------------------------------------ sessions
    def health(self) -> dict[str, Any]:
        return self._json("GET", "/health")

    def create_session(self, name: str = "", config: dict[str, Any] | None = None) -> dict[str, Any]:
        return self._json("POST", "/sessions", {"name": name, "config": config or {}})

    def sessions(self) -> list[dict[str, Any]]:
        return self._json("GET", "/sessions")

    def session(self, session_id: str) -> dict[str, Any]:
        return self._json("GET", f"/sessions/{session_id}")

    def delete_session(self, session_id: str) -> None:
        self._req("DELETE", f"/sessions/{session_id}")

    def stats(self, session_id: str) -> dict[str, Any]:
        return self._json("GET", f"/sessions/{session_id}/stats")

    def wait_processed(self, session_id: str, timeout: float = 120.0, poll: float = 0.05) -> dict[str, Any]:
        """Block until the mapper has consumed every stored input; returns the stats."""
        deadline = time.monotonic() + timeout
        while True:
            st = self.stats(session_id)
            if st.get("error"):
                raise ServerError(503, st["error"])
            if not st["replaying"] and st["processed_seq"] >= st["last_seq"]:
                return st
            if time.monotonic() > deadline:
                raise TimeoutError(f"session {session_id}: processed {st['processed_seq']} of {st['last_seq']}")
            time.sleep(poll)

    # -------------------------------------------------------------- ingest
    def send_odometry(self, session_id: str, readings: Odometry | dict | Iterable[Odometry | dict]) -> dict[str, Any]:
        """Store one reading or a batch; returns the ack (``seq``..``last_seq``)."""
        if isinstance(readings, (Odometry, dict)):
            readings = [readings]
        return self._json(
            "POST", f"/sessions/{session_id}/odometry", {"readings": [odometry_reading(r) for r in readings]}
        )

    def send_frame(
        self, session_id: str, t: float, image: bytes | np.ndarray, multipart: bool = False
    ) -> dict[str, Any]:
        """Store one frame (JPEG/PNG bytes, or an image array encoded here)."""
        data = encode_image(image)
        if multipart:
            return self._json(
                "POST",
                f"/sessions/{session_id}/frames",
                data={"t": repr(float(t))},
                files={"image": ("frame.jpg", data, "image/jpeg")},
            )
        ctype = "image/png" if data[:4] == b"\x89PNG" else "image/jpeg"
        return self._json(
            "POST",
            f"/sessions/{session_id}/frames",
            params={"t": repr(float(t))},
            content=data,
            headers={"Content-Type": ctype},
        )

    def stream(self, session_id: str, max_in_flight: int = 128) -> "Stream":
        return Stream(self.url, self.token, session_id, max_in_flight)

    # ------------------------------------------------------------- queries
    def map(self, session_id: str) -> dict[str, Any]:
        return self._json("GET", f"/sessions/{session_id}/map")

    def map_graphml(self, session_id: str) -> str:
        return self._req("GET", f"/sessions/{session_id}/map.graphml").text

    def map_g2o(self, session_id: str) -> str:
        return self._req("GET", f"/sessions/{session_id}/map.g2o").text

    def trajectory_tum(self, session_id: str, source: str = "map") -> str:
        return self._req("GET", f"/sessions/{session_id}/trajectory.tum", params={"source": source}).text

    def loop_closures(
        self,
        session_id: str,
        since_id: int = -1,
        t_min: float | None = None,
        t_max: float | None = None,
        status: str | None = None,
        limit: int = 1000,
        used: bool | None = None,
    ) -> list[dict[str, Any]]:
        """Loop decisions with an id above ``since_id``, oldest first; ``status`` ('accepted', 'rejected',
        'pending') and ``used`` (the map applies it: accepted and not faded by the robust kernel) filter
        them. Each row holds its link's robust ``weight`` now."""
        return self._json(
            "GET",
            f"/sessions/{session_id}/loop-closures",
            params=self._params(since_id=since_id, t_min=t_min, t_max=t_max, status=status, limit=limit, used=used),
        )

    def recognitions(self, session_id: str, since_id: int = -1, limit: int = 1000) -> list[dict[str, Any]]:
        return self._json("GET", f"/sessions/{session_id}/recognitions", params={"since_id": since_id, "limit": limit})

    def saccades(self, session_id: str, recognition_id: int) -> dict[str, Any]:
        return self._json("GET", f"/sessions/{session_id}/saccades/{recognition_id}")

    def saccade_image(self, session_id: str, recognition_id: int, attempt: str | int = "last") -> bytes:
        return self._req(
            "GET", f"/sessions/{session_id}/saccades/{recognition_id}/image", params={"attempt": str(attempt)}
        ).content

    def place_field(self, session_id: str, step: int | None = None, fmt: str = "json") -> Any:
        """The current (``step=None``) or a past place field: ``fmt`` json -> dict, npy -> array, png -> bytes."""
        path = f"/sessions/{session_id}/place-field" if step is None else f"/sessions/{session_id}/place-fields/{step}"
        if fmt == "json":
            return self._json("GET", path)
        content = self._req("GET", f"{path}/{fmt}").content
        if fmt == "npy":
            import io

            return np.load(io.BytesIO(content), allow_pickle=False)
        return content

    def place_fields(self, session_id: str, since_step: int = -1, limit: int = 1000) -> list[dict[str, Any]]:
        return self._json(
            "GET", f"/sessions/{session_id}/place-fields", params={"since_step": since_step, "limit": limit}
        )

    def events(
        self, session_id: str, since_id: int = -1, types: list[str] | None = None, limit: int = 1000
    ) -> list[dict[str, Any]]:
        return self._json(
            "GET", f"/sessions/{session_id}/events", params=self._params(since_id=since_id, type=types, limit=limit)
        )

    def inputs(self, session_id: str, since_seq: int = -1, limit: int = 10_000) -> list[dict[str, Any]]:
        return self._json("GET", f"/sessions/{session_id}/inputs", params={"since_seq": since_seq, "limit": limit})

    def all_inputs(self, session_id: str) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        while True:
            page = self.inputs(session_id, out[-1]["seq"] if out else -1)
            if not page:
                return out
            out += page

    def frame(self, session_id: str, seq: int) -> bytes:
        return self._req("GET", f"/sessions/{session_id}/frames/{seq}").content

    # ------------------------------------------------------------- exports
    def groundtruth_tum(self, session_id: str) -> str:
        """The ground truth the session's readings carried, as TUM (ServerError 404 without any)."""
        return self.trajectory_tum(session_id, "groundtruth")

    def _download(self, path: str, target: Any) -> Any:
        """Stream a download into the file ``target`` (written only once the answer is a success)."""
        from pathlib import Path

        with self._http.stream("GET", path) as resp:
            if resp.status_code >= 400:
                resp.read()
                raise ServerError(resp.status_code, _detail(resp))
            target = Path(target)
            with target.open("wb") as fh:
                for chunk in resp.iter_bytes(1 << 20):
                    fh.write(chunk)
        return target

    def export_data_zip(self, session_id: str, target: Any) -> Any:
        """Save the session's recorded inputs as a zipped data folder (``hippomap run`` reads the
        unzipped folder, named after the session) to ``target``; returns its path."""
        return self._download(f"/sessions/{session_id}/export/data.zip", target)

    def export_rosbag2_zip(self, session_id: str, target: Any) -> Any:
        """Save the session's recorded inputs as a zipped ROS 2 bag (topics in
        :mod:`hippomap.io.session_export`) to ``target``; returns its path."""
        return self._download(f"/sessions/{session_id}/export/rosbag2.zip", target)

    # -------------------------------------------------------------- tokens
    def create_token(self, role: str = "viewer", session: str | None = None, label: str = "") -> dict[str, Any]:
        return self._json("POST", "/tokens", {"role": role, "session": session, "label": label})

    def tokens(self) -> list[dict[str, Any]]:
        return self._json("GET", "/tokens")

    def delete_token(self, token_id: str) -> None:
        self._req("DELETE", f"/tokens/{token_id}")


class AsyncStream:
    """A websocket stream into one session (asyncio). Messages are pipelined: each ``send_*``
    returns a future of its ack at once, and at most ``max_in_flight`` messages wait for acks."""

    def __init__(self, url: str, token: str | None, session_id: str, max_in_flight: int = 128) -> None:
        self.url = _ws_url(url, session_id)
        self.token = token or default_token()
        self.session_id = session_id
        self.max_in_flight = max_in_flight
        self.hello: dict[str, Any] = {}
        self.busy_notices = 0
        self._ids = itertools.count(1)
        self._waiting: dict[int, tuple[asyncio.Future, float]] = {}
        self._window = asyncio.Semaphore(max_in_flight)
        self._ws: Any = None
        self._reader: asyncio.Task | None = None
        self._closed_error: BaseException | None = None

    async def connect(self) -> "AsyncStream":
        with requires("client", "the websocket stream"):
            from websockets.asyncio.client import connect

        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        self._ws = await connect(self.url, additional_headers=headers, max_size=None, compression=None)
        first = json.loads(await self._ws.recv())
        if first.get("type") != "hello":
            raise ServerError(500, f"unexpected first message {first!r}")
        self.hello = first
        self._reader = asyncio.create_task(self._read())
        return self

    async def __aenter__(self) -> "AsyncStream":
        return await self.connect()

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    async def _read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for raw in self._ws:
                msg = json.loads(raw)
                kind = msg.get("type")
                if kind == "busy":
                    self.busy_notices += 1
                    continue
                entry = self._waiting.pop(msg.get("id"), None)
                if entry is None:
                    continue
                fut, sent = entry
                if not fut.done():
                    if kind == "error":
                        fut.set_exception(ServerError(msg.get("status", 400), msg.get("detail")))
                    else:
                        msg["latency_s"] = time.perf_counter() - sent
                        fut.set_result(msg)
                self._window.release()
        except ConnectionClosed as exc:
            self._closed_error = exc
        finally:
            err = ServerError(499, f"stream closed before the acknowledgement ({self._closed_error or 'closed'})")
            if self._ws is not None and self._ws.close_code not in (None, 1000, 1001):
                err = ServerError(int(self._ws.close_code), self._ws.close_reason or "stream closed")
            for fut, _ in self._waiting.values():
                if not fut.done():
                    fut.set_exception(err)
                self._window.release()  # wake a sender blocked on the window: it will see the stream closed
            self._waiting.clear()

    async def _send(self, payload: str | bytes, mid: int) -> asyncio.Future:
        assert self._ws is not None, "connect() first"
        await self._window.acquire()
        if self._reader is not None and self._reader.done():
            self._window.release()
            raise ServerError(499, "stream is closed")
        fut = asyncio.get_running_loop().create_future()
        self._waiting[mid] = (fut, time.perf_counter())
        try:
            await self._ws.send(payload)
        except Exception as exc:  # the connection is gone
            if self._waiting.pop(mid, None) is not None:
                self._window.release()
            raise ServerError(499, f"stream closed: {exc}") from exc
        return fut

    async def send_odometry(self, readings: Odometry | dict | Iterable[Odometry | dict]) -> asyncio.Future:
        """Send one reading or a batch (one message); returns the future of its ack."""
        mid = next(self._ids)
        if isinstance(readings, (Odometry, dict)):
            body: dict[str, Any] = {"type": "odometry", "id": mid, **odometry_reading(readings)}
        else:
            body = {"type": "odometry", "id": mid, "readings": [odometry_reading(r) for r in readings]}
        return await self._send(json.dumps(body), mid)

    async def send_frame(self, t: float, image: bytes | np.ndarray) -> asyncio.Future:
        mid = next(self._ids) & 0xFFFFFFFF
        return await self._send(pack_frame(mid, t, encode_image(image)), mid)

    async def drain(self) -> None:
        """Wait until every message sent so far is acknowledged (or rejected)."""
        pending = [f for f, _ in self._waiting.values()]
        if pending:
            await asyncio.gather(*pending, return_exceptions=True)

    async def close(self) -> None:
        if self._ws is not None:
            await self._ws.close()
        if self._reader is not None:
            await self._reader


class Stream:
    """Synchronous facade of :class:`AsyncStream` (its event loop runs in a helper thread);
    ``send_*`` return :class:`concurrent.futures.Future` objects of the acks."""

    def __init__(self, url: str, token: str | None, session_id: str, max_in_flight: int = 128) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="hippomap-stream", daemon=True)
        self._thread.start()
        self._stream = AsyncStream(url, token, session_id, max_in_flight)
        self._call(self._stream.connect())

    @property
    def hello(self) -> dict[str, Any]:
        return self._stream.hello

    def _call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result()

    def _ack(self, coro: Any) -> Future:
        inner = self._call(coro)  # the asyncio future of the ack, created on the stream's loop
        out: Future = Future()

        def done(f: asyncio.Future) -> None:
            if f.exception() is not None:
                out.set_exception(f.exception())
            else:
                out.set_result(f.result())

        self._loop.call_soon_threadsafe(inner.add_done_callback, done)
        return out

    def send_odometry(self, readings: Odometry | dict | Iterable[Odometry | dict]) -> Future:
        return self._ack(self._stream.send_odometry(readings))

    def send_frame(self, t: float, image: bytes | np.ndarray) -> Future:
        return self._ack(self._stream.send_frame(t, image))

    def drain(self) -> None:
        self._call(self._stream.drain())

    def close(self) -> None:
        try:
            self._call(self._stream.close())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)

    def __enter__(self) -> "Stream":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
