"""Simulated overhead stereo pairs: a MuJoCo warehouse, rendered headless and published over Zenoh."""
