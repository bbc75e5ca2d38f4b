"""Shared plumbing of the experiment commands: building a validated config and printing results."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from ..config import ConfigError, from_dict, parse_toml
from ..model.twin import merge, preset_overrides

__all__ = ["build_config", "print_json_last"]

T = TypeVar("T")


def build_config(cls: type[T], *, config_file: str | Path | None = None, preset: str | None = None,
                 overrides: dict | None = None, twin_key: str = "twin") -> T:
    """Defaults, then ``config_file`` (TOML), then the named ``preset`` (endoscope settings of the
    twin), then ``overrides`` (nested dict, e.g. from command-line flags); validated at the end.

    The file is first validated on its own, so its problems are reported together and name the
    file (and a scalar where a table belongs, such as ``twin = 5``, cannot vanish in the merge)."""
    data: dict[str, Any] = {}
    if config_file is not None:
        where = f"--config {config_file}"
        data = parse_toml(config_file, "--config")
        try:
            from_dict(cls, data)
        except ConfigError as exc:
            raise ConfigError(errors=exc.errors, where=where) from None
    if preset is not None:
        data = merge(data, {twin_key: merge(preset_overrides(preset), {"preset": preset})})
    if overrides:
        data = merge(data, overrides)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(errors=exc.errors, where="options" if config_file is None else
                          f"options with --config {config_file}") from None


def print_json_last(summary: dict) -> None:
    """Print ``summary`` as one JSON object on the last stdout line (for --json)."""
    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        if isinstance(v, float) and v != v:
            return None
        if hasattr(v, "item"):
            return clean(v.item())
        return v
    print(json.dumps(clean(summary)), flush=True)

