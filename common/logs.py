"""Structured, quiet logging: one ``key=value`` line per event (logfmt), to stderr."""

from __future__ import annotations

import logging
import sys
import time
from typing import Any

_STANDARD_ATTRS = set(vars(logging.makeLogRecord({}))) | {"message", "asctime"}


def _fmt_value(value: Any) -> str:
    text = f"{value:.4g}" if isinstance(value, float) else str(value)
    if not text or any(c in text for c in ' ="'):
        text = '"' + text.replace('"', '\\"') + '"'
    return text


class LogfmtFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(record.created))
        parts = [
            f"ts={stamp}.{int(record.msecs):03d}",
            f"level={record.levelname.lower()}",
            f"svc={record.name}",
            f"msg={_fmt_value(record.getMessage())}",
        ]
        parts += [
            f"{k}={_fmt_value(v)}" for k, v in vars(record).items() if k not in _STANDARD_ATTRS
        ]
        if record.exc_info:
            parts.append(f"exc={_fmt_value(self.formatException(record.exc_info))}")
        return " ".join(parts)


def setup_logging(service: str, level: str = "info") -> logging.Logger:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(LogfmtFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    return logging.getLogger(service)


class RateLimitedLog:
    """Logs at most one line per ``period_s`` per key, so a flood of bad input stays readable."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0) -> None:
        self._logger = logger
        self._period_s = period_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, msg: str, **fields: Any) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < self._period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        fields["suppressed"] = self._suppressed.pop(key, 0)
        self._last[key] = now
        self._logger.warning(msg, extra=fields)
