import time

from common.lattice import Window
from services.fusion.captures import CaptureGroups
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.inbox import Delivery
from services.fusion.service import FusionState, health_of
from services.fusion.settings import FusionSettings
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
    state.update_view()  # p1 did not deliver within the wait: health says it is not waited for
    assert health_of(state.view, None, {})["pairs"]["p1"]["lagging"] is True
