"""Sweeps: case expansion (grid × seeded draws), spec errors, and a run on a real Dask cluster whose
rows are reproducible from their saved configs."""
from __future__ import annotations

import csv
import json

import pytest

from targetlock.cli import main
from targetlock.config import ConfigError, load_toml
from targetlock.experiments.sweep import SweepSpec, expand, load_spec
from targetlock.experiments.target_lock import RunConfig, run_target_lock

SPEC = """
preset = "calibrated"
seed = 3
[base]
loop = { seconds = 3.0, metrics_after = 1.0 }
[grid]
"controller.kind" = ["pi", "pi-hc"]
[random]
n = 3
"twin.camera.latency" = { uniform = [0.25, 0.6] }
"twin.camera.fps" = { integers = [15, 25] }
"twin.scene.path" = { choice = ["linear", "ellipse"] }
"""


def _spec(tmp_path, text=SPEC):
    p = tmp_path / "spec.toml"
    p.write_text(text)
    return p


def test_cases_are_draws_times_grid_with_shared_seed_per_draw(tmp_path):
    cases = expand(load_spec(_spec(tmp_path)))
    assert len(cases) == 3 * 2
    for d in range(3):
        pair = [c for c in cases if c.draw == d]
        assert [c.varied["controller.kind"] for c in pair] == ["pi", "pi-hc"]
        # the controllers of one draw see the same scope, latency and noise
        assert pair[0].overrides["seed"] == pair[1].overrides["seed"]
        assert pair[0].varied["twin.camera.latency"] == pair[1].varied["twin.camera.latency"]
    assert len({c.overrides["seed"] for c in cases}) == 3
    for c in cases:
        assert 0.25 <= c.varied["twin.camera.latency"] <= 0.6
        assert c.varied["twin.camera.fps"] in range(15, 26)
        assert c.overrides["twin"]["camera"]["latency"] == c.varied["twin.camera.latency"]


def test_expansion_is_reproducible_and_seed_dependent():
    spec = SweepSpec(seed=5, random={"n": 4, "twin.camera.latency": {"loguniform": [0.2, 0.6]}})
    a, b = expand(spec), expand(spec)
    assert [c.varied for c in a] == [c.varied for c in b]
    other = expand(SweepSpec(seed=6, random=spec.random))
    assert [c.varied for c in a] != [c.varied for c in other]


@pytest.mark.parametrize("text, words", [
    ('[grid]\n"twin.camera.latency" = [0.4, -1.0]\n', ["twin.camera.latency", "-1.0", "allowed"]),
    ('[grid]\n"controller.kind" = []\n', ["grid.controller.kind", "non-empty"]),
    ('[random]\nn = 2\n"twin.camera.fps" = { normal = [20, 2] }\n', ["random.twin.camera.fps", "uniform"]),
    ('[random]\nn = 2\n"twin.camera.fps" = { uniform = [25, 15] }\n', ["low <= high"]),
    ('[grid]\n"controller.gain" = [1.0]\n', ["unknown setting", "controller.gain"]),
    ('speed = 3\n', ["unknown sweep setting", "speed"]),
    ('preset = "rubber"\n', ["preset", "rubber"]),
])
def test_bad_specs_name_the_setting(tmp_path, text, words):
    with pytest.raises(ConfigError) as err:
        load_spec(_spec(tmp_path, text))
    for w in words:
        assert w in str(err.value)


def test_sweep_on_a_dask_cluster_writes_reproducible_rows(tmp_path, capsys):
    out = tmp_path / "sweep"
    spec = _spec(tmp_path, SPEC.replace("n = 3", "n = 1"))
    assert main(["sweep", str(spec), "--workers", "1", "--out", str(out), "--json"]) == 0
    printed = capsys.readouterr()
    summary = json.loads(printed.out.strip().splitlines()[-1])
    assert summary["cases"] == 2 and summary["failed"] == 0
    # Dask's scheduler logs in this process; its INFO lines are not the user's business
    assert "distributed." not in printed.err
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert sorted(r["controller.kind"] for r in rows) == ["pi", "pi-hc"]
    for r in rows:
        # the row's config, run again in this process, gives the row's figures
        cfg = load_toml(RunConfig, out / r["config"])
        again = run_target_lock(cfg)
        assert float(r["rms_px"]) == pytest.approx(again["rms_px"], rel=1e-9)
        assert float(r["peak_px"]) == pytest.approx(again["peak_px"], rel=1e-9)
    assert {g["controller.kind"] for g in summary["groups"]} == {"pi", "pi-hc"}
    assert (out / "sweep.png").stat().st_size > 0
    assert load_spec(out / "config.toml").seed == 3   # the run folder's spec runs again
