"""Shared plumbing of the experiment commands: building a validated config and printing results."""
from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from ..config import ConfigError, from_dict
from ..model.twin import merge, preset_overrides

__all__ = ["build_config", "print_json_last"]

T = TypeVar("T")


def build_config(cls: type[T], *, config_file: str | Path | None = None, preset: str | None = None,
                 overrides: dict | None = None, twin_key: str = "twin") -> T:
    """Defaults, then ``config_file`` (TOML), then the named ``preset`` (endoscope settings of the
    twin), then ``overrides`` (nested dict, e.g. from command-line flags); validated at the end."""
    data: dict[str, Any] = {}
    if config_file is not None:
        try:
            data = tomllib.loads(Path(config_file).read_text())
        except FileNotFoundError:
            raise ConfigError(f"--config {config_file}: no such file") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"--config {config_file}: not valid TOML: {exc}") from None
    if preset is not None:
        data = merge(data, {twin_key: merge(preset_overrides(preset), {"preset": preset})})
    if overrides:
        data = merge(data, overrides)
    return from_dict(cls, data)


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

