"""Per-pair depth: stereo images → disparity → world points → occupancy tile on the global lattice."""
