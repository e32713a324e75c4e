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

No line shows a secret: a filter on the handler (:class:`RedactSecrets`) replaces ``token=...``
query values, ``Authorization`` credentials and anything shaped like a hippomap token by
``[REDACTED]`` in every record (uvicorn's access lines included), and the formatters redact their
output again (tracebacks).

The format: ``--log-format`` of ``hippomap serve``, else ``HIPPOMAP_LOG_FORMAT``, else ``auto``:
text when stderr is a terminal (someone is reading it), JSON otherwise (a container, systemd, a
pipe: something is collecting it).
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import time
from typing import Any, TextIO

from hippomap.errors import InputError

FORMATS = ("auto", "json", "text")
ENV_FORMAT = "HIPPOMAP_LOG_FORMAT"

#: attributes every LogRecord has: anything else on a record came from ``extra=``
_STANDARD = frozenset(vars(logging.LogRecord("x", logging.INFO, "x", 0, "x", None, None))) | {
    "message",
    "asctime",
    "color_message",
    "taskName",
}
#: the loggers set to the chosen level (everything else stays at WARNING)
OWN_LOGGERS = ("hippomap", "web")


#: secrets in log text: a ``token=`` query parameter, an Authorization header's credentials (``Bearer ...``)
#: and anything shaped like a hippomap token (``hm_`` + base64url)
_SECRETS = (
    (re.compile(r"(?i)(\btoken=)[^&\s\"'#,;)]+"), r"\1[REDACTED]"),
    (re.compile(r"(?i)(\b(?:bearer|basic)\s+)[^\s\"',;)]+"), r"\1[REDACTED]"),
    (
        re.compile(r"(?i)(\bauthorization[\"']?\s*[:=]\s*[\"']?)(?!bearer\b|basic\b|\[REDACTED)[^\s\"',;)]+"),
        r"\1[REDACTED]",
    ),
    (re.compile(r"\bhm_[A-Za-z0-9_\-]{8,}"), "hm_[REDACTED]"),
)
REDACTED = "[REDACTED]"


def redact(text: str) -> str:
    """``text`` with every secret it shows replaced by ``[REDACTED]`` (see :data:`_SECRETS`)."""
    if (
        "token" not in text.lower()
        and "hm_" not in text
        and "auth" not in text.lower()
        and "bearer" not in text.lower()
        and "basic" not in text.lower()
    ):
        return text
    for pattern, repl in _SECRETS:
        text = pattern.sub(repl, text)
    return text


def _redact_value(value: Any) -> Any:
    if isinstance(value, str):
        return redact(value)
    if isinstance(value, bytes):
        return redact(value.decode("utf-8", "replace"))
    return value


class RedactSecrets(logging.Filter):
    """Removes tokens from a record before any handler formats it: in the message, its arguments
    (uvicorn's access line carries the request path with its query as an argument) and ``extra``
    fields. Installed on the server's log handler, so it applies to every logger's lines."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):  # each argument alone (uvicorn's access fields stay usable)...
            record.args = tuple(_redact_value(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: _redact_value(v) for k, v in record.args.items()}
        try:
            message = record.getMessage()
        except Exception:  # a broken format string: the formatter reports it as usual
            message = None
        if message is not None and redact(message) != message:  # ...then the whole line ("token=%s" % secret)
            record.msg, record.args = redact(message), None
        for k, v in _extras(record).items():
            if isinstance(v, (str, bytes)):
                setattr(record, k, _redact_value(v))
        return True


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
        out: dict[str, Any] = {
            "time": _utc(record.created),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
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
        return redact(json.dumps(out, ensure_ascii=False, default=str))  # tracebacks too


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
            return redact(super().format(record))  # tracebacks too
        finally:
            record.msg, record.args = saved


def resolve_format(fmt: str | None = None, stream: TextIO | None = None) -> str:
    """``json`` or ``text``: the argument, else ``$HIPPOMAP_LOG_FORMAT``, else ``auto`` (text on a terminal)."""
    choice = (fmt or os.environ.get(ENV_FORMAT) or "auto").strip().lower()
    if choice not in FORMATS:
        raise InputError(
            f"log format {choice!r} (from {'--log-format' if fmt else ENV_FORMAT}): "
            f"expected one of {', '.join(FORMATS)}"
        )
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
    handler.addFilter(RedactSecrets())
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
