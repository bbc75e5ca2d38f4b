"""Typed, validated configuration shared by every part of targetlock.

Each setting is a dataclass field declared with :func:`param`, which records its unit, its
allowed range and a one-line description. :func:`validate` checks a whole (nested) config and
refuses a bad value with the dotted field name, the value and the allowed range, so a typo in a
TOML file never reaches a motor. :func:`from_dict` refuses unknown keys for the same reason.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, TypeVar

import tomli_w

__all__ = ["ConfigError", "param", "validate", "from_dict", "to_dict", "load_toml", "save_toml", "replace_path", "describe"]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


def param(default: Any, *, unit: str = "", lo: float | None = None, hi: float | None = None,
          choices: tuple | None = None, doc: str = "", lo_open: bool = False) -> Any:
    """Declare a config field with its unit, allowed range [lo, hi] (or choices) and meaning."""
    meta = {"unit": unit, "lo": lo, "hi": hi, "choices": choices, "doc": doc, "lo_open": lo_open}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


def _range_text(meta: dict) -> str:
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("lo"), meta.get("hi")
    left = "(" if meta.get("lo_open") else "["
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    return f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]{unit}"


def _check_value(name: str, value: Any, meta: dict) -> None:
    choices = meta.get("choices")
    if choices is not None:
        if value not in choices:
            raise ConfigError(f"{name} = {value!r} is not allowed; allowed: {_range_text(meta)}")
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    lo, hi = meta.get("lo"), meta.get("hi")
    bad = not math.isfinite(value)
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        bad = True
    if hi is not None and value > hi:
        bad = True
    if bad:
        raise ConfigError(f"{name} = {value!r} is out of range; allowed: {_range_text(meta)}")


def validate(cfg: Any, prefix: str = "") -> Any:
    """Check every field of a (nested) config dataclass; return it unchanged or raise ConfigError."""
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if is_dataclass(value):
            validate(value, prefix=name + ".")
        elif isinstance(value, (list, tuple)) and f.metadata:
            for i, v in enumerate(value):
                _check_value(f"{name}[{i}]", v, f.metadata)
        elif f.metadata:
            _check_value(name, value, f.metadata)
    post = getattr(cfg, "check", None)
    if callable(post):
        post(prefix)
    return cfg


def _coerce(name: str, tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{name} must be a table of settings, got {value!r}")
        return from_dict(tp, value, prefix=name + ".")
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(name, args[0], value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name} must be a whole number, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be text, got {value!r}")
        return value
    if origin in (tuple, list):
        (inner, *_) = typing.get_args(tp) or (Any,)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name} must be a list, got {value!r}")
        out = [_coerce(f"{name}[{i}]", inner, v) for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    return value


def from_dict(cls: type[T], data: dict, prefix: str = "") -> T:
    """Build config ``cls`` from a plain dict (e.g. parsed TOML); unknown keys are refused."""
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls) if f.init}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"unknown setting{'s' if len(unknown) > 1 else ''} "
                          f"{', '.join(prefix + u for u in unknown)}; known: {', '.join(sorted(known))}")
    kwargs = {k: _coerce(prefix + k, hints[k], v) for k, v in data.items()}
    obj = cls(**kwargs)
    if not prefix:
        validate(obj)
    return obj


def to_dict(cfg: Any) -> dict:
    """Plain dict of a config dataclass (tuples become lists, None values are dropped for TOML)."""
    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if x is not None}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return clean(dataclasses.asdict(cfg))


def load_toml(cls: type[T], path: str | Path) -> T:
    with open(path, "rb") as fh:
        try:
            data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def save_toml(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(tomli_w.dumps(to_dict(cfg)))


def replace_path(cfg: T, dotted: str, value: Any) -> T:
    """Return a copy of ``cfg`` with the nested field ``a.b.c`` set to ``value`` (validated)."""
    head, _, rest = dotted.partition(".")
    if head not in {f.name for f in fields(cfg)}:
        raise ConfigError(f"unknown setting {dotted!r}")
    if rest:
        return dataclasses.replace(cfg, **{head: replace_path(getattr(cfg, head), rest, value)})
    return validate(dataclasses.replace(cfg, **{head: value}))


def describe(cls: type, prefix: str = "") -> list[dict]:
    """Rows (name, default, unit, range, doc) for documentation of every field of ``cls``."""
    rows = []
    for f in fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if is_dataclass(default):
            rows += describe(type(default), prefix + f.name + ".")
            continue
        rows.append({"name": prefix + f.name, "default": default, "unit": f.metadata.get("unit", ""),
                     "range": _range_text(f.metadata) if f.metadata else "", "doc": f.metadata.get("doc", "")})
    return rows
