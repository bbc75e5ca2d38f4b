import dataclasses

import pytest

from targetlock.config import ConfigError, from_dict
from targetlock.controllers import KnowledgeConfig, resolve_knowledge
from targetlock.experiments.target_lock import RunConfig, build_controller, build_rig
from targetlock.model.twin import twin_config


def plant():
    """A plant unlike the nominal one: looped shaft, 0.25 s latency, f 350 px, target at 3 cm."""
    t = twin_config("looped-shaft", {"camera": {"latency": 0.25, "fx": 350.0, "fy": 350.0},
                                      "scene": {"distance": 0.03}})
    return t


def test_the_controller_gets_the_nominal_assumptions_not_the_plants_truth():
    cfg = RunConfig(twin=plant())
    ctrl = build_controller(cfg, build_rig(cfg))
    k = ctrl.knowledge
    assert k.source == "nominal"
    assert k.latency == 0.4 and k.depth == 0.12 and k.camera.fx == 300.0
    assert k.endoscope == twin_config("calibrated").endoscope != cfg.twin.endoscope
    assert "nominal" in k.label and "0.4 s" in k.label


def test_oracle_hands_over_the_truth_and_says_so():
    cfg = RunConfig(twin=plant(), knowledge=KnowledgeConfig(source="oracle"))
    k = build_controller(cfg, build_rig(cfg)).knowledge
    assert k.endoscope == cfg.twin.endoscope and k.latency == 0.25 and k.depth == 0.03 and k.camera.fx == 350.0
    assert k.label.startswith("oracle")


def test_the_knowledge_section_is_validated_and_kept_in_the_run_config():
    with pytest.raises(ConfigError, match="knowledge.latency"):
        from_dict(RunConfig, {"knowledge": {"latency": -1.0}})
    with pytest.raises(ConfigError, match="knowledge.source"):
        from_dict(RunConfig, {"knowledge": {"source": "truth"}})
    cfg = from_dict(RunConfig, {"knowledge": {"depth": 0.02}})
    assert cfg.knowledge.depth == 0.02 and dataclasses.asdict(cfg)["twin"]["scene"]["distance"] == 0.12
    assert resolve_knowledge(cfg.knowledge, cfg.twin).depth == 0.02


def test_a_partial_oracle_hands_over_that_item_only_and_says_so():
    truth = plant()
    nominal = resolve_knowledge(KnowledgeConfig(), truth)
    got = {item: resolve_knowledge(KnowledgeConfig(source=f"oracle-{item}"), truth)
           for item in ("endoscope", "latency", "depth", "camera")}
    assert got["endoscope"].endoscope == truth.endoscope and got["endoscope"].latency == nominal.latency
    assert got["latency"].latency == 0.25 and got["latency"].endoscope == nominal.endoscope
    assert got["depth"].depth == 0.03 and got["depth"].camera == nominal.camera
    assert got["camera"].camera.fx == 350.0 and got["camera"].depth == nominal.depth
    for item, k in got.items():
        assert k.label.startswith(f"oracle {item} only"), k.label
