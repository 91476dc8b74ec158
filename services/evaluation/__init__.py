"""Scoring the map against ground truth."""
