"""What a controller assumes about the plant, kept apart from what the (simulated) plant is.

A real lab knows its endoscope only roughly: the nominal ``calibrated`` preset, the report's video
latency (0.4 s) and working distance (12 cm), and the camera's nominal intrinsics. The controllers
get exactly that (:class:`KnowledgeConfig`, ``source = "nominal"``), never silently the twin's truth.
``source = "oracle"`` hands over the simulated plant's true parameters instead; every result made that
way is labelled "oracle" (the run summary's ``knowledge`` field). ``"oracle-endoscope"``,
``"oracle-latency"``, ``"oracle-depth"`` and ``"oracle-camera"`` (focal lengths) hand over that one item
of the truth and the nominal rest: which missing knowledge costs a controller how much (labelled so).

The target's distance is known as an assumed value (``depth``, the prior Jacobian's) and the range it
can be in (``nearest_depth`` .. ``farthest_depth``, by default 1-15 cm): the lock sizes its first steps
for the nearest, before the image has shown it the Jacobian. A source that knows the depth (``oracle``,
``oracle-depth``) knows that range as the one true distance.

A lab that has identified its scope hands that to the controller with ``endoscope_file``: a TOML whose
``[twin.endoscope]`` (what ``targetlock identify`` writes, ``fitted.toml``) or ``[knowledge.endoscope]``
table overrides the preset's endoscope parameters. (Handing ``adaptive`` its true endoscope and nothing
else brings its median on six robustness sets from 23.5 to 16.9 px; the oracle, which also knows the
distance, 11.2: see docs/research.md.)
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from ..config import from_dict, param, parse_toml, to_dict
from ..errors import ConfigError
from ..model.camera import CameraParams
from ..model.endoscope import EndoscopeParams
from ..model.twin import PRESETS, TwinConfig, merge, twin_config

__all__ = ["KnowledgeConfig", "Knowledge", "resolve_knowledge", "nominal_knowledge", "KNOWLEDGE_SOURCES"]

ORACLE_ITEMS = ("endoscope", "latency", "depth", "camera")
KNOWLEDGE_SOURCES = ("nominal", "oracle") + tuple(f"oracle-{item}" for item in ORACLE_ITEMS)


@dataclass(frozen=True)
class KnowledgeConfig:
    """The controller's own assumptions about endoscope, camera, latency and target depth."""
    source: str = param("nominal", choices=KNOWLEDGE_SOURCES,
                        doc="'nominal': the values below; 'oracle': the simulated plant's truth (labelled oracle); "
                            "'oracle-endoscope' / -latency / -depth / -camera: that item of the truth, the rest nominal")
    preset: str = param("calibrated", choices=PRESETS, doc="endoscope preset the controller assumes")
    endoscope_file: str = param("", file=True,
                                doc="TOML whose [twin.endoscope] (targetlock identify's fitted.toml) or "
                                    "[knowledge.endoscope] table overrides the preset's endoscope parameters")
    latency: float = param(0.4, unit="s", lo=0.0, hi=5.0,
                           doc="assumed video latency (report: 0.4 s); frames are stamped with it, as a rig stamps them")
    depth: float = param(0.12, unit="m", lo=0.005, hi=2.0, doc="assumed target distance (report: 12 cm)")
    nearest_depth: float = param(0.01, unit="m", lo=0.005, hi=2.0,
                                 doc="nearest the target can be: the lock's first steps, before it has learned the image "
                                     "Jacobian, are sized for it (default: 1 cm, the nearest the lock is made for; a lab "
                                     "that knows its working distance sets it there)")
    farthest_depth: float = param(0.15, unit="m", lo=0.005, hi=2.0,
                                  doc="farthest the target can be (bounds the smallest image Jacobian the lock accepts)")
    fx: float = param(300.0, unit="px", lo=1.0, hi=1e5, doc="assumed focal length along x")
    fy: float = param(300.0, unit="px", lo=1.0, hi=1e5, doc="assumed focal length along y")

    def check(self, prefix: str = "") -> None:
        if not self.nearest_depth <= self.depth <= self.farthest_depth:
            raise ConfigError(f"{prefix}depth = {self.depth:g} m lies outside {prefix}nearest_depth .. "
                              f"{prefix}farthest_depth = {self.nearest_depth:g} .. {self.farthest_depth:g} m; "
                              f"allowed: the assumed distance within the range the target can be at")


@dataclass(frozen=True)
class Knowledge:
    """Resolved assumptions handed to a controller (SI units, pixels)."""
    endoscope: EndoscopeParams
    camera: CameraParams          # intrinsics assumed; its ``latency`` is the assumed latency
    depth: float                  # m
    depth_range: tuple[float, float]   # m, the nearest and farthest the target can be (contains depth)
    source: str                   # one of KNOWLEDGE_SOURCES
    preset: str                   # the endoscope preset these parameters came from
    endoscope_from: str = ""      # what overrode the preset's endoscope parameters, if anything (a file's name)

    @property
    def latency(self) -> float:
        return self.camera.latency

    @property
    def label(self) -> str:
        """One line saying which knowledge this is (for summaries and tables)."""
        if self.source == "oracle":
            return "oracle (the plant's true parameters)"
        scope = f"preset {self.preset}" + (f" + {self.endoscope_from}" if self.endoscope_from else "")
        near, far = (100 * d for d in self.depth_range)
        nominal = (f"{scope}, latency {self.latency:g} s, depth {100 * self.depth:g} cm ({near:g}-{far:g} cm), "
                   f"f {self.camera.fx:g} px")
        if self.source.startswith("oracle-"):
            item = self.source.removeprefix("oracle-")
            return f"oracle {item} only (the plant's true {item}; otherwise {nominal})"
        return f"nominal ({nominal})"


def resolve_knowledge(k: KnowledgeConfig, plant: TwinConfig) -> Knowledge:
    """The assumptions a controller gets. Only the image size and principal point are taken from the
    plant's camera (they are read off the image itself); everything else is the configured nominal,
    unless ``k.source`` is ``"oracle"`` (all of the plant's truth) or ``"oracle-<item>"`` (that item's)."""
    truth = plant.scene.distance
    if k.source == "oracle":
        return Knowledge(endoscope=plant.endoscope, camera=plant.camera, depth=truth, source="oracle",
                         preset=plant.preset, depth_range=(truth, truth))
    item = k.source.removeprefix("oracle-") if k.source.startswith("oracle-") else ""
    endoscope = plant.endoscope if item == "endoscope" else twin_config(k.preset).endoscope
    from_file = k.endoscope_file if item != "endoscope" else ""
    if from_file:
        endoscope = _load_endoscope_file(from_file, endoscope)
    fx, fy = (plant.camera.fx, plant.camera.fy) if item == "camera" else (k.fx, k.fy)
    camera = dataclasses.replace(CameraParams(), width=plant.camera.width, height=plant.camera.height,
                                 cx=plant.camera.cx, cy=plant.camera.cy, fps=plant.camera.fps, fx=fx, fy=fy,
                                 latency=plant.camera.latency if item == "latency" else k.latency)
    # A controller that knows the depth knows the range it can be in: that one distance. Otherwise the
    # range holds the assumed depth (KnowledgeConfig.check refuses one outside it; an unvalidated config
    # built in code widens the range instead).
    depth, depth_range = ((truth, (truth, truth)) if item == "depth" else
                          (k.depth, (min(k.nearest_depth, k.depth), max(k.farthest_depth, k.depth))))
    return Knowledge(endoscope=endoscope, camera=camera, depth=depth, depth_range=depth_range,
                     source=k.source, preset=plant.preset if item == "endoscope" else k.preset,
                     endoscope_from=Path(from_file).name if from_file else "")


def _load_endoscope_file(path: str, base: EndoscopeParams) -> EndoscopeParams:
    """``base`` with the endoscope table of the TOML file ``path`` applied: ``[knowledge.endoscope]``, or
    else ``[twin.endoscope]`` (``targetlock identify``'s ``fitted.toml``). ConfigError / InputFileError
    naming the setting and the file if it is missing, has no such table or a value out of range."""
    name = "knowledge.endoscope_file"
    data = parse_toml(path, f"{name} =")
    table = _table(data, "knowledge", "endoscope") or _table(data, "twin", "endoscope")
    if not isinstance(table, dict) or not table:
        raise ConfigError(f"{name} = {path!r}: no [knowledge.endoscope] or [twin.endoscope] table in it")
    try:
        return from_dict(EndoscopeParams, merge(to_dict(base), table))
    except ConfigError as exc:
        raise ConfigError(errors=exc.errors, where=f"{name} = {path!r}") from None


def nominal_knowledge(plant: TwinConfig | None = None) -> Knowledge:
    """The default nominal knowledge (for tests and tools that have no run config)."""
    return resolve_knowledge(KnowledgeConfig(), plant or TwinConfig())


def _table(data: object, *keys: str) -> object:
    for key in keys:
        data = data.get(key) if isinstance(data, dict) else None
    return data
