"""Fusion: stitches every pair's tiles on one global log-odds grid and serves it over Zenoh."""
