"""Settings from CLI flags and ``OVERGRID_*`` environment variables, validated by pydantic.

Every service declares one flat ``BaseSettings`` subclass; flags are generated from its fields so a
setting is named once. A bad value stops start-up with a message that names the flag and the
environment variable.
"""

from __future__ import annotations

import argparse
import sys
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn, TypeVar, get_args, get_origin

from pydantic import BeforeValidator, Field, ValidationError
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

ENV_PREFIX = "OVERGRID_"


def _split_commas(value: Any) -> Any:
    """Accept ``a,b``, ``["a,b", "c"]`` and JSON-free env values alike."""
    if value is None:
        return []
    if isinstance(value, str):
        value = [value]
    if isinstance(value, list | tuple):
        return [part.strip() for item in value for part in str(item).split(",") if part.strip()]
    return value


CommaList = Annotated[list[str], NoDecode, BeforeValidator(_split_commas)]
"""A list setting given as ``--flag a,b``, ``--flag a --flag b`` or ``OVERGRID_FLAG=a,b``."""

LogLevel = Literal["debug", "info", "warning", "error"]


class OvergridSettings(BaseSettings):
    """Base of every service's settings: the environment prefix and strictness live here."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="forbid", validate_default=True)


class ZenohSettings(OvergridSettings):
    """Zenoh session flags shared by every service, after zenoh-python's examples' ``common.py``."""

    mode: Literal["peer", "client", "router"] | None = Field(
        None, description="Zenoh session mode (default: the config file's, else peer)"
    )
    connect: CommaList = Field(default_factory=list, description="endpoints to connect to")
    listen: CommaList = Field(default_factory=list, description="endpoints to listen on")
    config: Path | None = Field(
        None, description="Zenoh JSON5 config file (default: $ZENOH_CONFIG if set)"
    )
    no_multicast_scouting: bool = Field(False, description="disable multicast scouting")
    namespace: str | None = Field(
        None, description="Zenoh namespace prefixed to every key: isolates a site or a test run"
    )
    log_level: LogLevel = Field("info", description="log verbosity")


S = TypeVar("S", bound=OvergridSettings)


def flag_name(field: str) -> str:
    return "--" + field.replace("_", "-")


def env_name(field: str) -> str:
    return ENV_PREFIX + field.upper()


def _is_list(annotation: Any) -> bool:
    origin = get_origin(annotation)
    if origin is Annotated:
        return _is_list(get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return any(_is_list(arg) for arg in get_args(annotation))
    return origin is list


def _is_bool(annotation: Any) -> bool:
    return annotation is bool


def build_parser(
    settings_cls: type[OvergridSettings], prog: str, description: str
) -> argparse.ArgumentParser:
    """One flag per settings field; defaults stay in the model so env vars can fill the gaps."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    for name, field in settings_cls.model_fields.items():
        help_text = f"{field.description or ''} [env {env_name(name)}]"
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        flag = flag_name(str(extra.get("flag", name)))  # a field may not shadow BaseModel (json)
        if _is_bool(field.annotation):
            parser.add_argument(
                flag,
                dest=name,
                action=argparse.BooleanOptionalAction,
                default=None,
                help=help_text,
            )
        elif _is_list(field.annotation):
            parser.add_argument(flag, dest=name, action="append", default=None, help=help_text)
        else:
            parser.add_argument(flag, dest=name, default=None, help=help_text)
    return parser


def describe_validation_error(error: ValidationError) -> str:
    """Name the flag and env var of each bad setting, with what was wrong."""
    lines = []
    for item in error.errors():
        loc = [str(part) for part in item["loc"]]
        if not loc:  # a check across settings names them in its own message
            lines.append(f"invalid settings: {item['msg'].removeprefix('Value error, ')}")
            continue
        where = f"{flag_name(loc[0])} / {env_name(loc[0])}"
        got = item.get("input")
        suffix = f" (got {got!r})" if got is not None and not isinstance(got, dict) else ""
        lines.append(f"invalid setting {where}: {item['msg']}{suffix}")
    return "\n".join(lines)


STARTUP_ERROR_EXIT = 2


def startup_error(message: str) -> NoReturn:
    """Stop start-up with one line naming the setting or file and what is wrong (exit 2)."""
    print(message, file=sys.stderr)
    raise SystemExit(STARTUP_ERROR_EXIT)


def load_settings(settings_cls: type[S], **values: Any) -> S:
    """Validate ``values`` (CLI wins over env); exit with a clear message naming bad settings."""
    try:
        return settings_cls(**{k: v for k, v in values.items() if v is not None})
    except ValidationError as error:
        startup_error(describe_validation_error(error))


def parse_settings(
    settings_cls: type[S], argv: Sequence[str] | None, prog: str, description: str
) -> S:
    parser = build_parser(settings_cls, prog, description)
    args = parser.parse_args(argv)
    return load_settings(settings_cls, **vars(args))
