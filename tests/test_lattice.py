import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from common.lattice import Window, cell_center, cell_of

resolutions = st.sampled_from([0.01, 0.02, 0.05, 0.1, 0.25])
coords = st.floats(min_value=-500.0, max_value=500.0, allow_nan=False)


@given(coords, coords, resolutions)
def test_world_to_cell_to_world_stays_within_half_a_cell(x: float, y: float, r: float) -> None:
    ij = cell_of((x, y), r)
    center = cell_center(ij, r)
    assert np.all(np.abs(center - (x, y)) <= r / 2 + 1e-9)


@given(st.integers(-10_000, 10_000), st.integers(-10_000, 10_000), resolutions)
def test_cell_edges_and_centers_map_back_to_their_cell(i: int, j: int, r: float) -> None:
    assert tuple(cell_of(cell_center((i, j), r), r)) == (i, j)
    assert tuple(cell_of((i * r, j * r), r)) == (i, j)  # the lower edge belongs to the cell


@given(
    st.integers(-50, 50),
    st.integers(-50, 50),
    st.integers(0, 30),
    st.integers(0, 30),
    st.integers(-50, 50),
    st.integers(-50, 50),
    st.integers(0, 30),
    st.integers(0, 30),
)
def test_window_slices_address_the_same_cells(
    i0: int, j0: int, c0: int, r0: int, i1: int, j1: int, c1: int, r1: int
) -> None:
    a, b = Window(i0, j0, c0, r0), Window(i1, j1, c1, r1)
    assume(not a.empty)
    outer = a.union(b)
    assert outer.contains(a) and outer.contains(b)
    canvas = np.zeros(outer.shape, dtype=np.int64)
    rows, cols = a.slices_in(outer)
    ii, jj = np.meshgrid(np.arange(a.i0, a.i1), np.arange(a.j0, a.j1))
    canvas[rows, cols] = ii * 1000 + jj
    common = a.intersect(b)
    if not common.empty:
        r_sub, c_sub = common.slices_in(outer)
        ci, cj = np.meshgrid(np.arange(common.i0, common.i1), np.arange(common.j0, common.j1))
        np.testing.assert_array_equal(canvas[r_sub, c_sub], ci * 1000 + cj)


def test_covering_window_is_tight() -> None:
    window = Window.covering(0.0, 0.0, 12.0, 10.0, 0.05)
    assert (window.i0, window.j0, window.cols, window.rows) == (0, 0, 240, 200)
    assert window.origin_m(0.05) == (0.0, 0.0)
