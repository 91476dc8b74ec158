import logging
import time

import numpy as np
import pytest

from common.codec import decode, encode
from common.lattice import Window
from common.messages import (
    DETECTIONS_KIND,
    MAP_UPDATE_KIND,
    DetectionRecord,
    DetectionsHeader,
    MapUpdateHeader,
)
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
    groups.add("p0", T0_NS + 3 * FRAME_NS, ["d"], now_s=1.3)  # p0 skipped p1's capture
    assert _stamps(groups.ready(1.3, LIVE)) == [T0_NS + 2 * FRAME_NS]
    assert _stamps(groups.ready(2.2, LIVE)) == []  # p0's capture waits for p1 …
    assert _stamps(groups.ready(2.4, LIVE)) == [T0_NS + 3 * FRAME_NS]  # … as long as the wait


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


def _held_s(groups: CaptureGroups[str], offset_ns: int, frames: int = 8) -> list[float]:
    """How long each of p0's captures is held when p1 stamps ``offset_ns`` after p0 and
    delivers 0.1 s after it (2 Hz)."""
    held_s = []
    for k in range(frames):
        now_s = 0.5 * k
        groups.add("p0", T0_NS + k * FRAME_NS, [f"a{k}"], now_s)
        groups.add("p1", T0_NS + k * FRAME_NS + offset_ns, ["b"], now_s + 0.1)
        for step in range(21):
            released = groups.ready(now_s + 0.1 + 0.1 * step, LIVE)
            if any(("p0", f"a{k}") in items for _, items in released):
                held_s.append(round(0.1 + 0.1 * step, 1))
                break
    return held_s


def test_clocks_tens_of_ms_apart_are_one_capture() -> None:
    """Camera boxes whose clocks differ by 50 ms: each capture split in two, neither ever
    complete, and each waited out the second (capture → map 0.2 → 1.2 s)."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    held_s = _held_s(groups, 50_000_000)
    # The first capture, before either pair's frame interval is known, is two.
    assert held_s[2:] == [0.1] * 6
    assert groups.lagging == set()


@pytest.mark.parametrize("phase", [0.25, 0.5, 0.75])
def test_cameras_not_triggered_together_hold_no_capture_past_a_frame(phase: float) -> None:
    """Free-running cameras stamp anywhere within a frame interval of each other: a capture is
    released once every pair delivered it or a frame past it."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    held_s = _held_s(groups, int(phase * FRAME_NS))
    assert len(held_s) == 8 and max(held_s[2:]) <= 0.6, held_s
    assert groups.lagging == set()


def test_a_pair_that_is_not_live_has_no_say_in_the_window() -> None:
    """A pair heard twice 10 ms apart (one that left, or a forged one) narrowed the window to
    30 ms for good: the live pairs' captures, 50 ms apart, split again."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    _held_s(groups, 50_000_000, frames=4)
    groups.add("ghost", T0_NS + 4 * FRAME_NS, ["g"], 2.0)
    groups.add("ghost", T0_NS + 4 * FRAME_NS + 10_000_000, ["g"], 2.0)
    groups.ready(2.0, LIVE)
    assert groups.window_ns() == pytest.approx(0.4 * FRAME_NS)
    assert "ghost" not in groups.newest_ns


def test_a_slow_replays_pairs_seconds_apart_are_one_capture_and_none_lags() -> None:
    """At 0.1 Hz, pairs 2.5 s apart: the window (4 s) was longer than the wait (1 s), so each
    capture went out half, and the second pair stayed lagging for good."""
    frame_ns = 10 * 10**9
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    sizes = []
    for k in range(6):
        now_s = 10.0 * k
        groups.add("p0", T0_NS + k * frame_ns, ["a"], now_s)
        sizes += [len(items) for _, items in groups.ready(now_s + 1.5, LIVE)]
        groups.add("p1", T0_NS + k * frame_ns + 2_500_000_000, ["b"], now_s + 2.5)
        sizes += [len(items) for _, items in groups.ready(now_s + 2.5, LIVE)]
        sizes += [len(items) for _, items in groups.ready(now_s + 9.9, LIVE)]
    assert sizes[-5:] == [2] * 5 and groups.lagging == set()  # once the interval is known


def test_a_wait_as_long_as_the_window_is_no_longer_than_a_tile_may_be_old() -> None:
    """At 0.1 Hz the window (4 s) made the wait 4 s: a tile held past ``max_tile_age_s`` (2 s),
    older than tiles fusion refuses. And a pair that left stayed lagging in health for good."""
    frame_ns = 10 * 10**9
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0, wait_max_s=2.0)
    for k in range(3):  # both pairs, long enough for the interval to be known
        groups.add("p0", T0_NS + k * frame_ns, ["a"], 10.0 * k)
        groups.add("p1", T0_NS + k * frame_ns, ["b"], 10.0 * k)
        groups.ready(10.0 * k, LIVE)
    groups.add("p0", T0_NS + 3 * frame_ns, ["a"], 30.0)  # p1, alive, silent
    assert groups.ready(31.9, LIVE) == []
    assert _stamps(groups.ready(32.0, LIVE)) == [T0_NS + 3 * frame_ns]
    assert groups.lagging == {"p1"}
    groups.ready(33.0, {"p0"})  # p1's token went
    assert groups.lagging == set()


def test_at_30_hz_no_capture_holds_two_frames_of_one_pair() -> None:
    """The 30 ms window is a whole frame at 30 Hz: with a few ms of jitter, one capture in six
    held two frames of one pair."""
    frame_ns = 33_333_333
    rng = np.random.default_rng(4)
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    released = []
    for k in range(300):  # p1's frames come two frames after p0's
        for pair, frame in (("p0", k), ("p1", k - 2)):
            jitter_ns = int(rng.uniform(-4e6, 4e6))
            groups.add(pair, T0_NS + frame * frame_ns + jitter_ns, [pair], k / 30)
        released += groups.ready(k / 30 + 0.01, LIVE)
    doubled = [items for _, items in released if len(items) != len({p for p, _ in items})]
    assert not doubled and len(released) >= 290


def test_a_lagging_pair_that_comes_within_the_wait_again_is_waited_for_again() -> None:
    """p1 stalled past the wait once (lagging), then delivered 50 ms after p0 as before: every
    capture was released before it came, so it stayed lagging for good, and the tracker dropped
    each of its detections as late."""
    groups: CaptureGroups[str] = CaptureGroups(wait_s=1.0)
    groups.add("p0", T0_NS, ["a"], now_s=0.0)
    assert _stamps(groups.ready(1.0, LIVE)) == [T0_NS]
    assert groups.lagging == {"p1"}
    groups.add("p0", T0_NS + FRAME_NS, ["b"], now_s=1.5)
    assert _stamps(groups.ready(1.5, LIVE)) == [T0_NS + FRAME_NS]  # not waited for
    groups.add("p1", T0_NS + FRAME_NS, ["late"], now_s=1.55)  # 50 ms after p0's
    assert groups.ready(1.55, LIVE) == [(T0_NS + FRAME_NS, [("p1", "late")])]
    assert groups.lagging == set()
    groups.add("p0", T0_NS + 2 * FRAME_NS, ["c"], now_s=2.0)
    assert groups.ready(2.0, LIVE) == []  # waited for again
    groups.add("p1", T0_NS + 2 * FRAME_NS, ["d"], now_s=2.05)
    assert _stamps(groups.ready(2.05, LIVE)) == [T0_NS + 2 * FRAME_NS]


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


def test_a_capture_goes_out_as_one_chain_that_names_its_end() -> None:
    """Two pairs' tiles far apart are two updates; each names the version the chain ends at, the
    one ``map/latest`` serves, so a follower moves its copy there only (never half a capture)."""
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    now = time.time_ns()
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), now)
    _deliver_tile(state, "p1", Window(4000, 0, 8, 8), now)
    state.fuse_captures()
    before = state.view.frozen.version
    headers = [decode(p, MAP_UPDATE_KIND, MapUpdateHeader).header for p in state.publish()]
    assert len(headers) == 2
    versions = [before] + [h.version for h in headers]
    assert [h.previous_version for h in headers] == versions[:-1]  # each continues the last
    end = state.view.frozen.version
    assert headers[-1].version == end and all(h.final_version == end for h in headers)


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


def _deliver_frame(state: FusionState, pair: str, seq: int, stamp_ns: int, x_m: float) -> None:
    """A pair's tile and its one object of a frame."""
    _deliver_tile(state, pair, Window(0 if pair == "p0" else 60, 0, 60, 60), stamp_ns)
    found = DetectionRecord(
        center_m=(x_m, 1.5), size_m=(0.6, 0.4), yaw_rad=0.0, top_m=1.0, points=500, partial=False
    )
    header = DetectionsHeader(pair=pair, seq=seq, stamp_ns=stamp_ns, detections=[found])
    key = f"depth/{pair}/objects"
    state.handle(Delivery("detections", key, time.time_ns(), encode(DETECTIONS_KIND, header)))


def _deliver_detections(state: FusionState, pair: str, seq: int, stamp_ns: int) -> None:
    header = DetectionsHeader(pair=pair, seq=seq, stamp_ns=stamp_ns, detections=[])
    key = f"depth/{pair}/objects"
    state.handle(Delivery("detections", key, time.time_ns(), encode(DETECTIONS_KIND, header)))


def test_a_capture_goes_out_with_its_objects(caplog: pytest.LogCaptureFixture) -> None:
    """Depth sends a frame's tile, then its detections (tens of ms later): a map published in
    between held the new capture's evidence under the tracks of the one before (a mover's new
    cells free, its layers where it was). The map waits for the capture's objects from the pairs
    that sent the capture before's, no longer than the capture wait; a pair that stopped sending
    them is not waited for again."""
    state = FusionState(FusionSettings(capture_wait_s=0.3), FusedGrid(GridParams()))
    for pair in ("p0", "p1"):
        state.handle(Delivery("presence", f"depth/{pair}/alive/x{pair}", time.time_ns(), b""))
    start_ns = time.time_ns() - 400_000_000  # captures 0.1 s apart, none stale

    def capture(k: int, detected_by: tuple[str, ...]) -> tuple[float, float]:
        """Capture k's tiles fused, then the detections of ``detected_by``: the hold before them
        and after."""
        stamp_ns = start_ns + k * 100_000_000
        for pair in ("p0", "p1"):
            _deliver_tile(state, pair, Window(0 if pair == "p0" else 60, 0, 60, 60), stamp_ns)
        state.fuse_captures()
        before = state.objects_hold_s(time.monotonic())
        for pair in detected_by:
            _deliver_detections(state, pair, k, stamp_ns)
        state.refresh_objects()
        return before, state.objects_hold_s(time.monotonic())

    assert capture(0, ("p0", "p1")) == (0.0, 0.0)  # nothing says objects come yet
    state.publish()
    before, after = capture(1, ("p0", "p1"))
    assert 0.0 < before <= 0.3 and after == 0.0
    state.publish()
    before, after = capture(2, ("p0",))  # p1's objects of it never come
    assert before > 0.0 and after > 0.0
    assert state.objects_hold_s(time.monotonic() + 0.3) == 0.0  # waited for long enough
    with caplog.at_level(logging.WARNING):
        state.say_if_objects_overdue()
    assert "objects did not come within the capture wait" in caplog.text
    state.publish()
    time.sleep(0.35)  # the tracker takes capture 2 without p1's
    state.refresh_objects()
    before, after = capture(3, ("p0",))
    assert before > 0.0 and after == 0.0  # p0 is waited for, p1 no more
    # p0's objects stop (its detections refused, or measuring them failed): after one hold in
    # vain its captures go out at once (waited for each, the map went out once a second).
    state.publish()
    assert capture(4, ())[0] > 0.0
    state.publish()
    assert capture(5, ()) == (0.0, 0.0)


def test_a_pair_that_stalled_once_keeps_its_objects_tracked() -> None:
    """p1 stalled past the capture wait once, then delivered 50 ms after p0 as before: it stayed
    lagging, each capture was tracked before its detections came, and its object left
    ``map/objects`` for good with nothing counted or said. (Real time, a 0.2 s wait.)"""
    state = FusionState(FusionSettings(capture_wait_s=0.2), FusedGrid(GridParams()))
    for pair in ("p0", "p1"):
        state.handle(Delivery("presence", f"depth/{pair}/alive/x{pair}", time.time_ns(), b""))

    def pump(until_s: float) -> None:
        while time.monotonic() < until_s:
            state.fuse_captures()
            state.refresh_objects()
            time.sleep(0.005)

    start_s, start_ns = time.monotonic(), time.time_ns()
    for k in range(24):
        frame_s = start_s + 0.1 * k
        pump(frame_s)
        _deliver_frame(state, "p0", k, start_ns + k * 100_000_000, 1.0)
        pump(frame_s + 0.05)
        if not 6 <= k < 10:  # p1 stalls 0.4 s, twice the wait
            _deliver_frame(state, "p1", k, start_ns + k * 100_000_000, 4.0)
        if k == 9:
            assert state.tracker.captures.lagging == {"p1"}
    pump(start_s + 2.45)
    state.update_view()
    pairs_seen = {pair for o in state.view.objects.objects for pair in o.pairs}
    assert pairs_seen == {"p0", "p1"}
    health = health_of(state.view, None, {})["pairs"]["p1"]
    assert health["lagging"] is False
    assert health["detections_late"] <= 1  # the one capture it came back late for, if any


def test_a_clock_stepped_back_takes_tiles_again_and_moves_the_maps_times(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The site's clocks set back by an hour (an NTP server corrected): every tile was refused
    as out of order for that hour, with nothing said of clocks."""
    hour_ns = 3600 * 10**9
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    before_ns = time.time_ns()
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), before_ns)
    state.fuse_captures()
    assert state.grid.stamp_ns == before_ns
    stamp_ns = before_ns - hour_ns + 500_000_000  # half a second later, on the clock set back
    payload = tile_payload("p0", Window(0, 0, 8, 8), 0.8, stamp_ns=stamp_ns)
    state.handle(Delivery("tile", "depth/p0/tile", stamp_ns, payload))
    state.fuse_captures()
    assert dict(state.rejected) == {} and dict(state.accepted) == {"p0": 2}
    assert state.grid.stamp_ns == stamp_ns
    assert float(state.grid.layer("last_seen_s").max()) == pytest.approx(stamp_ns / 1e9)
    assert "the clock stepped back" in caplog.text


def test_each_pairs_refused_tiles_are_named_and_the_clocks_said(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Two camera boxes' clocks off (5 s and an hour): for 16 s the log named the first pair
    only ("capture stamp is 5.02 s old", 19 suppressed), never the one an hour off."""
    state = FusionState(FusionSettings(), FusedGrid(GridParams()))
    for pair in ("p0", "p2"):
        state.handle(Delivery("presence", f"depth/{pair}/alive/x{pair}", time.time_ns(), b""))
    for _ in range(5):
        _deliver_tile(state, "p0", Window(0, 0, 8, 8), time.time_ns() - 5 * 10**9)
        _deliver_tile(state, "p2", Window(8, 0, 8, 8), time.time_ns() - 3600 * 10**9)
    refused = [r for r in caplog.records if r.getMessage() == "tile rejected"]
    assert sorted(r.__dict__["on"] for r in refused) == ["depth/p0/tile", "depth/p2/tile"]
    assert all("clocks synchronised" in r.__dict__["error"] for r in refused)
    # Made-up pairs no process claims share one line per reason.
    for k in range(5):
        _deliver_tile(state, f"x{k}", Window(0, 0, 8, 8), time.time_ns() - 5 * 10**9)
    assert len([r for r in caplog.records if r.getMessage() == "tile rejected"]) == 3


def test_a_tile_of_no_cell_is_taken_not_refused() -> None:
    """A camera gone black gives a tile of no cell: it was refused as lying beyond the site
    ("Window(0, 0, 0, 0) lies beyond …"), counted against its pair."""
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    _deliver_tile(state, "p0", Window(0, 0, 8, 8), time.time_ns())
    _deliver_tile(state, "p0", Window(0, 0, 0, 0), time.time_ns())
    state.fuse_captures()
    assert dict(state.rejected) == {} and dict(state.accepted) == {"p0": 2}
    assert int(state.grid.layer("known").sum()) == 64  # the first tile's cells, and no more


def test_a_pairs_last_process_leaving_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    """Every pair gone at once (a router lost) was four lines at info level."""
    caplog.set_level(logging.INFO, logger="fusion")
    state = FusionState(FusionSettings(), FusedGrid(GridParams()))
    for instance in ("a", "b"):
        state.handle(Delivery("presence", f"depth/p0/alive/{instance}", time.time_ns(), b""))
    state.handle(Delivery("presence", "depth/p0/alive/a", time.time_ns(), b"", alive=False))
    state.handle(Delivery("presence", "depth/p0/alive/b", time.time_ns(), b"", alive=False))
    left = [(r.levelname, r.getMessage()) for r in caplog.records if "left" in r.getMessage()]
    assert left == [
        ("INFO", "depth process left"),
        ("WARNING", "depth process left: no process left for the pair, its cells will decay"),
    ]


def test_late_detections_of_a_pair_not_live_are_neither_counted_nor_said(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Forged detections on made-up pairs, each a capture behind the tracker: a warning line
    each (1000 for 1000), and a key each kept in four tables."""
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    state.handle(Delivery("presence", "depth/p0/alive/x", time.time_ns(), b""))
    now_ns = time.time_ns()
    _deliver_frame(state, "p0", 0, now_ns, 1.0)
    state.fuse_captures()
    state.refresh_objects()
    record = DetectionRecord(
        center_m=(4.0, 1.5), size_m=(0.6, 0.4), yaw_rad=0.0, top_m=1.0, points=500, partial=False
    )
    for k in range(50):
        found = DetectionsHeader(
            pair=f"fake{k}", seq=0, stamp_ns=now_ns - 10**8, detections=[record]
        )
        key = f"depth/fake{k}/objects"
        state.handle(Delivery("detections", key, time.time_ns(), encode(DETECTIONS_KIND, found)))
        state.refresh_objects()
    assert "detections came after" not in caplog.text
    assert dict(state.tracker.late) == {}
    assert set(state.tracker.captures.newest_ns) <= {"p0"}


def test_a_clock_stepped_back_takes_the_old_tracks_off_map_objects() -> None:
    """After the step, map/objects kept serving the old tracks, stamped an hour ahead."""
    state = FusionState(FusionSettings(capture_wait_s=0.0), FusedGrid(GridParams()))
    now_ns = time.time_ns()
    for k in range(4):
        _deliver_frame(state, "p0", k, now_ns + k * 100_000_000 - 10**9, 1.0)
        state.fuse_captures()
        state.refresh_objects()
    assert state.objects_header.objects
    stamp_ns = now_ns - 3600 * 10**9
    payload = tile_payload("p0", Window(0, 0, 8, 8), 0.8, stamp_ns=stamp_ns)
    state.handle(Delivery("tile", "depth/p0/tile", stamp_ns, payload))
    published = state.refresh_objects()
    assert published is not None and published.objects == []
    assert state.refresh_objects() is None  # said once


def test_a_process_never_seen_leaving_changes_nothing(caplog: pytest.LogCaptureFixture) -> None:
    """A DELETE for a pair never seen made it a known pair (its refusals then said apart) and
    logged a warning per message."""
    state = FusionState(FusionSettings(), FusedGrid(GridParams()))
    state.handle(Delivery("presence", "depth/zz/alive/x", time.time_ns(), b"", alive=False))
    assert state.processes == {} and "left" not in caplog.text
