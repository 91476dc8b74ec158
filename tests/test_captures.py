import time

import pytest

from common.lattice import Window
from services.fusion.captures import CaptureGroups
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.inbox import Delivery
from services.fusion.settings import FusionSettings
from services.fusion.state import FusionState, health_of
from tests.tiles import tile_payload

T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 500_000_000
LIVE = {"p0", "p1"}


def _stamps(released: list[tuple[int, list[tuple[str, str]]]]) -> list[int]:
    return [stamp for stamp, _ in released]


def test_a_capture_is_released_once_every_live_pair_delivered_it() -> None:
    groups: CaptureGroups[str] = CaptureGroups()
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert groups.ready(0.1, LIVE) == []
    # The other pair's stamp differs by a few ms (one trigger, two clocks): the same capture.
    groups.add("p1", T0_NS + 5_000_000, ["b"], now_s=0.2)
    assert groups.ready(0.2, LIVE) == [(T0_NS, [("p0", "a"), ("p1", "b")])]
    assert groups.ready(0.3, LIVE) == []


def test_a_later_complete_capture_releases_the_ones_before_it_in_order() -> None:
    groups: CaptureGroups[str] = CaptureGroups()
    groups.add("p0", T0_NS, ["a"], now_s=0.0)  # p1 skipped this frame
    groups.add("p0", T0_NS + FRAME_NS, ["c"], now_s=0.5)
    assert groups.ready(0.5, LIVE) == []
    groups.add("p1", T0_NS + FRAME_NS, [], now_s=0.6)  # saw nothing: still delivered
    assert _stamps(groups.ready(0.6, LIVE)) == [T0_NS, T0_NS + FRAME_NS]


def test_a_pair_missing_past_the_wait_is_not_waited_for_until_it_delivers() -> None:
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert groups.ready(0.9, LIVE) == []
    assert _stamps(groups.ready(1.0, LIVE)) == [T0_NS]
    groups.add("p0", T0_NS + FRAME_NS, ["b"], now_s=1.1)  # p1 lags: no wait
    assert _stamps(groups.ready(1.1, LIVE)) == [T0_NS + FRAME_NS]
    groups.add("p1", T0_NS + 2 * FRAME_NS, ["c"], now_s=1.2)  # p1 is back: waited for again
    groups.add("p0", T0_NS + 3 * FRAME_NS, ["d"], now_s=1.3)
    assert _stamps(groups.ready(1.3, LIVE)) == []
    assert _stamps(groups.ready(2.2, LIVE)) == [T0_NS + 2 * FRAME_NS]


def test_a_late_message_of_a_released_capture_is_released_at_once() -> None:
    groups: CaptureGroups[str] = CaptureGroups()
    groups.add("p0", T0_NS + FRAME_NS, ["new"], now_s=0.0)
    groups.add("p1", T0_NS + FRAME_NS, ["new"], now_s=0.0)
    assert _stamps(groups.ready(0.0, LIVE)) == [T0_NS + FRAME_NS]
    groups.add("p1", T0_NS, ["old"], now_s=0.1)
    assert groups.ready(0.1, LIVE) == [(T0_NS, [("p1", "old")])]


def test_a_late_message_a_few_ms_off_a_released_capture_is_late_too() -> None:
    """Pairs whose clocks differ by a few ms: p1's tile of a capture released without it (the
    wait ran out) is released at once, and does not make p1 waited for again."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert _stamps(groups.ready(1.0, LIVE)) == [T0_NS]  # p1 missed it: lagging
    groups.add("p1", T0_NS + 10_000_000, ["late"], now_s=1.2)
    assert groups.ready(1.2, LIVE) == [(T0_NS + 10_000_000, [("p1", "late")])]
    assert groups.lagging == {"p1"}


def test_a_pair_always_later_than_the_wait_holds_no_capture_back() -> None:
    """p1's tiles come 1.2 s after p0's: once it lags, each capture is released as p0 delivers
    it, not after waiting out the second again and again."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    held_s = []
    for k in range(6):
        now_s = 0.5 * k
        groups.add("p0", T0_NS + k * FRAME_NS, ["a"], now_s)
        if k >= 3:  # p1's tile of the capture three frames back
            groups.add("p1", T0_NS + (k - 3) * FRAME_NS, ["b"], now_s)
        for step in range(11):
            if groups.ready(now_s + 0.1 * step, LIVE) and groups.pending == {}:
                held_s.append(round(0.1 * step, 1))
                break
    # The first capture waits once; then p1 lags, and its late tiles do not undo that.
    assert held_s == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def test_with_no_wait_nothing_is_held_and_no_pair_lags() -> None:
    groups: CaptureGroups[str] = CaptureGroups(wait_s=0.0)
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert _stamps(groups.ready(0.0, LIVE)) == [T0_NS]
    assert groups.lagging == set()


def test_a_pair_that_leaves_no_longer_holds_a_capture() -> None:
    groups: CaptureGroups[str] = CaptureGroups()
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert groups.ready(0.1, LIVE) == []
    assert _stamps(groups.ready(0.2, {"p0"})) == [T0_NS]  # p1's liveliness token went


def test_everything_releases_what_is_held() -> None:
    groups: CaptureGroups[str] = CaptureGroups()
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert groups.ready(0.0, LIVE, everything=True) == [(T0_NS, [("p0", "a")])]
    assert groups.pending == {}


def _deliver_tile(state: FusionState, pair: str, window: Window, stamp_ns: int) -> None:
    key = f"depth/{pair}/tile"
    payload = tile_payload(pair, window, 0.8, stamp_ns=stamp_ns)
    state.handle(Delivery("tile", key, time.time_ns(), payload))


def test_fusion_takes_a_capture_into_the_map_when_its_last_pair_arrives() -> None:
    """Two pairs alive: the first pair's tile waits for the second's of the same capture, so the
    map never claims a capture's stamp while showing another pair's older frame."""
    state = FusionState(FusionSettings(), FusedGrid(GridParams()))
    for pair in ("p0", "p1"):
        state.handle(Delivery("presence", f"depth/{pair}/alive/x{pair}", time.time_ns(), b""))
    now = time.time_ns()
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), now)
    state.fuse_captures()
    assert state.grid.version == 0 and state.grid.stamp_ns == 0
    _deliver_tile(state, "p1", Window(8, 0, 8, 8), now + 2_000_000)
    state.fuse_captures()
    assert state.grid.stamp_ns == now + 2_000_000
    assert dict(state.accepted) == {"p0": 1, "p1": 1}


def test_with_no_capture_wait_each_tile_is_fused_as_it_comes() -> None:
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    for pair in ("p0", "p1"):
        state.handle(Delivery("presence", f"depth/{pair}/alive/x{pair}", time.time_ns(), b""))
    now = time.time_ns()
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), now)
    state.fuse_captures()
    assert state.grid.stamp_ns == now and dict(state.accepted) == {"p0": 1}
    state.update_view()  # with no wait, no pair is waited for, so none lags
    assert health_of(state.view, None, {})["pairs"]["p1"]["lagging"] is False
    assert state.tracker.captures.wait_s == 0.0  # the tracker takes its detections alike


def test_a_capture_wait_longer_than_a_tile_may_be_old_is_refused() -> None:
    with pytest.raises(ValueError, match="capture_wait_s"):
        FusionSettings(capture_wait_s=3.0, max_tile_age_s=2.0)


def test_a_held_tile_the_map_cannot_take_is_counted_by_its_reason() -> None:
    """The map's growth is checked when a capture is fused: a tile that would grow it past its
    cell limit is refused then, counted as ``growth``, and the capture's other tile is taken."""
    grid = FusedGrid(GridParams(max_cells=128 * 128))
    state = FusionState(FusionSettings(), grid)
    now = time.time_ns()
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), now)
    _deliver_tile(state, "p1", Window(1000, 1000, 8, 8), now)
    state.fuse_captures()
    assert dict(state.rejected) == {"growth": 1} and dict(state.accepted) == {"p0": 1}
