"""TOML configuration into typed, frozen dataclasses.

``load(cls, path)`` reads a TOML file and builds ``cls``; unknown keys, wrong types and values
outside a field's declared range raise :class:`~handfe.errors.ConfigError` naming the file, the
key (dotted path) and the value. Ranges are declared in the field metadata::

    @dataclass(frozen=True)
    class Plate:
        angle_deg: float = field(default=15.0, metadata=bounds(0.0, 90.0))
        mode: str = field(default="force", metadata=choices("force", "displacement"))
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from handfe.errors import ConfigError

T = TypeVar("T")


def toml_string(s: str) -> str:
    """``s`` as a TOML basic string (quotes, backslashes, newlines and non-ASCII escaped;
    JSON's string escapes are a subset of TOML's), so ``tomllib`` reads back ``s``."""
    return json.dumps(s)


def bounds(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False) -> dict[str, Any]:
    """Field metadata: numeric value must lie in [lo, hi] (open ends on request)."""
    return {"bounds": (lo, hi, lo_open, hi_open)}


def choices(*allowed: str) -> dict[str, Any]:
    """Field metadata: value must be one of ``allowed``."""
    return {"choices": tuple(allowed)}


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; a missing file or a syntax error becomes a ConfigError naming it."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: file not found")
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None


def load(cls: type[T], path: str | Path) -> T:
    """Load ``cls`` (a dataclass) from the TOML file at ``path``."""
    return from_dict(cls, load_toml(path), source=str(path))


def from_dict(cls: type[T], data: Mapping[str, Any], *, source: str = "<dict>",
              prefix: str = "") -> T:
    """Build dataclass ``cls`` from a mapping, checking keys, types and ranges."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: {prefix or 'top level'} must be a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        key = f"{prefix}{unknown[0]}"
        allowed = ", ".join(sorted(fields))
        raise ConfigError(f"{source}: unknown key '{key}' (allowed here: {allowed})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key = f"{prefix}{name}"
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{source}: missing required key '{key}'")
            continue
        value = _convert(hints[name], data[name], source=source, key=key)
        _check_meta(f, value, source=source, key=key)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{source}: {prefix or 'top level'}: {exc}") from None


def _convert(tp: Any, value: Any, *, source: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, source=source, key=key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{source}: '{key}' = {value!r}: bad value")
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, source=source, prefix=f"{key}.")
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected a list")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{source}: '{key}' = {value!r}: expected {len(args)} values")
            return tuple(_convert(a, v, source=source, key=f"{key}[{i}]")
                         for i, (a, v) in enumerate(zip(args, value, strict=True)))
        inner = args[0] if args else Any
        out = [_convert(inner, v, source=source, key=f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected a table")
        vt = args[1] if len(args) == 2 else Any
        return {str(k): _convert(vt, v, source=source, key=f"{key}.{k}") for k, v in value.items()}
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected a number")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected an integer")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected a string")
        return value
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: '{key}' = {value!r}: expected a path string")
        return Path(value)
    return value


def _check_meta(f: dataclasses.Field, value: Any, *, source: str, key: str) -> None:
    meta = f.metadata
    if "choices" in meta and value not in meta["choices"]:
        allowed = ", ".join(meta["choices"])
        raise ConfigError(f"{source}: '{key}' = {value!r}: must be one of {allowed}")
    if "bounds" in meta and value is not None:
        lo, hi, lo_open, hi_open = meta["bounds"]
        vals = value if isinstance(value, list | tuple) else [value]
        for v in vals:
            bad = (lo is not None and (v < lo or (lo_open and v == lo))) or (
                hi is not None and (v > hi or (hi_open and v == hi)))
            if bad:
                lo_s = "-inf" if lo is None else f"{lo:g}"
                hi_s = "inf" if hi is None else f"{hi:g}"
                rng = f"{'(' if lo_open else '['}{lo_s}, {hi_s}{')' if hi_open else ']'}"
                raise ConfigError(f"{source}: '{key}' = {value!r}: out of range {rng}")
