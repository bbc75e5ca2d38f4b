"""The behaviour report §3.1/§3.5 describes, measured on the twin's hysteresis sweep."""
import json

import numpy as np
import pytest

from targetlock.cli import main
from targetlock.experiments.hysteresis import HysteresisConfig, run_sweep
from targetlock.model.twin import twin_config


@pytest.fixture(scope="module")
def sweeps():
    return {p: run_sweep(HysteresisConfig(twin=twin_config(p))) for p in ("calibrated", "uncalibrated", "looped-shaft")}


def widths(res):
    return [c["hysteresis_width_deg"] for c in res.curves]


def test_total_gain_is_90_over_110(sweeps):
    assert sweeps["calibrated"].total_gain == pytest.approx(90 / 110, abs=0.02)


@pytest.mark.parametrize("preset", ["calibrated", "uncalibrated", "looped-shaft"])
def test_hysteresis_grows_with_the_held_angle(preset, sweeps):
    w = widths(sweeps[preset])
    assert all(b > a for a, b in zip(w, w[1:]))


@pytest.mark.parametrize("preset", ["calibrated", "uncalibrated", "looped-shaft"])
def test_hysteresis_grows_with_the_bend(preset, sweeps):
    for c in sweeps[preset].curves:
        r = c["reversal_width_deg"]
        assert all(b > a for a, b in zip(r, r[1:])), r


def test_returning_tip_enters_the_deadband_earlier_when_the_other_axis_is_bent(sweeps):
    for preset in ("calibrated", "uncalibrated"):
        stops = [c["stop_angle_deg"] for c in sweeps[preset].curves]
        assert stops[0] > 1.0
        assert all(b > a for a, b in zip(stops, stops[1:])), stops


def test_uncalibrated_has_a_clearly_wider_deadband(sweeps):
    cal = sweeps["calibrated"].curves[0]["deadband_deg"]
    unc = sweeps["uncalibrated"].curves[0]["deadband_deg"]
    assert unc > 3 * cal and unc > 4.0


def test_looped_shaft_has_no_deadband_and_wider_hysteresis(sweeps):
    looped = sweeps["looped-shaft"]
    assert all(c["deadband_deg"] == 0.0 and c["stop_angle_deg"] == 0.0 for c in looped.curves)
    assert all(lw > cw for lw, cw in zip(widths(looped), widths(sweeps["calibrated"])))


def test_held_axis_stays_where_it_was_put(sweeps):
    for c in sweeps["calibrated"].curves:
        assert c["second_angle_measured_deg"] == pytest.approx(c["second_angle_deg"], abs=1.5)


def test_cli_writes_a_run_folder_and_json(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["hysteresis", "--preset", "uncalibrated", "--held", "0", "50", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [c["second_angle_deg"] for c in summary["curves"]] == [0.0, 50.0]
    for key in ("hysteresis_width_deg", "deadband_deg", "stop_angle_deg"):
        assert key in summary["curves"][0]
    assert "total_gain" in summary
    for f in ("config.toml", "timeseries.csv", "hysteresis.png", "summary.json"):
        assert (out / f).stat().st_size > 0
    assert "uncalibrated" in (out / "config.toml").read_text()
    data = np.genfromtxt(out / "timeseries.csv", delimiter=",", names=True)
    assert set(np.unique(data["curve"])) == {0.0, 1.0}
    # The folder's config re-runs to the same figures.
    out2 = tmp_path / "rerun"
    assert main(["hysteresis", "--config", str(out / "config.toml"), "--out", str(out2), "--json"]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["curves"] == summary["curves"]


def test_cli_refuses_bad_values_naming_the_field(capsys):
    assert main(["hysteresis", "--held", "0", "500"]) == 2
    err = capsys.readouterr().err
    assert "held_angles_deg[1]" in err and "500" in err and "[-120.0, 120.0]" in err
