import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.lattice import Window
from common.mapfiles import OCCUPIED_MIN
from common.occupancy_map import OCCUPIED, UNKNOWN, occupancy_from_logodds
from services.fusion.grid import (
    FusedGrid,
    GridParams,
    ServedAssembler,
    TileOutsideMap,
    chunk_aligned,
    chunk_keys,
    chunk_window,
    update_parts,
)
from tests.tiles import dirty_window

P = GridParams()


def _integrate(
    grid: FusedGrid,
    window: Window,
    value: float,
    height: float = 0.0,
    stamp_ns: int = 1,
    count: int = 5,
) -> Window:
    return grid.integrate(
        window,
        np.full(window.shape, value, np.float32),
        np.full(window.shape, height, np.float32),
        np.full(window.shape, count, np.uint16),
        stamp_ns,
    )


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(-20, 20), st.integers(-20, 20), st.integers(0, 2**32 - 1)),
        min_size=1,
        max_size=25,
    )
)
def test_logodds_never_leave_the_clamp(tiles: list[tuple[int, int, int]]) -> None:
    grid = FusedGrid(GridParams(bounds=Window(-20, -20, 47, 45)))  # fixed: every tile lies inside
    for i0, j0, seed in tiles:
        rng = np.random.default_rng(seed)
        window = Window(i0, j0, 7, 5)
        count = rng.integers(0, 3, window.shape).astype(np.uint16)
        before = grid.layer("logodds")[window.slices_in(grid.window)].copy()
        grid.integrate(
            window,
            rng.uniform(-3, 3, window.shape).astype(np.float32),
            rng.uniform(0, 2, window.shape).astype(np.float32),
            count,
            1,
        )
        assert (
            grid.layer("logodds").min() >= P.logodds_min
            and grid.layer("logodds").max() <= P.logodds_max
        )
        after = grid.layer("logodds")[window.slices_in(grid.window)]
        np.testing.assert_array_equal(after[count == 0], before[count == 0])
    # The kernel's cell-by-cell occupancy is the whole-layer conversion's, exactly.
    np.testing.assert_array_equal(
        grid.layer("occupancy"), occupancy_from_logodds(grid.layer("logodds"), grid.layer("known"))
    )


def test_overlapping_tiles_stitch_exactly() -> None:
    grid = FusedGrid(P)
    a, b = Window(10, 20, 30, 10), Window(25, 25, 30, 10)
    _integrate(grid, a, 0.4, height=1.0)
    _integrate(grid, b, -0.3, height=0.5)
    expected = np.zeros(grid.window.shape, np.float32)
    expected[a.slices_in(grid.window)] += 0.4
    expected[b.slices_in(grid.window)] += np.float32(-0.3)
    np.testing.assert_array_equal(grid.layer("logodds"), expected)
    overlap = a.intersect(b)
    assert np.all(
        grid.layer("logodds")[overlap.slices_in(grid.window)] == np.float32(0.4) + np.float32(-0.3)
    )
    # Height: the occupied pair's top, replaced by the floor where a free observation came last.
    assert np.all(grid.layer("height_m")[overlap.slices_in(grid.window)] == 0.5)
    only_a = Window(10, 20, 15, 5)
    assert np.all(grid.layer("height_m")[only_a.slices_in(grid.window)] == 1.0)
    assert not grid.layer("known")[Window(0, 0, 5, 5).slices_in(grid.window)].any()


def test_height_keeps_the_maximum_over_occupied_observations() -> None:
    grid = FusedGrid(P)
    w = Window(0, 0, 4, 4)
    _integrate(grid, w, 0.8, height=1.2)
    _integrate(grid, w, 0.8, height=0.9)
    assert np.all(grid.layer("height_m")[w.slices_in(grid.window)] == np.float32(1.2))


def test_cells_with_no_pixels_are_not_updated() -> None:
    grid = FusedGrid(P)
    w = Window(0, 0, 4, 4)
    _integrate(grid, w, 0.8, count=0)
    assert not grid.layer("known").any() and np.all(grid.layer("logodds") == 0)


def test_decay_returns_unobserved_cells_to_unknown() -> None:
    grid = FusedGrid(GridParams(decay_after_s=1.0, decay_time_constant_s=0.5))
    w = Window(0, 0, 10, 10)
    _integrate(grid, w, 3.5, height=1.0, stamp_ns=int(100e9))
    assert grid.decay(now_s=100.5, elapsed_s=1.0) == 0  # not stale yet
    for k in range(30):
        grid.decay(now_s=102.0 + k, elapsed_s=1.0)
    region = w.slices_in(grid.window)
    assert not grid.layer("known")[region].any()
    assert np.all(grid.layer("logodds")[region] == 0) and np.all(
        np.isnan(grid.layer("height_m")[region])
    )


def test_fresh_cells_do_not_decay() -> None:
    grid = FusedGrid(GridParams(decay_after_s=1.0))
    _integrate(grid, Window(0, 0, 4, 4), 2.0, stamp_ns=int(100e9))
    grid.decay(now_s=100.2, elapsed_s=1.0)
    assert np.all(grid.layer("logodds")[Window(0, 0, 4, 4).slices_in(grid.window)] == 2.0)


def test_map_grows_and_keeps_what_it_had() -> None:
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 10, 10), 1.0)
    before = grid.layer("logodds")[Window(0, 0, 10, 10).slices_in(grid.window)].copy()
    _integrate(grid, Window(-100, 300, 5, 5), -1.0)
    assert grid.window.contains(Window(-100, 300, 5, 5)) and grid.window.contains(
        Window(0, 0, 10, 10)
    )
    np.testing.assert_array_equal(
        grid.layer("logodds")[Window(0, 0, 10, 10).slices_in(grid.window)], before
    )


def test_fixed_bounds_crop_and_reject_outside() -> None:
    bounds = Window(0, 0, 100, 100)
    grid = FusedGrid(GridParams(bounds=bounds))
    touched = _integrate(grid, Window(90, 90, 20, 20), 1.0)
    assert touched == Window(90, 90, 10, 10) and grid.window == bounds
    with pytest.raises(TileOutsideMap):
        _integrate(grid, Window(500, 500, 5, 5), 1.0)


def test_growth_beyond_the_cell_limit_is_refused() -> None:
    grid = FusedGrid(GridParams(max_cells=200 * 200))
    with pytest.raises(TileOutsideMap, match="over the limit"):
        _integrate(grid, Window(0, 0, 1000, 10), 1.0)


def test_dirty_window_collects_changes_until_taken() -> None:
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 5, 5), 1.0)
    _integrate(grid, Window(10, 10, 5, 5), 1.0)
    assert dirty_window(grid) == Window(0, 0, 15, 15)
    assert dirty_window(grid).empty


def test_growth_beyond_the_limit_changes_nothing() -> None:
    grid = FusedGrid(GridParams(max_cells=256 * 256))
    _integrate(grid, Window(0, 0, 10, 10), 1.0)
    window, version, chunks = grid.window, grid.version, set(grid.chunks)
    with pytest.raises(TileOutsideMap) as refused:
        _integrate(grid, Window(4900, 4900, 1, 1), 1.0)
    assert refused.value.reason == "growth"
    assert (grid.window, grid.version, set(grid.chunks)) == (window, version, chunks)


def test_memory_follows_the_area_observed_not_the_extent() -> None:
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 10, 10), 1.0)
    _integrate(grid, Window(1000, 1000, 1, 1), 1.0)
    assert grid.window.cols * grid.window.rows > 1000 * 1000
    assert len(grid.chunks) == 2  # two chunks, not a million cells
    bounded = FusedGrid(GridParams(bounds=Window(0, 0, 5000, 5000)))
    _integrate(bounded, Window(100, 100, 70, 10), 1.0)
    assert set(bounded.chunks) == {(1, 1), (2, 1)}


def test_freeze_copies_only_the_changed_chunks_and_shares_the_rest() -> None:
    grid = FusedGrid(P, epoch_ns=7)
    _integrate(grid, Window(0, 0, 200, 200), 1.0)
    first, changed = grid.freeze()
    assert changed == set(grid.chunks) and len(changed) == 16
    _integrate(grid, Window(70, 70, 5, 5), -2.0)
    second, changed = grid.freeze()
    assert changed == {(1, 1)} and second.key == (7, 2) and first.key == (7, 1)
    assert all(second.chunks[k] is first.chunks[k] for k in first.chunks if k != (1, 1))
    # The first snapshot is immutable: the later tile is not in it.
    assert first.layer("served")[72, 72] > 50 and second.layer("served")[72, 72] < 50
    np.testing.assert_array_equal(second.layer("logodds"), grid.layer("logodds"))
    with pytest.raises(ValueError):
        second.chunks[(1, 1)].layers["logodds"][0, 0] = 0.0


def test_decay_visits_only_chunks_that_may_be_stale() -> None:
    grid = FusedGrid(GridParams(decay_after_s=1.0, decay_time_constant_s=0.5))
    _integrate(grid, Window(0, 0, 10, 10), 2.0, stamp_ns=int(100e9))
    _integrate(grid, Window(640, 640, 10, 10), 2.0, stamp_ns=int(103e9))
    grid.freeze()
    dirty_window(grid)
    assert grid.decay(now_s=103.5, elapsed_s=1.0) == 100  # the old chunk only
    assert grid.changed == {(0, 0)} and dirty_window(grid) == Window(0, 0, 64, 64)


def test_the_served_assembler_pastes_changes_and_matches_a_full_assembly() -> None:
    grid = FusedGrid(P)
    assembler = ServedAssembler()
    _integrate(grid, Window(0, 0, 300, 200), -1.0)
    first = assembler.occupancy(grid.freeze()[0])
    _integrate(grid, Window(100, 100, 10, 10), 3.0)
    grid.set_predicted([(Window(5, 5, 3, 3), np.ones((3, 3), np.bool_))])
    frozen, _ = grid.freeze()
    np.testing.assert_array_equal(assembler.occupancy(frozen), frozen.layer("served"))
    assert first[101, 101] < 50 and frozen.layer("served")[101, 101] > 50  # copies, not views
    _integrate(grid, Window(1000, 0, 2, 2), 1.0)  # the map grows: assembled anew
    frozen, _ = grid.freeze()
    np.testing.assert_array_equal(assembler.occupancy(frozen), frozen.layer("served"))


def test_the_predicted_layer_is_served_occupied_and_clears() -> None:
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 20, 20), -1.0)
    assert grid.set_predicted([(Window(2, 2, 3, 3), np.ones((3, 3), np.bool_))])
    assert grid.served_occupancy()[3, 3] == OCCUPIED and grid.layer("occupancy")[3, 3] < 50
    assert grid.layer("predicted").sum() == 9
    assert grid.set_predicted([]) and not grid.layer("predicted").any()
    assert not grid.set_predicted([])  # nothing predicted: nothing to visit


def test_a_fringe_is_served_unknown_where_the_frames_call_it_occupied_but_not_over_a_prediction() -> (
    None
):
    """The fringe layer (just outside a static object's measured footprint) serves its cells unknown,
    occupied or not, while the evidence stays as measured; a predicted cell (a mover's path
    through the fringe) stays occupied; the cells show the frames again once it is gone."""
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 20, 20), -1.0)
    _integrate(grid, Window(4, 4, 6, 1), 3.0)
    fringe = (Window(4, 4, 6, 2), np.ones((2, 6), np.bool_))  # occupied row 4, free row 5
    assert grid.set_fringe([fringe])
    served, evidence = grid.served_occupancy(), grid.layer("occupancy")
    assert (served[4:6, 4:10] == UNKNOWN).all() and (evidence[4, 4:10] >= OCCUPIED_MIN).all()
    assert served[3, 4] == evidence[3, 4] and served[6, 4] == evidence[6, 4]
    grid.set_predicted([(Window(7, 4, 1, 1), np.ones((1, 1), np.bool_))])
    assert grid.served_occupancy()[4, 7] == OCCUPIED
    assert not grid.set_fringe([fringe])  # unchanged
    assert grid.set_fringe([]) and grid.served_occupancy()[4, 5] == evidence[4, 5]


def test_a_contested_footprint_is_served_unknown_where_the_frames_call_it_free() -> None:
    """A static object's footprint the frames call mostly free (:meth:`FusedGrid.agrees`):
    its free cells are served unknown, its occupied ones stay occupied, the evidence stays as
    measured, and the cells show it again once the footprint is gone."""
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 20, 20), -1.0)
    _integrate(grid, Window(6, 6, 1, 1), 3.0)
    footprint = (Window(4, 4, 4, 4), np.ones((4, 4), np.bool_))
    solid = (Window(10, 10, 2, 2), np.ones((2, 2), np.bool_))
    _integrate(grid, Window(10, 10, 2, 2), 3.0)
    assert grid.agrees(*solid) and not grid.agrees(*footprint)
    assert grid.set_contested([footprint])
    served, evidence = grid.served_occupancy(), grid.layer("occupancy")
    free = int(evidence[3, 3])
    others = np.ones((4, 4), np.bool_)
    others[2, 2] = False  # cell (6, 6), called occupied
    assert (served[4:8, 4:8][others] == UNKNOWN).all() and served[6, 6] == evidence[6, 6]
    assert evidence[6, 6] >= OCCUPIED_MIN and 0 <= free < 50 and served[3, 3] == free
    assert (evidence[4:8, 4:8][others] == free).all()  # the evidence stays as measured
    assert not grid.set_contested([footprint])  # unchanged
    assert grid.set_contested([]) and grid.served_occupancy()[5, 5] == free


def test_chunk_aligned_is_integer_exact_at_any_lattice_index() -> None:
    """A float division rounded cell 2**62 + 1 down and made a 1×1 window 0×0."""
    far = 2**62 + 1
    assert chunk_aligned(Window(far, far, 1, 1)) == Window(2**62, 2**62, 64, 64)
    assert chunk_aligned(Window(-65, -1, 2, 1)) == Window(-128, -64, 128, 64)


@pytest.mark.parametrize("corner", [2**62, 10**7, -(10**7), 20_001])
def test_tiles_beyond_the_site_extent_are_refused_and_change_nothing(corner: int) -> None:
    grid = FusedGrid(P)  # ±1 km around the origin: cells -20000 … 19999
    with pytest.raises(TileOutsideMap) as refused:
        _integrate(grid, Window(corner, corner, 1, 1), 1.0)
    assert refused.value.reason == "outside_extent"
    assert grid.window.empty and not grid.chunks and grid.version == 0
    _integrate(grid, Window(0, 0, 10, 10), 1.0)  # the real site is not locked out
    assert grid.window == Window(0, 0, 64, 64)


def test_a_tile_across_the_site_edge_keeps_its_part_inside() -> None:
    grid = FusedGrid(GridParams(max_extent_m=10.0))  # cells -200 … 199
    assert _integrate(grid, Window(190, 0, 20, 4), 1.0) == Window(190, 0, 10, 4)


def test_updates_are_the_changed_groups_not_their_bounding_box() -> None:
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 20, 20), 1.0)
    _integrate(grid, Window(4900, 4900, 20, 20), 1.0)
    parts = update_parts(grid.take_dirty_parts())
    assert sorted(parts, key=lambda w: w.i0) == [Window(0, 0, 20, 20), Window(4900, 4900, 20, 20)]
    _integrate(grid, Window(10, 10, 300, 200), 1.0)  # one tile over 24 chunks: one part
    assert update_parts(grid.take_dirty_parts()) == [Window(10, 10, 300, 200)]


@settings(max_examples=80, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(-3000, 3000), st.integers(-3000, 3000), st.integers(1, 150)),
        min_size=1,
        max_size=40,
    ),
    st.integers(4, 12),
)
def test_update_parts_are_few_and_cover_every_changed_cell(
    tiles: list[tuple[int, int, int]], limit: int
) -> None:
    dirty: dict[tuple[int, int], Window] = {}
    for i0, j0, size in tiles:
        window = Window(i0, j0, size, size)
        for key in chunk_keys(window):
            cells = window.intersect(chunk_window(key))
            dirty[key] = dirty.get(key, Window(0, 0, 0, 0)).union(cells)
    parts = update_parts(dirty, limit)
    assert 1 <= len(parts) <= limit
    for cells in dirty.values():  # each chunk's changed cells lie in one part
        assert any(part.contains(cells) for part in parts)


def test_restore_leaves_out_what_lies_beyond_the_limits_not_everything() -> None:
    saved = FusedGrid(GridParams(max_extent_m=1e6, max_cells=10**12))
    _integrate(saved, Window(0, 0, 200, 200), 1.0)
    _integrate(saved, Window(30_000, 30_000, 1, 1), 1.0)  # 1.5 km: beyond today's extent
    _integrate(saved, Window(9_000, 9_000, 1, 1), 1.0)  # within it, past the cell limit
    frozen, _ = saved.freeze()
    chunks = {key: chunk.layers for key, chunk in frozen.chunks.items()}
    restored = FusedGrid(P)
    assert restored.restore(chunks) == 2
    assert restored.window == Window(0, 0, 256, 256)
    np.testing.assert_array_equal(
        restored.layer("logodds"), saved.window_of("logodds", restored.window)
    )


def test_a_hidden_cell_believed_free_turns_unknown_and_no_other_changes() -> None:
    """A tile names the cells whose floor something hides now (floor model, rule 10): a free
    belief there is out of date and goes; an occupied one keeps its belief, a cell the tile also
    measures takes the measurement, and every cell the tile does not name keeps its own."""
    grid = FusedGrid(P)
    _integrate(grid, Window(0, 0, 1, 1), -2.0, stamp_ns=10**9)  # believed free
    _integrate(grid, Window(1, 0, 1, 1), 2.0, height=0.5, stamp_ns=10**9)  # believed occupied
    _integrate(grid, Window(2, 0, 1, 1), -2.0, stamp_ns=10**9)  # free, measured again below
    _integrate(grid, Window(0, 1, 3, 1), -2.0, stamp_ns=10**9)  # free, not named
    w = Window(0, 0, 3, 1)
    count = np.array([[0, 0, 5]], np.uint16)
    grid.integrate(
        w,
        np.array([[0.0, 0.0, 2.0]], np.float32),
        np.array([[np.nan, np.nan, 0.6]], np.float32),
        count,
        2 * 10**9,
        np.ones(w.shape, np.bool_),
    )
    known, logodds = grid.layer("known"), grid.layer("logodds")
    assert not known[0, 0] and logodds[0, 0] == 0.0  # was free: unknown now
    assert np.isnan(grid.layer("height_m")[0, 0])
    assert known[0, 1] and logodds[0, 1] > 0  # occupied: kept
    assert known[0, 2] and logodds[0, 2] > 0  # measured in the same tile: the measurement
    assert known[1, :3].all() and (logodds[1, :3] < 0).all()  # not named: still free
    assert grid.served_occupancy()[0, 0] == -1


def test_a_hidden_cell_another_pair_measured_in_the_same_capture_stays_free() -> None:
    """One pair's hidden cell is the floor behind something as that pair sees it; a pair that
    measured that floor free in the same capture (stamps a few ms apart) is right about it."""
    grid = FusedGrid(P)
    w = Window(0, 0, 2, 1)
    _integrate(grid, Window(0, 0, 1, 1), -2.0, stamp_ns=10**9)  # the last frame
    _integrate(grid, Window(1, 0, 1, 1), -2.0, stamp_ns=2 * 10**9)  # another pair, this capture
    grid.integrate(
        w,
        np.zeros(w.shape, np.float32),
        np.full(w.shape, np.nan, np.float32),
        np.zeros(w.shape, np.uint16),
        2 * 10**9 + 5 * 10**6,
        np.ones(w.shape, np.bool_),
    )
    known = grid.layer("known")
    assert not known[0, 0] and known[0, 1]
