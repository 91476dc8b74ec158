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


class CountedRefusals:
    """Messages refused, counted by reason (``counts``), each reason said in a rate-limited
    warning with its count so far: what a client refuses is seen in its counters and its log."""

    def __init__(self, logger: logging.Logger, msg: str) -> None:
        self.counts: dict[str, int] = {}
        self._msg = msg
        self._warn = RateLimitedLog(logger)

    def refuse(self, reason: str, **fields: Any) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1
        self._warn.warning(reason, self._msg, reason=reason, count=self.counts[reason], **fields)


class Transitions:
    """A condition watched over time, logged only when it changes: a warning when it goes
    wrong, an info line when it is right again (``first_right`` the first time, if it started
    wrong), so a service that loses something says so once, not every period."""

    def __init__(
        self,
        logger: logging.Logger,
        wrong: str,
        right_again: str,
        first_right: str | None = None,
        *,
        right: bool = True,
    ) -> None:
        self._logger = logger
        self._wrong, self._right_again = wrong, right_again
        self._first_right = first_right or right_again
        self._ever_right = right
        self.right = right

    def update(self, right: bool, **fields: Any) -> None:
        if right and not self.right:
            self._logger.info(
                self._right_again if self._ever_right else self._first_right, extra=fields
            )
        elif self.right and not right:
            self._logger.warning(self._wrong, extra=fields)
        self._ever_right |= right
        self.right = right
