"""The digital twin's configuration: endoscope, drives, camera and scene, with named presets.

A configuration is built from the defaults, then a preset (``presets/NAME.toml``), then a user's
TOML file, then command-line overrides; every step is validated (see :mod:`targetlock.config`).
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources

from ..config import ConfigError, from_dict, param
from ..presets import PRESETS
from .camera import CameraParams
from .drives import DriveParams
from .endoscope import EndoscopeParams
from .scene import SceneParams

__all__ = ["TwinConfig", "PRESETS", "preset_overrides", "merge", "twin_config"]


@dataclass(frozen=True)
class TwinConfig:
    """Everything the simulated rig needs to behave like the TeleFLEX rig."""
    endoscope: EndoscopeParams = field(default_factory=EndoscopeParams)
    drive: DriveParams = field(default_factory=DriveParams)
    camera: CameraParams = field(default_factory=CameraParams)
    scene: SceneParams = field(default_factory=SceneParams)
    model_dt: float = param(0.001, unit="s", lo=1e-5, hi=0.02, doc="internal integration step of the endoscope model")
    preset: str = param("calibrated", choices=PRESETS, doc="named endoscope preset the config started from")


def preset_overrides(name: str) -> dict:
    """The settings a named preset changes, as a nested dict."""
    if name not in PRESETS:
        raise ConfigError(f"preset = {name!r} is not known; allowed: {', '.join(PRESETS)}")
    text = resources.files("targetlock.presets").joinpath(f"{name}.toml").read_text()
    return tomllib.loads(text)


def merge(base: dict, override: dict) -> dict:
    """Recursive dict merge: values of ``override`` win, tables merge."""
    out = dict(base)
    for k, v in override.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def twin_config(preset: str = "calibrated", overrides: dict | None = None) -> TwinConfig:
    """A validated :class:`TwinConfig` from a preset plus optional nested overrides."""
    data = merge(preset_overrides(preset), overrides or {})
    data["preset"] = preset
    return from_dict(TwinConfig, data)
