"""Files that settings name (a calibration, a scene, a Zenoh config): read once at start-up and
refused with a reason when they are no regular file, larger than any such file or nested deeper
than any such file, never a hang or a traceback. A pipe named as ``--calib`` blocked the start
past SIGTERM; 600 levels of YAML or JSON ended in a RecursionError's 3000 lines, 60,000 levels
of a JSON5 config in a crash inside Zenoh's parser."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

MAX_SETTING_FILE_BYTES = 16 * 1024 * 1024
"""Calibrations, scenes and Zenoh configs are kilobytes."""
MAX_NESTING = 64
"""Their brackets nest a few levels deep."""


def setting_file_text(path: Path) -> str:
    """The file's text; ValueError naming why it cannot be one of these files."""
    if not path.exists():
        raise ValueError("no such file")
    if not path.is_file():
        raise ValueError("not a regular file (a folder, a pipe or a device)")
    size = path.stat().st_size
    if size > MAX_SETTING_FILE_BYTES:
        raise ValueError(f"{size} bytes, larger than any such file")
    text = path.read_text()
    depth = bracket_depth(text)
    if depth > MAX_NESTING:
        raise ValueError(f"brackets nested {depth} deep (at most {MAX_NESTING})")
    return text


def bracket_depth(text: str) -> int:
    """The deepest nesting of [ and { outside quoted strings (JSON, JSON5, YAML flow style)."""
    depth = deepest = 0
    quote = ""
    escaped = False
    for char in text:
        if quote:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == quote:
                quote = ""
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(depth - 1, 0)
    return deepest


def data_of(text: str, path: Path) -> Any:
    """A JSON (by ``path``'s suffix) or YAML file's data; ValueError naming why it has none."""
    try:
        return json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except RecursionError:  # nested by indentation, which bracket_depth does not see
        raise ValueError("nested too deep") from None


def load_data_file(path: Path) -> Any:
    return data_of(setting_file_text(path), path)
