import math

import numpy as np
import pytest

from targetlock.config import ConfigError
from targetlock.experiments.robustness import MOTIONS, case_config, draw_cases, parse_controllers, run_robustness, score


def test_cases_are_seeded_and_within_the_stated_ranges():
    a, b = draw_cases(12, seed=3), draw_cases(12, seed=3)
    assert [c.camera for c in a] == [c.camera for c in b]
    assert {c.motion for c in a} == set(MOTIONS)
    for c in a:
        assert 0.25 <= c.camera["latency"] <= 0.6 and 15.0 <= c.camera["fps"] <= 25.0
        assert 0.0 <= c.camera["latency_jitter"] <= 0.04
        assert 0.01 <= c.distance <= 0.15
        assert np.all(np.isfinite(c.waypoints)) and np.all(np.diff(c.waypoints[:, 0]) > 0)
    assert [c.camera for c in draw_cases(12, seed=4)] != [c.camera for c in a]


def test_paths_scale_with_the_distance():
    cases = [c for c in draw_cases(60, seed=0) if c.motion == "move"]
    ext = [np.abs(c.waypoints[-1, 1:3]).max() / c.distance for c in cases]
    assert max(ext) / min(ext) < 3.0       # the same angular motion at any distance


def test_out_of_view_counts_as_the_half_diagonal():
    t = np.arange(0.0, 4.0, 0.02)
    data = np.zeros((t.size, 16))
    data[:, 0] = t
    data[:, 3] = 10.0
    data[t > 3.0, 3] = np.nan
    s = score(data, 720, 576, after=1.0)
    assert s["peak_px"] == math.hypot(360, 288)
    assert 0.3 < s["out_of_view"] < 0.4


def test_rest_motion_sees_an_oscillation_but_not_a_steady_offset():
    t = np.arange(0.0, 12.0, 0.02)
    steady, hunting = np.zeros((t.size, 16)), np.zeros((t.size, 16))
    for d in (steady, hunting):
        d[:, 0] = t
    steady[:, 1] = 30.0                                   # 30 px off centre, not moving
    hunting[:, 1] = 30.0 * np.sign(np.sin(2 * np.pi * 0.5 * t))  # ±30 px, back and forth
    for d in (steady, hunting):
        d[:, 3] = np.hypot(d[:, 1], d[:, 2])
    a, b = score(steady, 720, 576, after=1.0), score(hunting, 720, 576, after=1.0)
    assert a["rest_rms_px"] == b["rest_rms_px"] == 30.0
    assert a["rest_motion_px"] == 0.0 and b["rest_motion_px"] > 25.0


def test_a_small_run_summarises_every_controller_against_pi():
    r = run_robustness(2, seed=0, controllers=("pi", "ik"), seconds=3.0)
    s = r["summary"]
    assert set(s) == {"pi", "ik"}
    assert s["pi"]["ratio_to_pi_median"] == 1.0 and s["pi"]["cases_worse_than_pi_by_10pct"] == 0
    assert all(math.isfinite(s["ik"][k]) for k in ("rms_median", "rms_p95", "rms_worst", "peak_worst"))


def test_the_benchmark_on_dask_workers_gives_the_same_scores():
    here = run_robustness(2, seed=1, controllers=("pi", "pi-hc"), seconds=3.0)
    dask = run_robustness(2, seed=1, controllers=("pi", "pi-hc"), seconds=3.0, workers=1)
    for c in ("pi", "pi-hc"):
        assert [r["rms_px"] for r in dask["per_case"][c]] == [r["rms_px"] for r in here["per_case"][c]]


def test_controller_names_take_a_knowledge_source_and_bad_ones_name_what_is_allowed(tmp_path):
    assert parse_controllers("pi, adaptive+oracle-endoscope") == ("pi", "adaptive+oracle-endoscope")
    for bad in ("adaptive+truth", "mpc", ""):
        with pytest.raises(ConfigError, match="--controllers"):
            parse_controllers(bad)
    case = draw_cases(1, seed=0)[0]
    path = tmp_path / "path.csv"
    path.write_text("t,x,y,z\n" + "\n".join(",".join(map(str, row)) for row in case.waypoints.tolist()) + "\n")
    cfg = case_config(case, "adaptive+oracle-depth", path, 3.0, 0)
    assert cfg.controller.kind == "adaptive" and cfg.knowledge.source == "oracle-depth"
    assert case_config(case, "pi", path, 3.0, 0).knowledge.source == "nominal"
