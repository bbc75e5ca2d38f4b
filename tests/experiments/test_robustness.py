import math

import numpy as np
import pytest

from targetlock.config import ConfigError
from targetlock.experiments.robustness import (DISTANCE_BANDS, MOTIONS, breakdown, case_config, draw_cases, parse_controllers,
                                               parse_seeds, run_robustness, score, score_run, write_waypoints)
from targetlock.experiments.target_lock import RunConfig, run_engagements, run_target_lock


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
    assert parse_controllers("adaptive@2,adaptive+oracle@3") == ("adaptive@2", "adaptive+oracle@3")
    for bad in ("adaptive+truth", "mpc", "", "adaptive@1", "adaptive@11", "adaptive@x", "adaptive@"):
        with pytest.raises(ConfigError, match="--controllers"):
            parse_controllers(bad)
    case = draw_cases(1, seed=0)[0]
    path = tmp_path / "path.csv"
    path.write_text("t,x,y,z\n" + "\n".join(",".join(map(str, row)) for row in case.waypoints.tolist()) + "\n")
    cfg = case_config(case, "adaptive+oracle-depth", path, 3.0, 0)
    assert cfg.controller.kind == "adaptive" and cfg.knowledge.source == "oracle-depth"
    assert case_config(case, "pi", path, 3.0, 0).knowledge.source == "nominal"
    assert case_config(case, "adaptive+oracle-depth@2", path, 3.0, 0) == cfg     # @N: which run is scored, not the run


def test_engaged_again_on_the_same_scope_the_lock_starts_from_what_it_found(tmp_path):
    # Seed 23 case 45: a slow drift at 2 cm on a looped shaft whose friction band is far wider than the
    # assumed scope's; the first engagement finds a wider candidate only after the tip broke free at ~7 s.
    case = draw_cases(60, seed=23)[45]
    path = tmp_path / "path.csv"
    write_waypoints(case, path)
    cfg = case_config(case, "adaptive", path, 12.0, 23)
    first, second = run_engagements(cfg, 2)
    alone = run_target_lock(cfg)
    assert np.array_equal(first["_data"], alone["_data"], equal_nan=True)     # the first is the plain run
    cam = cfg.twin.camera
    rms = [score(s["_data"], cam.width, cam.height, cfg.loop.metrics_after)["rms_px"] for s in (first, second)]
    assert rms[1] < 0.8 * rms[0]
    assert score_run(cfg, 2)["rms_px"] == rms[1]


def test_several_sets_are_pooled_and_each_set_is_the_same_as_run_alone():
    both = run_robustness(2, seed=(1, 2), controllers=("pi", "pi-hc"), seconds=3.0)
    alone = run_robustness(2, seed=2, controllers=("pi", "pi-hc"), seconds=3.0)
    assert [r["seed"] for r in both["per_case"]["pi-hc"]] == [1, 1, 2, 2]
    assert both["sets"][2] == alone["summary"]
    pooled = [r["rms_px"] for r in both["per_case"]["pi-hc"]]
    assert both["summary"]["pi-hc"]["rms_median"] == float(np.median(pooled))


def test_the_breakdown_splits_every_case_into_one_distance_band_and_one_motion():
    per = {"pi": [], "x": []}
    for i, (d, m) in enumerate([(0.012, "step"), (0.025, "drift"), (0.05, "step"), (0.14, "drift")]):
        per["pi"].append({"rms_px": 10.0, "distance": d, "motion": m})
        per["x"].append({"rms_px": 5.0 + 5.0 * i, "distance": d, "motion": m})   # 5, 10, 15, 20 px
    b = breakdown(per)["x"]
    assert sum(b[band]["cases"] for band in DISTANCE_BANDS) == 4
    assert sum(b[m]["cases"] for m in MOTIONS) == 4
    assert b["1-3 cm"]["rms_median"] == 7.5 and b["1-3 cm"]["cases_worse_than_pi_by_10pct"] == 0
    assert b["step"]["rms_median"] == 10.0 and b["drift"]["cases_worse_than_pi_by_10pct"] == 1
    assert b["10-15 cm"]["ratio_to_pi_median"] == 2.0 and b["rotation"]["cases"] == 0


def test_the_benchmark_folder_keeps_every_finished_run_and_each_case_runs_again(tmp_path, monkeypatch, capsys):
    import csv

    from targetlock.config import load_toml
    from targetlock.experiments import robustness
    from targetlock.experiments.target_lock import run_target_lock

    res = robustness.bench_robustness(2, (4,), controllers=("pi", "pi-hc"), out=tmp_path / "bench")
    rows = list(csv.DictReader((tmp_path / "bench" / "cases.csv").open()))
    assert [(r["case"], r["controller"]) for r in rows] == [("0", "pi"), ("0", "pi-hc"), ("1", "pi"), ("1", "pi-hc")]
    assert res["controllers"]["pi-hc"]["rms_median"] == float(np.median([float(r["rms_px"]) for r in rows[1::2]]))
    # A row is reproduced by its case's config (written for PI), with the waypoints it names.
    cfg = load_toml(RunConfig, tmp_path / "bench" / "cases" / "seed-4-case-001.toml")
    again = robustness.score(run_target_lock(cfg)["_data"], cfg.twin.camera.width, cfg.twin.camera.height,
                             cfg.loop.metrics_after)
    assert again["rms_px"] == float(rows[2]["rms_px"])

    # Killed during the third run: the two finished rows are on disk already (read while it runs, as
    # after a kill -9, which closes no file).
    calls, seen = [], []
    real = robustness.score_run

    def dies(cfg, engagement=1):
        calls.append(cfg)
        if len(calls) > 2:
            seen.extend(csv.DictReader((tmp_path / "killed" / "cases.csv").open()))
            raise KeyboardInterrupt
        return real(cfg, engagement)
    monkeypatch.setattr(robustness, "score_run", dies)
    with pytest.raises(KeyboardInterrupt):
        robustness.bench_robustness(2, (4,), controllers=("pi", "pi-hc"), out=tmp_path / "killed")
    assert [(r["case"], r["controller"]) for r in seen] == [("0", "pi"), ("0", "pi-hc")]


def test_seeds_are_one_or_a_list_and_bad_ones_name_what_is_allowed():
    assert parse_seeds("7") == (7,) and parse_seeds("0, 23,204") == (0, 23, 204)
    for bad in ("", "a", "-1", "1,1", "1.5"):
        with pytest.raises(ConfigError, match="--seed"):
            parse_seeds(bad)


def test_the_command_takes_several_seeds_and_prints_each_sets_median_and_the_breakdown(tmp_path, capsys):
    import json

    from targetlock.cli import main
    assert main(["bench", "robustness", "--cases", "2", "--seed", "1,2", "--controllers", "pi-hc", "--json"]) == 0
    out = capsys.readouterr().out
    res = json.loads(out.strip().splitlines()[-1])
    assert res["seed"] == [1, 2] and set(res["sets"]) == {"1", "2"}
    assert res["mean_of_set_medians"]["pi-hc"] == pytest.approx(
        (res["sets"]["1"]["pi-hc"]["rms_median"] + res["sets"]["2"]["pi-hc"]["rms_median"]) / 2)
    assert "median rms per set" in out and "1-3 cm" in out
    assert main(["bench", "robustness", "--seed", "1,1"]) == 2
    assert "named twice" in capsys.readouterr().err


def test_the_benchmark_through_the_camera_tracks_the_rendered_target():
    """--vision: the same cases, rendered and measured by the feature tracker; the lock stays close to
    its ideal-tracker result and every frame's observation is counted (lost_fraction)."""
    plain = run_robustness(1, seed=0, controllers=("pi",), seconds=3.0)
    seen = run_robustness(1, seed=0, controllers=("pi",), seconds=3.0, vision=True)
    ideal, row = plain["per_case"]["pi"][0], seen["per_case"]["pi"][0]
    assert seen["vision"] and not plain["vision"]
    assert row["lost_fraction"] < 0.05 and ideal["lost_fraction"] < 0.15   # the ideal one drops frames on purpose
    assert row["rms_px"] != ideal["rms_px"] and abs(row["rms_px"] - ideal["rms_px"]) < 0.2 * ideal["rms_px"] + 3.0
    assert seen["summary"]["pi"]["lost_fraction_worst"] == row["lost_fraction"]
    assert row["tracker_median_px"] < 1.5 and math.isnan(ideal["tracker_median_px"])


def test_bench_robustness_records_the_camera_run_in_its_folder(tmp_path, capsys):
    from targetlock.cli import main
    from targetlock.config import load_toml
    from targetlock.experiments.robustness import RobustnessSpec
    out = tmp_path / "rb"
    assert main(["bench", "robustness", "--cases", "1", "--controllers", "pi", "--vision", "--out", str(out)]) == 0
    assert "through the rendered view" in capsys.readouterr().out
    assert load_toml(RobustnessSpec, out / "config.toml").vision is True
    header = (out / "cases.csv").read_text().splitlines()[0].split(",")
    assert header[-3:] == ["lost_fraction", "tracker_median_px", "tracker_p95_px"]
