"""targetlock: keep a flexible endoscope's camera locked on a selected target.

Layout (design notes §1): ``model`` (physics of the endoscope, drives, camera, scene),
``rig`` (what the loop talks to: simulated twin or hardware), ``loop`` (fixed-rate control loop
and clocks), ``controllers`` (PI, PI + hysteresis compensation, inverse kinematics),
``vision`` (renderer and trackers), ``experiments`` (the report's procedures, run folders) and
``interfaces`` (CANopen drives, NatNet motion capture).

The small public API (reference: docs/api.md) is importable from here; names are loaded on first
use, so ``import targetlock`` stays cheap::

    import targetlock
    cfg = targetlock.load_config("runs/run-.../config.toml")      # or targetlock.RunConfig(...)
    summary = targetlock.run(cfg, out="runs/mine")                # dict: rms_px, peak_px, ...
"""
from __future__ import annotations

import importlib
import os
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# x86-64 feature flags of the level the numba kernels are compiled for (x86-64-v3: AVX2, FMA, BMI2)
_X86_64_V3 = ("avx2", "fma", "bmi2", "f16c", "movbe")


def _has_x86_64_v3() -> bool:
    """Whether this machine is x86-64 with the x86-64-v3 features (:data:`_X86_64_V3`)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:
            flags = next((line.split(":", 1)[1].split() for line in fh if line.startswith("flags")), [])
    except OSError:
        try:   # not Linux: ask LLVM (numba's own dependency; slower to import)
            from llvmlite import binding
            flags = [k for k, v in binding.get_host_cpu_features().items() if v]
        except Exception:   # noqa: BLE001 - no numba here: nothing to compile for
            return False
    return all(f in flags for f in _X86_64_V3)


def _pin_numba_cpu() -> None:
    """Compile the numba kernels for one x86-64 level, x86-64-v3, on every x86-64 machine that has it.

    The renderer's kernels use fastmath, and LLVM tunes them to the host CPU: on an AVX-512 machine
    (``emeraldrapids``) the rendered frames differed in their last bits from an AVX2 machine's, and
    the tracker's frame-by-frame decisions on them with it (18 vision tests pinned to recorded
    sequences failed there). With one target the frames, ``vision-eval``'s figures and the tests are
    the same on every x86-64-v3 machine. Older or other CPUs compile for themselves. A
    ``NUMBA_CPU_NAME`` the user set wins."""
    if "NUMBA_CPU_NAME" in os.environ or not _has_x86_64_v3():
        return
    os.environ["NUMBA_CPU_NAME"] = "x86-64-v3"
    if "numba" in sys.modules:   # imported before us: its configuration is read again
        sys.modules["numba"].core.config.reload_config()


_pin_numba_cpu()

# public name -> module that defines it (imported lazily by __getattr__)
_LAZY = {
    # configuration
    "RunConfig": "targetlock.experiments.target_lock",
    "TwinConfig": "targetlock.model.twin",
    "ControllerConfig": "targetlock.controllers.base",
    "LoopConfig": "targetlock.loop.runner",
    "CameraParams": "targetlock.model.camera",
    "SceneParams": "targetlock.model.scene",
    "HardwareRigConfig": "targetlock.interfaces.rigfile",
    "from_dict": "targetlock.config",
    "to_dict": "targetlock.config",
    "load_toml": "targetlock.config",
    "save_toml": "targetlock.config",
    "replace_path": "targetlock.config",
    "describe": "targetlock.config",
    # interfaces a rig or a controller implements
    "Rig": "targetlock.rig.base",
    "Drives": "targetlock.rig.base",
    "ObservationSource": "targetlock.rig.base",
    "Observation": "targetlock.rig.base",
    "DriveFault": "targetlock.rig.base",
    "Controller": "targetlock.controllers.base",
    "SimulatedRig": "targetlock.rig.simulated",
    "RunFolder": "targetlock.experiments.runfolder",
    # errors
    "TargetlockError": "targetlock.errors",
    "ConfigError": "targetlock.errors",
}

__all__ = ["__version__", "run", "load_config", *_LAZY]

if TYPE_CHECKING:   # for type checkers and editors; at run time these load on first use
    from .config import describe, from_dict, load_toml, replace_path, save_toml, to_dict
    from .controllers.base import Controller, ControllerConfig
    from .errors import ConfigError, TargetlockError
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig
    from .interfaces.rigfile import HardwareRigConfig
    from .loop.runner import LoopConfig
    from .model.camera import CameraParams
    from .model.scene import SceneParams
    from .model.twin import TwinConfig
    from .rig.base import DriveFault, Drives, Observation, ObservationSource, Rig
    from .rig.simulated import SimulatedRig


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'targetlock' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


def load_config(path: str | Path) -> RunConfig:
    """The validated :class:`RunConfig` of a TOML file (e.g. a run folder's ``config.toml``);
    raises :class:`ConfigError` listing every bad setting."""
    from .config import load_toml
    from .experiments.target_lock import RunConfig
    return load_toml(RunConfig, path)


def run(config: RunConfig | dict | str | Path | None = None, *, out: str | Path | None = None,
        overwrite: bool = False, progress: bool = False) -> dict:
    """Run the closed-loop target lock on the digital twin, like ``targetlock run``.

    ``config``: a :class:`RunConfig`, a nested dict of settings (as in TOML), a TOML file, or
    None for the defaults; validated first (:class:`ConfigError`). ``out``: a run folder to write
    (config, time series, plots, run.log); an earlier run there is replaced only with
    ``overwrite``. Returns the summary: errors in px (``rms_px``, ``peak_px``, ``p95_px``,
    ``mean_px``), ``lost_fraction``, ``tip_range_deg`` and timing; keys starting with ``_`` hold
    the recorded arrays.
    """
    from .config import from_dict, validate
    from .experiments.runfolder import RunFolder
    from .experiments.target_lock import RunConfig, run_target_lock
    if config is None:
        cfg = RunConfig()
    elif isinstance(config, RunConfig):
        cfg = config
    elif isinstance(config, dict):
        cfg = from_dict(RunConfig, config)
    else:
        cfg = load_config(config)
    validate(cfg)
    if out is None:
        return run_target_lock(cfg, progress=progress)
    with RunFolder("run", cfg, out, overwrite=overwrite) as folder:
        return run_target_lock(folder.config, folder, progress=progress)
