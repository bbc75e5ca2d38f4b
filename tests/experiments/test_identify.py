"""`targetlock identify`: the endoscope model fitted to a recorded hysteresis sweep (issue 9 §4)."""
import dataclasses
import json

import numpy as np
import pytest
import tomli_w

from targetlock.cli import main
from targetlock.config import to_dict
from targetlock.experiments.common import build_config
from targetlock.experiments.hysteresis import HysteresisConfig, run_sweep
from targetlock.experiments.identify import RATIOS, Sweep, identify, load_sweep, ratios, replay, with_ratios
from targetlock.model.twin import twin_config

# A short sweep keeps each fit at a few seconds: two amplitudes, the other axis straight and bent.
SWEEP = ["--amplitudes", "30", "100", "--held", "0", "60", "--speed", "30", "--sample-rate", "100"]
NAMES = [r[0] for r in RATIOS]


def random_scope(seed: int):
    """A scope drawn around a preset: every mechanical parameter ±15 %, slack ±0.2 mm."""
    rng = np.random.default_rng(seed)
    preset = ("calibrated", "uncalibrated", "looped-shaft")[seed % 3]
    e = twin_config(preset).endoscope

    def f():
        return rng.uniform(0.85, 1.15)
    scope = dataclasses.replace(
        e, cable_stiffness=e.cable_stiffness * f(), cable_arm=e.cable_arm * f(), handle_radius=e.handle_radius * f(),
        tip_stiffness=e.tip_stiffness * f(), mu_n=e.mu_n * f(), friction_offset=e.friction_offset * f(),
        mu_f=e.mu_f * f(), tip_inertia=e.tip_inertia * f(), cable_slack=e.cable_slack + rng.uniform(-2e-4, 2e-4))
    return preset, scope


def record(folder, preset, scope, noise_deg, seed):
    """A twin sweep of ``scope`` through the CLI, with motion-capture-like noise added to the tip angles."""
    cfg_file = folder.parent / f"{folder.name}-scope.toml"
    cfg_file.write_text(tomli_w.dumps({"twin": {"preset": preset, "endoscope": to_dict(scope)}}))
    assert main(["hysteresis", "--config", str(cfg_file), *SWEEP, "--out", str(folder)]) == 0
    ts = folder / "timeseries.csv"
    header = ts.read_text().splitlines()[0]
    cols = header.split(",")
    data = np.loadtxt(ts, delimiter=",", skiprows=1)
    rng = np.random.default_rng(1000 + seed)
    for name in ("tip_deg", "held_tip_deg"):
        data[:, cols.index(name)] += rng.normal(0.0, noise_deg, len(data))
    np.savetxt(ts, data, delimiter=",", header=header, comments="", fmt="%.9g")
    return folder


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """Random scopes (seeded), recorded with noise and identified from their preset, via the CLI."""
    out = {}
    for seed, noise in ((1, 0.3), (2, 0.5)):
        root = tmp_path_factory.mktemp(f"scope{seed}")
        preset, scope = random_scope(seed)
        sweep = record(root / "sweep", preset, scope, noise, seed)
        assert main(["identify", str(sweep), "--preset", preset, "--out", str(root / "fit")]) == 0
        summary = json.loads((root / "fit" / "summary.json").read_text())
        out[seed] = (preset, scope, noise, root, summary)
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_recovers_the_identifiable_parameters_of_a_random_scope_within_10_percent(fits, seed):
    preset, scope, noise, _, summary = fits[seed]
    truth = ratios(scope)
    fitted = np.array([summary["ratios"][n]["value"] for n in NAMES])
    assert all(summary["ratios"][n]["identifiable"] for n in NAMES), summary["ratios"]
    err = np.abs(fitted - truth) / np.abs(truth)
    assert np.all(err < 0.10), dict(zip(NAMES, err))
    # The starting preset was clearly off, so the fit did the work.
    start_err = np.abs(ratios(twin_config(preset).endoscope) - truth) / np.abs(truth)
    assert start_err.max() > 2 * err.max()
    # Nothing but the added noise is left unexplained.
    assert noise * 0.95 < summary["residual_rms_deg"] < noise * 1.05


def test_fitted_preset_works_with_config_and_reproduces_the_scope(fits):
    preset, scope, _, root, summary = fits[1]
    cfg = build_config(HysteresisConfig, config_file=root / "fit" / "fitted.toml")
    assert np.allclose(ratios(cfg.twin.endoscope), [summary["ratios"][n]["value"] for n in NAMES])
    assert (root / "fit" / "identify.png").stat().st_size > 10_000
    # The fitted scope's own sweep (no noise) matches the true scope's within a fraction of a degree.
    short = dict(amplitudes_deg=(30.0, 100.0), held_angles_deg=(0.0, 60.0), sweep_speed_deg_s=30.0, sample_rate=100.0)
    true_run = run_sweep(HysteresisConfig(twin=dataclasses.replace(twin_config(preset), endoscope=scope), **short))
    fit_run = run_sweep(dataclasses.replace(cfg, **short))
    assert np.max(np.abs(np.degrees(fit_run.tip - true_run.tip))) < 1.0
    for a, b in zip(true_run.curves, fit_run.curves):
        assert b["hysteresis_width_deg"] == pytest.approx(a["hysteresis_width_deg"], abs=0.5)


@pytest.fixture(scope="module")
def clean_sweep():
    cfg = HysteresisConfig(amplitudes_deg=(30.0, 100.0), held_angles_deg=(0.0, 60.0), sweep_speed_deg_s=30.0,
                           sample_rate=100.0)
    res = run_sweep(cfg)
    return Sweep(res.time, np.stack([res.handle, res.held_handle], -1), np.stack([res.tip, res.held_tip], -1),
                 cfg, "twin")


def test_only_ratios_to_the_cable_stiffness_are_observable(clean_sweep):
    """Scaling every torque, or the cable arm with handle radius and slack, changes no recorded angle."""
    e = clean_sweep.config.twin.endoscope
    torques = dataclasses.replace(e, cable_stiffness=2 * e.cable_stiffness, tip_stiffness=2 * e.tip_stiffness,
                                  mu_n=2 * e.mu_n, mu_f=2 * e.mu_f, tip_inertia=2 * e.tip_inertia)
    arm = dataclasses.replace(e, cable_arm=1.3 * e.cable_arm, handle_radius=1.3 * e.handle_radius,
                              cable_slack=1.3 * e.cable_slack, cable_stiffness=e.cable_stiffness / 1.3 ** 2)
    stiffer_tip = dataclasses.replace(e, tip_stiffness=1.2 * e.tip_stiffness)
    tips = replay(clean_sweep, [e, torques, arm, stiffer_tip], 0.001)
    assert np.max(np.abs(tips[1] - tips[0])) < 1e-9
    assert np.max(np.abs(tips[2] - tips[0])) < 1e-9
    assert np.degrees(np.max(np.abs(tips[3] - tips[0]))) > 3.0
    assert np.allclose(ratios(torques), ratios(e)) and np.allclose(ratios(arm), ratios(e))
    # The replay of the recorded handle angles reproduces the recorded tip angles.
    assert np.degrees(np.max(np.abs(tips[0] - clean_sweep.tip))) < 0.2


def test_ratios_round_trip_at_the_scale_of_another_preset():
    preset, scope = random_scope(4)
    start = twin_config("looped-shaft").endoscope
    back = with_ratios(start, ratios(scope))
    assert np.allclose(ratios(back), ratios(scope))
    assert back.cable_arm == start.cable_arm and back.cable_stiffness == start.cable_stiffness


def test_without_slack_the_compliance_ratio_is_flagged_as_not_determined():
    """With s0 = 0 there is no region where the cable tension changes shape: only the static gain
    g/(1 + κ) is seen, not g and κ apart; the other coordinates stay determined."""
    truth = dataclasses.replace(twin_config().endoscope, cable_slack=0.0, tip_stiffness=1.7, mu_n=0.09)
    cfg = HysteresisConfig(twin=dataclasses.replace(twin_config(), endoscope=truth), amplitudes_deg=(30.0, 100.0),
                           held_angles_deg=(0.0, 60.0), sweep_speed_deg_s=30.0, sample_rate=100.0)
    res = run_sweep(cfg)
    noise = np.random.default_rng(5).normal(0.0, np.radians(0.3), (res.time.size, 2, 2))
    sweep = Sweep(res.time, np.stack([res.handle, res.held_handle], -1),
                  np.stack([res.tip, res.held_tip], -1) + noise, cfg, "twin")
    fit = identify(sweep, twin_config().endoscope, n_starts=16)
    flags = dict(zip(NAMES, fit.identifiable))
    assert not flags["compliance_ratio"]
    assert all(flags[n] for n in NAMES if n != "compliance_ratio")
    truth_r = ratios(truth)
    for i, n in enumerate(NAMES[:5]):
        if n != "slack_handle":
            assert fit.ratios[i] == pytest.approx(truth_r[i], rel=0.05), n
    assert abs(fit.ratios[1]) < 5e-4  # rad of handle: no slack found where there is none


def test_a_folder_that_is_not_a_sweep_is_refused_with_one_line(tmp_path, capsys):
    assert main(["identify", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "config.toml" in err and "hysteresis" in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_old_run_folders_without_the_held_handle_column_still_load(tmp_path):
    folder = tmp_path / "sweep"
    assert main(["hysteresis", *SWEEP, "--out", str(folder)]) == 0
    new = load_sweep(folder)
    ts = folder / "timeseries.csv"
    lines = ts.read_text().splitlines()
    cols = lines[0].split(",")
    drop = cols.index("held_handle_deg")
    ts.write_text("\n".join(",".join(v for i, v in enumerate(line.split(",")) if i != drop) for line in lines) + "\n")
    old = load_sweep(folder)
    # The program's setpoint and the drive's position differ only while the drive is moving.
    assert np.degrees(np.max(np.abs(old.handle - new.handle))) < 1.0
