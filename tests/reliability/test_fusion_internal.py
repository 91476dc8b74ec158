"""Fusion's own threads outlive what one message or one save raises: the owner's loop counts a tile
whose fusing raised anything (memory, numpy, a bug) as rejected ``internal`` and takes the next,
and so a capture whose tracking raised (detections rejected ``internal``); the state writer counts
a save that failed any way and saves again with the next hand-over."""

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.codec import encode
from common.lattice import Window
from common.messages import DETECTIONS_KIND, DetectionRecord, DetectionsHeader
from services.fusion import persistence
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.inbox import Delivery, Inbox
from services.fusion.persistence import StateWriter, load_grid
from services.fusion.service import run
from services.fusion.settings import FusionSettings
from services.fusion.state import FusionState
from tests.conftest import wait_for
from tests.tiles import tile_payload


class FlakyGrid(FusedGrid):
    """Fails its first tiles the ways fusing one can, then fuses."""

    def __init__(self, params: GridParams) -> None:
        super().__init__(params)
        self.failures: list[BaseException] = [
            MemoryError("cannot allocate"),
            np.linalg.LinAlgError("singular"),
            IndexError("index 64 is out of bounds"),
        ]

    def integrate(self, *args: Any, **kwargs: Any) -> Window:
        if self.failures:
            raise self.failures.pop(0)
        return super().integrate(*args, **kwargs)


class OwnerLoop:
    """Fusion's owner loop on a thread of its own, fed through its inbox; what it publishes is
    kept: map updates in ``updates``, object lists in ``objects``."""

    def __init__(self, settings: FusionSettings, state: FusionState, state_dir: Path) -> None:
        self.inbox = Inbox(64, 1 << 24)
        self.writer = StateWriter(state_dir)
        self.stop = threading.Event()
        self.updates: list[bytes] = []
        self.objects: list[bytes] = []
        self.thread = threading.Thread(
            target=run,
            args=(
                settings,
                state,
                self.inbox,
                self.writer,
                self.stop,
                self.updates.append,
                self.objects.append,
                lambda: None,
            ),
        )
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.writer.close()
        assert not self.thread.is_alive()


def test_the_owner_loop_counts_any_exception_of_one_tile_as_internal_and_goes_on(
    tmp_path: Path,
) -> None:
    settings = FusionSettings(state_dir=tmp_path, no_multicast_scouting=True)
    state = FusionState(settings, FlakyGrid(settings.grid_params()))
    loop = OwnerLoop(settings, state, tmp_path)
    for seq in range(5):
        payload = tile_payload("p0", Window(4 * seq, 0, 4, 4), 3.0, seq=seq)
        loop.inbox.offer(Delivery("tile", "depth/p0/tile", time.time_ns(), payload))
        time.sleep(0.05)
    wait_for(lambda: sum(state.view.accepted.values()) == 2, 5, "the tiles after the failures")
    assert loop.thread.is_alive()
    assert state.view.rejected == {"internal": 3}
    wait_for(lambda: bool(loop.updates), 5, "an update of the fused tiles")
    loop.close()


def test_the_owner_loop_counts_a_capture_whose_tracking_raised_and_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A track the object list refused (a NaN size of a yaw of 1e308) raised in the owner's loop,
    outside any message's handling: fusion died. Now it is counted, the map goes on, and the
    tracks begin anew."""
    settings = FusionSettings(state_dir=tmp_path, no_multicast_scouting=True)
    state = FusionState(settings, FusedGrid(settings.grid_params()))
    failures = [ValueError("size_m: a footprint's length and width must be positive")]
    objects = state.tracker.objects

    def failing_once(*args: Any, **kwargs: Any) -> Any:
        if failures:
            raise failures.pop()
        return objects(*args, **kwargs)

    monkeypatch.setattr(state.tracker, "objects", failing_once)
    loop = OwnerLoop(settings, state, tmp_path)
    box = DetectionRecord(
        center_m=(1.0, 1.0), size_m=(0.8, 0.5), yaw_rad=0.0, top_m=1.0, points=100, partial=False
    )
    for seq in range(5):
        header = DetectionsHeader(pair="p0", seq=seq, stamp_ns=time.time_ns(), detections=[box])
        payload = encode(DETECTIONS_KIND, header)
        loop.inbox.offer(Delivery("detections", "depth/p0/objects", time.time_ns(), payload))
        time.sleep(0.1)
    tile = tile_payload("p0", Window(0, 0, 4, 4), 3.0)
    loop.inbox.offer(Delivery("tile", "depth/p0/tile", time.time_ns(), tile))
    wait_for(lambda: len(state.view.objects.objects) == 1, 5, "the box tracked anew")
    wait_for(lambda: sum(state.view.accepted.values()) == 1, 5, "the tile fused")
    assert loop.thread.is_alive()
    assert state.view.detections_rejected == {"internal": 1}
    assert loop.objects  # the object lists after the failure were published
    loop.close()


def test_a_save_failing_any_way_is_counted_and_the_next_one_saves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    grid = FusedGrid(GridParams())

    def fuse(window: Window, stamp_ns: int) -> None:
        grid.integrate(
            window,
            np.full(window.shape, 2.0, np.float32),
            np.zeros(window.shape, np.float32),
            np.ones(window.shape, np.uint16),
            stamp_ns,
        )

    real = persistence.encode_records
    calls = []

    def failing_once(*args: Any, **kwargs: Any) -> Any:
        calls.append(args)
        if len(calls) == 1:
            raise ValueError("a bug in the encoder")  # not an OSError: escaped the old writer
        return real(*args, **kwargs)

    monkeypatch.setattr(persistence, "encode_records", failing_once)
    writer = StateWriter(tmp_path)
    fuse(Window(0, 0, 10, 10), 10**9)
    writer.hand_over(*grid.freeze())
    wait_for(lambda: writer.errors == 1, 5, "the failed save counted")
    assert writer._thread.is_alive() and writer.saved_version == -1
    fuse(Window(100, 0, 10, 10), 2 * 10**9)
    writer.hand_over(*grid.freeze())
    writer.close()
    assert writer.saved_version == grid.version and writer.errors == 1
    restored = load_grid(GridParams(), tmp_path, 1)
    np.testing.assert_array_equal(restored.layer("logodds"), grid.layer("logodds"))
