"""``hippomap serve``: run the mapping service (FastAPI sessions, ingest, queries, live viewer).

    hippomap serve [--host H] [--port P] [--data-dir D] [--database FILE|URL]
                   [--backend inprocess|process|ray] [--ray-address ADDR]
                   [--demo [--demo-rate HZ] [--demo-laps N] [--demo-speed X]]

Sessions are stored in the embedded SQLite database ``D/hippomap.sqlite3`` unless
``--database`` names another file or a PostgreSQL URL. On the first start an admin token is
generated, printed and saved in ``D/admin.token`` (later starts print where it is;
``export HIPPOMAP_TOKEN=$(cat D/admin.token)`` lets the client and ``hippomap replay`` find
it). ``HIPPOMAP_ADMIN_TOKEN`` sets it explicitly. Sessions are created with
``POST /sessions``. ``--demo`` also starts a simulated robot streaming into the admin's
session named "demo robot" (created on the first start, reused after a restart) and prints
that session's viewer URL; the robot stops after its laps and says so. ``--port 0`` picks a
free port. Other limits come from ``HIPPOMAP_*`` environment variables (see
``server/settings.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
from typing import Any, Callable

from .settings import ServerSettings


def _data_location(settings: ServerSettings) -> str:
    """Where the sessions are stored, never with a password (a PostgreSQL URL may carry one)."""
    db = settings.database or ""
    if db.startswith(("postgresql://", "postgres://")):
        from .storage.postgres import describe_url

        return f"PostgreSQL {describe_url(db)}"
    return str(settings.database_path)


def _banner(app: Any, settings: ServerSettings, url: str) -> None:
    print(f"hippomap server on {url}  (API docs: {url}/docs)", flush=True)
    print(f"data: {_data_location(settings)}", flush=True)
    if settings.admin_token:
        print("admin token: from HIPPOMAP_ADMIN_TOKEN", flush=True)
    elif app.state.admin_token_created:
        print(f"admin token (new, saved in {settings.token_file}): {app.state.admin_token}", flush=True)
    else:
        print(f"admin token: in {settings.token_file}", flush=True)
    print(f"  export HIPPOMAP_TOKEN=$(cat {settings.token_file})" if not settings.admin_token else "", flush=True)


async def _serve(args: argparse.Namespace) -> int:
    """Check the options, listen, and run the service until it stops (with the demo robot beside it if asked);
    the exit code: 2 for bad options, 1 when the server could not start."""
    import uvicorn

    from .app import create_app
    from .logs import configure as configure_logs

    configure_logs(args.log_format, args.log_level)
    settings = _checked_settings(args)
    if settings is None:
        return 2
    sys.setswitchinterval(settings.switch_interval_s)
    app = create_app(settings)
    sock = _listen(args.host, args.port)
    host = f"[{args.host}]" if ":" in args.host else args.host
    url = f"http://{host}:{sock.getsockname()[1]}"
    config = uvicorn.Config(
        app,
        log_level=args.log_level,
        log_config=None,
        ws_max_size=settings.max_body_bytes + 1024,
        timeout_graceful_shutdown=10,
        access_log=args.access_log,
    )
    server = uvicorn.Server(config)
    task = asyncio.create_task(server.serve(sockets=[sock]))
    while not server.started and not task.done():
        await asyncio.sleep(0.02)
    if task.done():
        return 1
    _banner(app, settings, url)
    demo = _start_demo(args, url, app.state.admin_token, lambda: server.should_exit) if args.demo else None
    await task
    if demo is not None:
        demo.cancel()
    return 0


def _checked_settings(args: argparse.Namespace) -> ServerSettings | None:
    """The settings of the command line and the environment; ``None`` once it printed why they cannot serve (a
    ``--demo-*`` value out of range, ``--backend ray`` without Ray: now, with the fix, not in the start-up)."""
    if args.demo:
        bad = [
            f"{flag} must be {what}, got {value}"
            for flag, value, ok, what in (
                ("--demo-rate", args.demo_rate, args.demo_rate > 0, "> 0"),
                ("--demo-laps", args.demo_laps, args.demo_laps >= 1, ">= 1"),
                ("--demo-speed", args.demo_speed, args.demo_speed > 0, "> 0"),
            )
            if not ok
        ]
        if bad:
            print(f"hippomap serve: {'; '.join(bad)}", file=sys.stderr, flush=True)
            return None
    settings = ServerSettings.from_env(
        data_dir=args.data_dir, database=args.database, backend=args.backend, ray_address=args.ray_address
    )
    if settings.backend == "ray":
        from .runtime.ray_backend import require_ray

        try:
            require_ray()
        except RuntimeError as exc:
            print(f"hippomap serve: {exc}", file=sys.stderr, flush=True)
            return None
    return settings


def _listen(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` (port 0: any free port) for uvicorn to serve on."""
    # proto=IPPROTO_TCP matters: asyncio sets TCP_NODELAY only on sockets that say they are TCP, and
    # without it small acks wait for the robot's next message (Nagle + delayed ACK: ~one message period)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.bind((host, port))
    return sock


def _start_demo(args: argparse.Namespace, url: str, token: str, stopping: Callable[[], bool]) -> asyncio.Task:
    """The simulated robot (``--demo``) streaming into the service at ``url``, as a task; it stops after its laps
    or when ``stopping()`` says the server is shutting down."""
    from .demo import run_demo

    return asyncio.create_task(
        run_demo(
            url,
            token,
            rate_hz=args.demo_rate,
            laps=args.demo_laps,
            speed=args.demo_speed,
            stopping=stopping,
        )
    )


def _cmd(args: argparse.Namespace) -> int:
    try:  # uvloop (part of uvicorn[standard]) when present: a faster event loop
        import uvloop

        return uvloop.run(_serve(args))
    except ImportError:
        return asyncio.run(_serve(args))


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "serve",
        help="serve the mapper to robots (HTTP + websocket)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 = any free port)")
    p.add_argument("--data-dir", default=None, help="data folder (default ./hippomap-data or $HIPPOMAP_DATA_DIR)")
    p.add_argument(
        "--database",
        default=None,
        help="SQLite file (default <data-dir>/hippomap.sqlite3) or a PostgreSQL URL "
        "postgresql://user:pw@host/db (replicas sharing sessions; needs the 'postgres' extra)",
    )
    p.add_argument(
        "--backend",
        default=None,
        choices=["inprocess", "process", "ray"],
        help="where sessions' mappers run: in this process (default), in child processes of this server "
        "($HIPPOMAP_PROCESS_WORKERS, default 1) or one Ray actor per session "
        '(needs pip install "hippomap[ray]"; $HIPPOMAP_BACKEND)',
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="Ray cluster to join with --backend ray (default: start a local Ray on loopback; $HIPPOMAP_RAY_ADDRESS)",
    )
    p.add_argument(
        "--demo",
        action="store_true",
        help="also stream a simulated robot into the session 'demo robot' (reused after a restart)",
    )
    p.add_argument(
        "--demo-rate",
        type=float,
        default=10.0,
        help="demo odometry readings per second of simulated time, each with a camera frame (default 10)",
    )
    p.add_argument("--demo-laps", type=int, default=10, help="laps the demo robot drives before it stops (default 10)")
    p.add_argument(
        "--demo-speed", type=float, default=1.0, help="demo real-time factor (default 1: real time; 2 = twice as fast)"
    )
    p.add_argument("--log-level", default="warning", choices=["critical", "error", "warning", "info", "debug"])
    p.add_argument("--access-log", action="store_true", help="log every request")
    p.add_argument(
        "--log-format",
        default=None,
        choices=["auto", "json", "text"],
        help="log lines as JSON objects or text (default $HIPPOMAP_LOG_FORMAT, else auto: "
        "text on a terminal, JSON otherwise)",
    )
    p.set_defaults(func=_cmd)


def main(argv: list[str] | None = None) -> int:
    from hippomap.cli import clean_help

    parser = argparse.ArgumentParser(prog="python -m server")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    clean_help(parser)
    args = parser.parse_args(["serve", *(argv if argv is not None else sys.argv[1:])])
    return int(args.func(args) or 0)
