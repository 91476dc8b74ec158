"""Settings from CLI flags and ``OVERGRID_*`` environment variables, parsed and validated by
pydantic-settings' own CLI support.

One configuration tree: a service's settings nest the parameter models of its algorithms (e.g.
``DepthSettings.model: SensorModelParams``), whose defaults and bounds live only there. A nested
parameter is ``--model.p-hit`` / ``OVERGRID_MODEL__P_HIT``; where its last name is unique in the
tree, the flat ``--p-hit`` says the same (flags derived from the tree, never declared twice). A bad
value stops start-up with one line that names the flag and the environment variable (exit 2).
"""

from __future__ import annotations

import re
import sys
from argparse import SUPPRESS
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn, TypeVar

from pydantic import AfterValidator, BaseModel, BeforeValidator, Field, ValidationError
from pydantic.dataclasses import is_pydantic_dataclass
from pydantic_settings import (
    BaseSettings,
    CliSettingsSource,
    CliToggleFlag,
    NoDecode,
    SettingsConfigDict,
    SettingsError,
)

from common.lattice import MAX_RESOLUTION_M, MIN_RESOLUTION_M

ENV_PREFIX = "OVERGRID_"
ENV_NESTED_DELIMITER = "__"
NESTED_FLAG_SEPARATOR = "."


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

PORTED_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
"""Zenoh's link protocols whose locator is HOST:PORT (a unix socket's is a path)."""


def endpoint_parts(endpoint: str) -> tuple[str, str, str, str]:
    """(protocol, address, host, port) of a Zenoh endpoint PROTOCOL/HOST:PORT[?metadata][#config];
    host and port empty where the address has no colon."""
    protocol, _, locator = endpoint.partition("/")
    address = locator.split("?", 1)[0].split("#", 1)[0]
    host, _, port = address.rpartition(":")
    return protocol, address, host, port


def _check_endpoints(endpoints: list[str]) -> list[str]:
    """PROTOCOL/HOST:PORT with a port Zenoh can use: in peer mode Zenoh starts with an endpoint
    of port 99999 or a bracket left open, logs a line at most and never connects."""
    for endpoint in endpoints:
        protocol, address, host, port = endpoint_parts(endpoint)
        if "/" not in endpoint or not protocol or not address:
            raise ValueError(
                f"{endpoint!r}: an endpoint is PROTOCOL/HOST:PORT, e.g. tcp/10.0.0.2:7447"
            )
        if protocol not in PORTED_PROTOCOLS:
            continue
        if ":" not in address or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(f"{endpoint!r}: no port from 0 to 65535 after the host")
        if host.startswith("[") != host.endswith("]") or not host.strip("[]"):
            raise ValueError(f"{endpoint!r}: no host (an IPv6 address in brackets: [::1])")
    return endpoints


Endpoints = Annotated[CommaList, AfterValidator(_check_endpoints)]


def _check_namespace(namespace: str | None) -> str | None:
    """A key expression without wildcards or empty chunks: Zenoh's own error for one names
    neither the setting nor the value."""
    if namespace is None:
        return None
    chunks = namespace.split("/")
    if not all(chunks) or any(mark in namespace for mark in "*$#?"):
        raise ValueError(
            "a key expression: no empty chunk (a leading, trailing or double slash) and no "
            "wildcard (* $ # ?)"
        )
    return namespace


LogLevel = Literal["debug", "info", "warning", "error"]

DEFAULT_RESOLUTION_M = 0.05
"""The one global lattice's cell size: depth's tiles and fusion's map must agree on it."""

ResolutionM = Annotated[
    float,
    Field(ge=MIN_RESOLUTION_M, le=MAX_RESOLUTION_M, description="lattice cell size, m"),
]


class OvergridSettings(BaseSettings):
    """Base of every service's settings: the environment prefix, strictness and CLI style."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        extra="forbid",
        validate_default=True,
        cli_kebab_case=True,
        cli_implicit_flags=True,
        cli_exit_on_error=False,  # parse errors become one line (startup_error), not a usage dump
        cli_show_env_vars=True,
        cli_hide_none_type=True,  # "--config Path", not "--config {Path,null}"
        allow_inf_nan=False,  # no setting means "forever" by inf: 1e300 overflowed as well
    )


class OvergridParams(BaseModel):
    """Base of a service's parameters apart from its Zenoh session: what ``overgrid up`` nests and
    hands to its children unchanged. (A settings-style config, so that a service's settings can be
    both this and :class:`ZenohSettings`.)"""

    model_config = SettingsConfigDict(extra="forbid", allow_inf_nan=False)


class ZenohSettings(OvergridSettings):
    """Zenoh session flags shared by every service, after zenoh-python's examples' ``common.py``."""

    mode: Literal["peer", "client", "router"] | None = Field(
        None, description="Zenoh session mode (default: the config file's, else peer)"
    )
    connect: Endpoints = Field(default_factory=list, description="endpoints to connect to")
    listen: Endpoints = Field(default_factory=list, description="endpoints to listen on")
    config: Path | None = Field(
        None, description="Zenoh JSON5 config file (default: $ZENOH_CONFIG if set)"
    )
    no_multicast_scouting: CliToggleFlag[bool] = Field(
        False, description="disable multicast scouting"
    )
    namespace: Annotated[
        str | None,
        BeforeValidator(lambda value: value or None),  # NS=${NS:-} in a template: none
        AfterValidator(_check_namespace),
    ] = Field(
        None, description="Zenoh namespace prefixed to every key: isolates a site or a test run"
    )
    log_level: LogLevel = Field("info", description="log verbosity")


S = TypeVar("S", bound=OvergridSettings)


def _model_fields(model: Any) -> Mapping[str, Any]:
    """Fields of a pydantic model or pydantic dataclass; empty for anything else (a leaf)."""
    if isinstance(model, type) and (issubclass(model, BaseModel) or is_pydantic_dataclass(model)):
        fields: Mapping[str, Any] = getattr(model, "__pydantic_fields__", {})
        return fields
    return {}


def _leaves(model: type[Any], path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """Path of every leaf flag of the tree (a nested model's fields, not the model itself)."""
    for name, field in _model_fields(model).items():
        if SUPPRESS in field.metadata:  # no flag (pydantic_settings.CliSuppress)
            continue
        nested = _model_fields(field.annotation)
        if nested:
            yield from _leaves(field.annotation, (*path, name))
        else:
            yield (*path, name)


def flag_name(path: Sequence[str]) -> str:
    """``("model", "p_hit")`` → ``--model.p-hit``."""
    return "--" + NESTED_FLAG_SEPARATOR.join(path).replace("_", "-")


def env_name(path: Sequence[str]) -> str:
    """``("model", "p_hit")`` → ``OVERGRID_MODEL__P_HIT``."""
    return ENV_PREFIX + ENV_NESTED_DELIMITER.join(path).upper()


def flat_flags(settings_cls: type[BaseSettings]) -> dict[str, list[str]]:
    """Nested flag (without ``--``) → its flat aliases: the class's own ``cli_shortcuts`` first,
    else the leaf's last name wherever no other setting of the tree has that name."""
    explicit = dict(settings_cls.model_config.get("cli_shortcuts") or {})
    taken = {flag for aliases in explicit.values() for flag in _as_list(aliases)}
    leaves = list(_leaves(settings_cls))
    nested_models = [name for name in _model_fields(settings_cls) if (name,) not in leaves]
    names = Counter([path[-1] for path in leaves] + nested_models)
    flags: dict[str, list[str]] = {}
    for path in leaves:
        target = flag_name(path)[2:]
        if target in explicit:
            flags[target] = _as_list(explicit[target])
            continue
        flat = flag_name(path[-1:])[2:]
        if len(path) > 1 and names[path[-1]] == 1 and flat not in taken:
            flags[target] = [flat]
    return flags


def _as_list(aliases: str | list[str]) -> list[str]:
    return [aliases] if isinstance(aliases, str) else list(aliases)


def _setting_path(settings_cls: type[BaseModel], loc: Sequence[int | str]) -> list[str]:
    """The settings path in an error's location (pydantic adds union members and list indices)."""
    path: list[str] = []
    model: Any = settings_cls
    for part in loc:
        fields = _model_fields(model)
        if not isinstance(part, str) or part not in fields:
            break
        path.append(part)
        model = fields[part].annotation
    return path


def describe_validation_error(error: ValidationError, settings_cls: type[BaseSettings]) -> str:
    """One line naming the flag (its flat alias too) and env var of each bad setting, and why."""
    flats = flat_flags(settings_cls)
    parts = []
    for item in error.errors():
        path = _setting_path(settings_cls, item["loc"])
        message = item["msg"].removeprefix("Value error, ")
        if not path:  # a check across settings names them in its own message
            parts.append(f"invalid settings: {message}")
            continue
        flag = flag_name(path)
        aliases = " ".join(f"--{alias}" for alias in flats.get(flag[2:], []))
        names = (f"{aliases} ({flag})" if aliases else flag) + f" / {env_name(path)}"
        got = item.get("input")
        said = ", got " in message  # the check named the value itself: once is enough
        suffix = "" if got is None or isinstance(got, dict) or said else f" (got {got!r})"
        parts.append(f"invalid setting {names}: {message}{suffix}")
    return "; ".join(parts)


STARTUP_ERROR_EXIT = 2


def startup_error(message: str) -> NoReturn:
    """Stop start-up with one line naming the setting or file and what is wrong (exit 2)."""
    print(" ".join(line.strip() for line in message.splitlines() if line.strip()), file=sys.stderr)
    raise SystemExit(STARTUP_ERROR_EXIT)


_UNDECODABLE = re.compile(r'error parsing value for field "(\w+)" from source "EnvSettingsSource"')


def load_settings(settings_cls: type[S], **values: Any) -> S:
    """Validate ``values`` (they win over env); exit with one line naming the bad settings."""
    try:
        return settings_cls(**values)
    except ValidationError as error:
        startup_error(describe_validation_error(error, settings_cls))
    except SettingsError as error:  # an env value that is not the JSON its nested model needs
        undecodable = _UNDECODABLE.search(str(error))
        if undecodable is None:
            raise
        startup_error(f"invalid setting {env_name([undecodable[1]])}: not valid JSON ({error})")


def parse_settings(
    settings_cls: type[S], argv: Sequence[str] | None, prog: str, description: str
) -> S:
    """Flags (``argv``, default ``sys.argv[1:]``) over ``OVERGRID_*`` env over the models' defaults."""
    try:
        source: CliSettingsSource[Any] = CliSettingsSource(
            settings_cls, cli_prog_name=prog, cli_shortcuts=flat_flags(settings_cls)
        )
        source.root_parser.description = description
        parsed = source(args=list(sys.argv[1:] if argv is None else argv))
        return load_settings(settings_cls, _cli_settings_source=parsed)
    except SettingsError as error:
        startup_error(f"{prog}: {str(error).removeprefix('error parsing CLI: ')} (see --help)")
