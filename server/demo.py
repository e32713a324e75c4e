"""``hippomap serve --demo``: a simulated robot streaming into a session of this server.

The robot is a client like any other (the Python client over the websocket), driving the
simulator's corridor loop (:func:`hippomap.sim.loop_world`) in real time: odometry and a
rendered camera frame at every step. It creates its session with the admin token, mints a
viewer token for it and prints the session's viewer URL.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Callable

log = logging.getLogger("hippomap.server")


async def run_demo(url: str, token: str, rate_hz: float = 10.0, laps: int = 10, seed: int = 1,
                   stopping: Callable[[], bool] = lambda: False) -> str:
    """Stream one simulated run in real time; returns the session id. ``stopping()`` tells
    whether the server is shutting down (then a closed stream is expected, not an error)."""
    from hippomap import sim
    from hippomap.client import AsyncStream, Client, encode_image
    from hippomap.inputs import Odometry

    # an 8 m x 5 m loop at 0.6 m/s: the first revisit (and loop closure) comes within a minute
    world = sim.loop_world(seed=seed, laps=laps, size=(8.0, 5.0), speed_mps=0.6)
    run = await asyncio.to_thread(sim.simulate, world, rate_hz=rate_hz, frame_every=1, seed=seed,
                                  odometry_noise=sim.OdometryNoise(sigma_omega=0.02, omega_bias=0.005))

    def setup() -> tuple[str, str]:
        with Client(url, token) as c:
            s = c.create_session(name="demo robot")  # the model's default config
            viewer = c.create_token("viewer", session=s["id"], label="demo viewer")
            return s["id"], viewer["token"]

    sid, viewer = await asyncio.to_thread(setup)
    print(f"demo robot streaming into session {sid}", flush=True)
    print(f"viewer: {url}/viewer/{sid}/?token={viewer}", flush=True)
    frame_at = {int(k): i for i, k in enumerate(run.frame_steps)}
    try:
        async with AsyncStream(url, token, sid, max_in_flight=256) as stream:
            start = time.monotonic()
            t0 = float(run.times[0])
            for k in range(len(run.times)):
                t = float(run.times[k])
                delay = start + (t - t0) - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                _, v, omega = (float(x) for x in run.odometry[k])
                gt = tuple(float(x) for x in run.groundtruth[k])  # drawn by the viewer, unused by the mapper
                await stream.send_odometry(Odometry(t, v=v, omega=omega, gt=gt))
                i = frame_at.get(k)
                if i is not None:
                    img = await asyncio.to_thread(lambda: encode_image(run.frame(i)))
                    await stream.send_frame(t, img)  # the frame of this step, at the same time
            await stream.drain()
        print(f"demo robot finished its run ({len(run.times)} steps) in session {sid}", flush=True)
    except asyncio.CancelledError:
        raise
    except Exception as exc:  # the demo must never take the server down
        if not stopping():
            log.warning("demo robot stopped: %s", exc)
    return sid
