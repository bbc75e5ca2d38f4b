"""The shipped Foxglove layout (docs/foxglove/targetlock_layout.json): its panels' settings are the keys of
Foxglove's own typed panel configs (foxglove-sdk's ``foxglove.layouts``), and every topic, message path
and frame it names exists in a ``run.mcap`` written by ``targetlock run``."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

from targetlock.cli import main

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove" / "targetlock_layout.json"
TITLE = "foxglovePanelTitle"      # a panel's title in the app's exported layouts (the SDK keeps it on the panel)


def _layout() -> dict:
    return json.loads(LAYOUT.read_text())


def _panels(tree) -> list[str]:
    """Panel ids of the layout's split tree."""
    if isinstance(tree, str):
        return [tree]
    assert set(tree) <= {"direction", "first", "second", "splitPercentage"}, tree
    assert tree["direction"] in ("row", "column")
    return _panels(tree["first"]) + _panels(tree["second"])


def test_every_panel_config_is_what_foxglove_sdk_writes_for_it():
    fl = pytest.importorskip("foxglove.layouts")
    from foxglove.layouts import _BaseModel   # the SDK's own JSON encoder of its config classes

    def encoded(config) -> dict:
        return json.loads(json.dumps(config, default=_BaseModel._to_json_default))

    def series(topic_field: str):
        return fl.PlotSeries(enabled=True, value=topic_field, timestamp_method="receiveTime")

    expected = {
        "3D!scene": fl.ThreeDeeConfig(
            follow_tf="base",
            scene=fl.BaseRendererSceneSettings(transforms=fl.BaseRendererTransforms(show_label=True, axis_size=0.02)),
            camera_state=fl.ThreeDeeCameraState(distance=0.45, perspective=True, phi=60, target=(0, 0, 0.08),
                                                theta_offset=45)),
        "Image!view": fl.ImageConfig(image_mode=fl.ImageModeConfig(
            image_topic="/camera/image", calibration_topic="/camera/calibration",
            annotations={"/camera/annotations": fl.ImageAnnotationSettings(visible=True)})),
        "Plot!error": fl.PlotConfig(paths=[series(f"/timeseries.{c}") for c in ("err_x", "err_y", "err")],
                                    show_legend=True, following_view_width=20),
        "Plot!angles": fl.PlotConfig(paths=[series(f"/timeseries.{c}") for c in (
            "motor_x_deg", "setpoint_x_deg", "tip_x_deg", "motor_y_deg", "tip_y_deg")],
                                     show_legend=True, following_view_width=20),
        "RosOut!log": fl.LogConfig(search_terms=[], min_log_level=1, topic_to_render="/log"),
    }
    layout = _layout()
    assert sorted(_panels(layout["layout"])) == sorted(layout["configById"]) == sorted(expected)
    for panel_id, config in layout["configById"].items():
        mine = {k: v for k, v in config.items() if k != TITLE}
        assert mine == encoded(expected[panel_id]), panel_id
        assert isinstance(config[TITLE], str) and config[TITLE]


def _read(path: Path) -> tuple[dict[str, list[dict]], dict[str, str]]:
    """Messages per topic (decoded JSON) and each topic's schema name."""
    out: dict[str, list[dict]] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        for _, channel, message in reader.iter_messages():
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out, schemas


def test_the_layouts_topics_paths_and_frames_exist_in_targetlock_runs(tmp_path):
    # frames and their annotations need vision; the log needs a lost target (a close target that runs away)
    vision, lost = tmp_path / "vision", tmp_path / "lost"
    assert main(["run", "--seconds", "1", "--set", "loop.metrics_after=0.5", "--vision", "--out", str(vision)]) == 0
    assert main(["run", "--seconds", "3", "--set", "loop.metrics_after=0.5", "--set", "twin.scene.distance=0.01",
                 "--set", "twin.scene.linear_length=0.3", "--out", str(lost)]) == 0
    seen, schemas = _read(vision / "run.mcap")
    seen_lost, schemas_lost = _read(lost / "run.mcap")
    assert "/log" not in seen and "/camera/image" not in seen_lost
    seen.update(seen_lost)
    schemas.update(schemas_lost)

    config = _layout()["configById"]
    image = config["Image!view"]["imageMode"]
    wanted = {image["imageTopic"]: "foxglove.CompressedImage", image["calibrationTopic"]: "foxglove.CameraCalibration",
              config["RosOut!log"]["topicToRender"]: "foxglove.Log"}
    wanted.update({topic: "foxglove.ImageAnnotations" for topic in image["annotations"]})
    for topic, schema in wanted.items():
        assert seen.get(topic), f"no messages on {topic}"
        assert schemas[topic] == schema
    assert any(m["message"] == "target lost" for m in seen["/log"])

    frames = {f for m in seen["/tf"] for f in (m["parent_frame_id"], m["child_frame_id"])}
    assert config["3D!scene"]["followTf"] in frames and {"tip", "target"} <= frames
    assert {m["frame_id"] for m in seen["/camera/image"]} <= frames      # the image sits in the 3D scene

    paths = [p["value"] for key, c in config.items() if key.startswith("Plot!") for p in c["paths"]]
    assert len(paths) == 8
    for path in paths:
        topic, field = path.split(".", 1)        # Foxglove's message path: /topic.field
        assert seen.get(topic), f"{path}: no messages on {topic}"
        values = [m[field] for m in seen[topic]]
        assert all(isinstance(v, float) for v in values if v is not None) and any(v is not None for v in values), path
