"""Shared fixtures: an isolated Zenoh router on loopback per test, and real service processes.

Isolation: every test gets its own namespace and port, with multicast scouting off, so concurrent test
runs never see each other. Every process is started under coreutils ``timeout`` so it stops by itself
even if pytest dies, and is stopped with SIGINT (then SIGKILL) at teardown.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from common.client import MapUnavailable, health

REPO = Path(__file__).resolve().parents[1]
PROCESS_LIFETIME_S = 240


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Bus:
    """A Zenoh router session in the test process; services connect to it as peers."""

    endpoint: str
    namespace: str
    session: zenoh.Session
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def flags(self) -> list[str]:
        return [
            "--connect",
            self.endpoint,
            "--no-multicast-scouting",
            "--namespace",
            self.namespace,
        ]

    def start(self, *args: str, log_path: Path | None = None) -> subprocess.Popen[bytes]:
        """Start ``overgrid ARGS`` connected to this bus; stops by itself after a bounded time."""
        command = [
            "timeout",
            "-s",
            "INT",
            "-k",
            "5",
            str(PROCESS_LIFETIME_S),
            sys.executable,
            "-m",
            "services.cli",
            *args,
            *self.flags(),
        ]
        output = open(log_path, "wb") if log_path else subprocess.DEVNULL  # noqa: SIM115
        process = subprocess.Popen(
            command,
            cwd=REPO,
            stdout=output,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.processes.append(process)
        return process

    @staticmethod
    def kill(process: subprocess.Popen[bytes]) -> None:
        """SIGKILL the service itself (``process`` is the ``timeout`` wrapping it), as a crash
        would: no handler runs, nothing is saved or undeclared."""
        children = subprocess.run(
            ["pgrep", "-P", str(process.pid)], capture_output=True, text=True
        ).stdout.split()
        for pid in children:
            os.kill(int(pid), signal.SIGKILL)
        process.wait(10)

    def stop_all(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10
        for process in self.processes:
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def open_router(namespace: str, port: int) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("namespace", json.dumps(namespace))
    return zenoh.open(config)


@pytest.fixture
def bus() -> Iterator[Bus]:
    port = free_port()
    namespace = f"test-{uuid.uuid4().hex[:10]}"
    session = open_router(namespace, port)
    bus = Bus(f"tcp/127.0.0.1:{port}", namespace, session)
    try:
        yield bus
    finally:
        bus.stop_all()
        session.close()  # type: ignore[no-untyped-call]


def fusion_answers(bus: Bus) -> bool:
    """Whether fusion answers map/health yet: it starts in 1.5-2.5 s here, longer on a loaded
    machine, and a wait must not end at the first query that finds nothing."""
    try:
        return "map" in health(bus.session, timeout_s=5)
    except MapUnavailable:
        return False


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def run_overgrid(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    """``overgrid ARGS`` to its end (at most 60 s), its output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
    )


def assert_one_line_exit_2(result: subprocess.CompletedProcess[str], *names: str) -> None:
    """A start-up error: exit 2 and one line on stderr naming each of ``names``, no traceback."""
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for name in names:
        assert name in lines[0], lines[0]
    assert "/.cargo/" not in lines[0]  # no build paths of the Zenoh library
