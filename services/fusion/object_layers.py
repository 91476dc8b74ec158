"""What a capture's tracks change in the map (DESIGN.md, Objects): the one sequence the fusion
service runs at every new capture and ``bench/map_accuracy.py`` runs offline, so the two cannot
drift apart. Pure: a grid and a tracker in, layers set."""

from __future__ import annotations

from services.fusion.grid import CellMasks, FusedGrid
from services.fusion.map_check import MapCheck
from services.fusion.objects import ObjectTracker


def serve_tracks(
    grid: FusedGrid, tracker: ObjectTracker, outline_static: bool
) -> tuple[CellMasks, CellMasks, MapCheck]:
    """Forget the movers' wakes, and set the contested layer (moving and unsettled tracks'
    footprints now: ``ObjectTracker.movers_now``; with ``outline_static`` also the static
    footprints the frames disagree with, the edge cells the frames call free of those they agree
    with and the rims of both (:class:`Outline`), and the rims' enclosures) and the fringe layer;
    returns, for the predicted layer, the rest of the static footprints the frames agree with and
    the movers' tops (``ObjectTracker.mover_tops``) where no frame measured them (the newest
    capture's: they go once captures stop), and the map check (whose pieces the object list
    reports)."""
    resolution_m = grid.params.resolution_m
    grid.forget_occupied(*tracker.wake(resolution_m))
    check = tracker.check_against(grid)
    contested = tracker.movers_now(resolution_m)
    outlined: CellMasks = []
    if outline_static:
        for outline in tracker.outlines(resolution_m):
            window = outline.window
            doubted = outline.cells  # all of it where the frames disagree, else its edge seen free
            if grid.agrees(window, outline.cells):
                doubted = outline.edge & grid.free_in(window)
                outlined.append((window, outline.cells & ~doubted))
            contested += [cells for cells in ((window, doubted), outline.rim) if cells[1].any()]
        contested += check.enclosures
        grid.set_fringe(check.fringes)
    grid.set_contested(contested)
    tops = [
        (window, top & grid.unknown_in(window)) for window, top in tracker.mover_tops(resolution_m)
    ]
    return outlined, tops, check
