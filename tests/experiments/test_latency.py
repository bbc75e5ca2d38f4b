import dataclasses
import json

import numpy as np
import pytest

from targetlock.cli import main
from targetlock.experiments.latency import measure_latency, motion_in_frames
from targetlock.experiments.target_lock import RunConfig
from targetlock.model.twin import TwinConfig


@pytest.mark.parametrize("latency,fps", [(0.0, 22.0), (0.4, 22.0), (0.4, 17.0), (0.7, 30.0)])
def test_procedure_measures_back_the_configured_latency(latency, fps):
    twin = TwinConfig()
    twin = dataclasses.replace(twin, camera=dataclasses.replace(twin.camera, latency=latency, fps=fps))
    r = measure_latency(RunConfig(twin=twin))
    # one frame of resolution, plus one control tick and the drive's first millisecond
    assert latency <= r["measured_latency_s"] <= latency + 1.0 / fps + 0.02 + 1e-9


def test_motion_in_recorded_frames_is_found():
    frames = [np.full((8, 8), 100, np.uint8)] * 5 + [np.full((8, 8), 140, np.uint8)] * 3
    assert motion_in_frames(frames) == 5
    assert motion_in_frames(frames[:5]) == -1


def test_latency_command(tmp_path, capsys):
    assert main(["latency", "--latency", "0.2", "--out", str(tmp_path / "l"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 0.2 <= r["measured_latency_s"] <= 0.2 + 1 / 22 + 0.02
