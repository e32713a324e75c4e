"""The server's logs: one JSON object per line (for log collectors) or plain text (for people).

``configure(fmt, level)`` installs ONE handler (stderr) on the root logger, so the server's own
logger ``hippomap.server``, uvicorn's loggers (``uvicorn.error``, ``uvicorn.access``; they
propagate to the root once uvicorn is told not to install its own handlers:
``uvicorn.Config(log_config=None)``), the viewer's (``web.*``) and any library's warnings all come
out in the same format.

A JSON line holds ``time`` (UTC, ISO 8601, milliseconds), ``level``, ``logger``, ``message``;
``session`` when the call passed ``extra={"session": session_id}`` (every session-related line
does); any other ``extra`` fields (e.g. ``duration_s``); ``exc`` with the traceback when the
record carries an exception; and for uvicorn's access lines ``client``, ``method``, ``path``,
``status``.

The format: ``--log-format`` of ``hippomap serve``, else ``HIPPOMAP_LOG_FORMAT``, else ``auto``:
text when stderr is a terminal (someone is reading it), JSON otherwise (a container, systemd, a
pipe: something is collecting it).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from typing import Any, TextIO

from hippomap.errors import InputError

FORMATS = ("auto", "json", "text")
ENV_FORMAT = "HIPPOMAP_LOG_FORMAT"

#: attributes every LogRecord has: anything else on a record came from ``extra=``
_STANDARD = frozenset(vars(logging.LogRecord("x", logging.INFO, "x", 0, "x", None, None))) | {"message", "asctime",
                                                                                              "color_message", "taskName"}
#: the loggers set to the chosen level (everything else stays at WARNING)
OWN_LOGGERS = ("hippomap", "web")


def _utc(created: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(created)) + f".{int(created % 1 * 1000):03d}Z"


def _extras(record: logging.LogRecord) -> dict[str, Any]:
    return {k: v for k, v in vars(record).items() if k not in _STANDARD and not k.startswith("_")}


def _access_fields(record: logging.LogRecord) -> dict[str, Any]:
    """uvicorn's access lines carry (client, method, path, http version, status) as args."""
    if record.name == "uvicorn.access" and isinstance(record.args, tuple) and len(record.args) == 5:
        client, method, path, _version, status = record.args
        return {"client": client, "method": method, "path": path, "status": status}
    return {}


class JSONFormatter(logging.Formatter):
    """One JSON object per line; never raises on odd ``extra`` values (they are ``str()``-ed)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"time": _utc(record.created), "level": record.levelname, "logger": record.name,
                               "message": record.getMessage()}
        extras = _extras(record)
        if "session" in extras:
            out["session"] = extras.pop("session")
        out.update(_access_fields(record))
        for k, v in extras.items():
            out.setdefault(k, v)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exc"] = record.exc_text
        if record.stack_info:
            out["stack"] = self.formatStack(record.stack_info)
        return json.dumps(out, ensure_ascii=False, default=str)


class TextFormatter(logging.Formatter):
    """``time LEVEL logger [session] message key=value...`` and the traceback, if any."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)-7s %(name)s %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        extras = _extras(record)
        session = extras.pop("session", None)
        saved = record.msg, record.args
        try:
            message = record.getMessage()
            if session is not None:
                message = f"[{session}] {message}"
            if extras:
                message += " " + " ".join(f"{k}={v}" for k, v in extras.items())
            record.msg, record.args = message, None
            return super().format(record)
        finally:
            record.msg, record.args = saved


def resolve_format(fmt: str | None = None, stream: TextIO | None = None) -> str:
    """``json`` or ``text``: the argument, else ``$HIPPOMAP_LOG_FORMAT``, else ``auto`` (text on a terminal)."""
    choice = (fmt or os.environ.get(ENV_FORMAT) or "auto").strip().lower()
    if choice not in FORMATS:
        raise InputError(f"log format {choice!r} (from {'--log-format' if fmt else ENV_FORMAT}): "
                         f"expected one of {', '.join(FORMATS)}")
    if choice == "auto":
        stream = stream if stream is not None else sys.stderr
        isatty = getattr(stream, "isatty", None)
        return "text" if isatty is not None and isatty() else "json"
    return choice


def configure(fmt: str | None = None, level: str | int = "warning", stream: TextIO | None = None) -> str:
    """Send every log record to ``stream`` (stderr) in ``fmt``; returns the format used.

    The root logger gets the one handler at WARNING (libraries' warnings are shown, their chatter
    is not); the project's loggers (:data:`OWN_LOGGERS`) get ``level``. uvicorn sets its own
    loggers' levels from its ``log_level`` and must be given ``log_config=None``."""
    stream = stream if stream is not None else sys.stderr
    used = resolve_format(fmt, stream)
    numeric = logging.getLevelName(level.upper()) if isinstance(level, str) else int(level)
    if not isinstance(numeric, int):
        raise InputError(f"log level {level!r}: expected critical, error, warning, info or debug")
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JSONFormatter() if used == "json" else TextFormatter())
    handler.set_name("hippomap")
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == "hippomap"]:
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(numeric)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        lg = logging.getLogger(name)  # uvicorn's own handlers (if a previous config left any) would print twice
        lg.handlers = []
        lg.propagate = True
    return used
