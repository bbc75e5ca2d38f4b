"""Typed, validated configuration shared by every part of targetlock.

Each setting is a dataclass field declared with :func:`param`, which records its unit, its
allowed range and a one-line description. :func:`validate` checks a whole (nested) config and
refuses a bad value with the dotted field name, the value and the allowed range, so a typo in a
TOML file never reaches a motor. :func:`from_dict` refuses unknown keys for the same reason.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
import types
import typing
from dataclasses import field, fields, is_dataclass
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError, InputFileError

__all__ = ["ConfigError", "param", "validate", "from_dict", "to_dict", "load_toml", "save_toml", "replace_path",
           "describe", "read_text_file", "parse_toml", "field_info", "nest"]

T = TypeVar("T")


def param(default: Any, *, unit: str = "", lo: float | None = None, hi: float | None = None,
          choices: tuple | None = None, doc: str = "", lo_open: bool = False, file: bool = False) -> Any:
    """Declare a config field with its unit, allowed range [lo, hi] (or choices) and meaning.

    ``file=True`` marks a path to an input file: run folders keep a copy of it."""
    meta = {"unit": unit, "lo": lo, "hi": hi, "choices": choices, "doc": doc, "lo_open": lo_open, "file": file}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def _range_text(meta: typing.Mapping[str, Any]) -> str:
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("lo"), meta.get("hi")
    left = "(" if meta.get("lo_open") else "["
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    return f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]{unit}"


def _check_value(name: str, value: Any, meta: typing.Mapping[str, Any]) -> str | None:
    """The problem with one value, or None."""
    choices = meta.get("choices")
    if choices is not None:
        if value not in choices:
            return f"{name} = {value!r} is not allowed; allowed: {_range_text(meta)}"
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    lo, hi = meta.get("lo"), meta.get("hi")
    bad = not math.isfinite(value)
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        bad = True
    if hi is not None and value > hi:
        bad = True
    return f"{name} = {value!r} is out of range; allowed: {_range_text(meta)}" if bad else None


def _fixed_length(tp: Any) -> int | None:
    """Length of a fixed-length tuple type such as ``tuple[float, float]``; None for ``tuple[float, ...]``."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and args and args[-1] is not Ellipsis:
        return len(args)
    return None


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    """Resolved field types of a config dataclass (cached: resolving them is most of a config's cost)."""
    return typing.get_type_hints(cls)


def _collect(cfg: Any, prefix: str, errors: list[str], checks: bool = True) -> None:
    n_before = len(errors)
    hints = _hints(cfg.__class__)
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if is_dataclass(value):
            _collect(value, name + ".", errors, checks)
            continue
        if isinstance(value, (list, tuple)):
            n = _fixed_length(hints.get(f.name))
            if n is not None and len(value) != n:
                errors.append(f"{name} = {list(value)!r} needs exactly {n} values")
            elif f.metadata:
                errors += [e for i, v in enumerate(value) if (e := _check_value(f"{name}[{i}]", v, f.metadata))]
        elif f.metadata and (e := _check_value(name, value, f.metadata)):
            errors.append(e)
    # Cross-field rules (``check(prefix)`` of the config class) only make sense on valid fields.
    post = getattr(cfg, "check", None)
    if checks and callable(post) and len(errors) == n_before:
        try:
            post(prefix)
        except ConfigError as exc:
            errors += exc.errors


def validate(cfg: Any, prefix: str = "") -> Any:
    """Check every field of a (nested) config dataclass; return it unchanged or raise one
    ConfigError listing every problem found."""
    errors: list[str] = []
    _collect(cfg, prefix, errors)
    if errors:
        raise ConfigError(errors=errors)
    return cfg


_BAD = object()   # marks a value that failed coercion (its error is already collected): the default is kept


def _coerce(name: str, tp: Any, value: Any, errors: list[str]) -> Any:
    origin = typing.get_origin(tp)
    if is_dataclass(tp):
        if not isinstance(value, dict):
            errors.append(f"{name} must be a table of settings ([{name}] in TOML), got {value!r}")
            return _BAD
        return _build(tp, value, name + ".", errors)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        members = [a for a in typing.get_args(tp) if a is not type(None)]
        return _coerce(name, members[0], value, errors)
    expect = {float: "a number", int: "a whole number", bool: "true or false", str: "text"}
    if tp in expect:
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool) if tp is float else
              isinstance(value, int) and not isinstance(value, bool) if tp is int else isinstance(value, tp))
        if not ok:
            errors.append(f"{name} must be {expect[tp]}, got {value!r}")
            return _BAD
        return float(value) if tp is float else value
    if origin in (tuple, list):
        args = typing.get_args(tp) or (Any,)
        if not isinstance(value, (list, tuple)):
            errors.append(f"{name} must be a list, got {value!r}")
            return _BAD
        n = _fixed_length(tp)
        if n is not None and len(value) != n:
            errors.append(f"{name} = {list(value)!r} needs exactly {n} values")
            return _BAD
        items = [_coerce(f"{name}[{i}]", args[0 if n is None else i], v, errors) for i, v in enumerate(value)]
        if any(v is _BAD for v in items):
            return _BAD
        return tuple(items) if origin is tuple else items
    return value


def _build(cls: Any, data: dict, prefix: str, errors: list[str]) -> Any:
    hints = _hints(cls)
    known = {f.name: f for f in fields(cls) if f.init}
    unknown = sorted(set(data) - set(known))
    if unknown:
        errors.append(f"unknown setting{'s' if len(unknown) > 1 else ''} {', '.join(prefix + u for u in unknown)}; "
                      f"known{' in ' + prefix[:-1] if prefix else ''}: {', '.join(sorted(known))}")
    kwargs = {k: _coerce(prefix + k, hints[k], v, errors) for k, v in data.items() if k in known}
    # Bad values keep their defaults, so the remaining fields can still be range-checked.
    return cls(**{k: v for k, v in kwargs.items() if v is not _BAD})


def from_dict(cls: type[T], data: dict, prefix: str = "") -> T:
    """Build config ``cls`` from a plain dict (e.g. parsed TOML); unknown keys are refused.

    Every problem (unknown key, wrong type or shape, out of range, cross-field rule) is collected
    and raised as one :class:`ConfigError` listing them all."""
    errors: list[str] = []
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or 'config'} must be a table of settings, got {data!r}")
    obj = _build(cls, data, prefix, errors)
    if not prefix:   # cross-field rules only once every field is of the right type
        _collect(obj, prefix, errors, checks=not errors)
    if errors:
        raise ConfigError(errors=errors)
    return obj


def read_text_file(path: str | Path, what: str) -> str:
    """Text of a UTF-8 file (a BOM is accepted); :class:`InputFileError` naming ``what`` and the
    file if it is missing, a folder, unreadable or not UTF-8."""
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(f"{what} {p}: no such file; check the path") from None
    except IsADirectoryError:
        raise InputFileError(f"{what} {p}: is a folder, a file is needed") from None
    except PermissionError:
        raise InputFileError(f"{what} {p}: permission denied; make it readable") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{what} {p}: not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except OSError as exc:
        raise InputFileError(f"{what} {p}: cannot read ({exc.strerror or exc})") from None


def to_dict(cfg: Any) -> dict:
    """Plain dict of a config dataclass (tuples become lists, None values are dropped for TOML)."""
    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if x is not None}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return clean(dataclasses.asdict(cfg))


def parse_toml(path: str | Path, what: str = "config file") -> dict:
    """The parsed TOML of a file; :class:`InputFileError` / :class:`ConfigError` naming the file."""
    text = read_text_file(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {path}: not valid TOML: {exc}") from None


def load_toml(cls: type[T], path: str | Path, what: str = "config file") -> T:
    """Read and validate a TOML file into config ``cls``; errors name the file and every bad setting."""
    data = parse_toml(path, what)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(errors=exc.errors, where=f"{what} {path}") from None


def save_toml(cfg: Any, path: str | Path) -> None:
    import tomli_w   # only needed when a config is written
    Path(path).write_text(tomli_w.dumps(to_dict(cfg)), encoding="utf-8")


def commented_toml(data: dict, note: str) -> str:
    """TOML text of ``data`` under a comment header: each line of ``note`` as a ``#`` line."""
    import tomli_w   # only needed when a config is written
    return "".join(f"# {line}\n" for line in note.splitlines()) + tomli_w.dumps(data)


def _replaced(cfg: Any, dotted: str, value: Any) -> Any:
    head, _, rest = dotted.partition(".")
    if head not in {f.name for f in fields(cfg)}:
        raise ConfigError(f"unknown setting {dotted!r}")
    if rest:
        return dataclasses.replace(cfg, **{head: _replaced(getattr(cfg, head), rest, value)})
    return dataclasses.replace(cfg, **{head: value})


def replace_path(cfg: T, dotted: str, value: Any) -> T:
    """Return a copy of ``cfg`` with the nested field ``a.b.c`` set to ``value``; the whole config is
    validated, so errors carry the full dotted name and cross-field rules apply."""
    return validate(_replaced(cfg, dotted, value))


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


def field_info(cls: Any, dotted: str) -> tuple[Any, dict, Any]:
    """(type, param metadata, default) of the nested field ``a.b.c`` of config class ``cls``."""
    head, _, rest = dotted.partition(".")
    known = {f.name: f for f in fields(cls)}
    if head not in known:
        raise ConfigError(f"unknown setting {dotted!r}; known: {', '.join(sorted(known))}")
    tp = _hints(cls)[head]
    if rest:
        if not is_dataclass(tp):
            raise ConfigError(f"{head} has no settings below it (got {dotted!r})")
        return field_info(tp, rest)
    f = known[head]
    default = f.default if f.default is not dataclasses.MISSING else (
        f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
    return tp, dict(f.metadata), default


def nest(dotted: str, value: Any) -> dict:
    """``nest("a.b", 1) == {"a": {"b": 1}}``: one override as a nested dict."""
    out: Any = value
    for key in reversed(dotted.split(".")):
        out = {key: out}
    return out
