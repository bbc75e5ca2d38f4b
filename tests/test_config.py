import pytest

from targetlock.config import ConfigError, describe, from_dict, load_toml, save_toml, to_dict
from targetlock.model.twin import TwinConfig, twin_config


def test_defaults_round_trip_through_toml(tmp_path):
    cfg = twin_config("looped-shaft")
    save_toml(cfg, tmp_path / "c.toml")
    assert load_toml(TwinConfig, tmp_path / "c.toml") == cfg


def test_out_of_range_value_names_field_value_and_range():
    with pytest.raises(ConfigError) as exc:
        from_dict(TwinConfig, {"endoscope": {"tip_stiffness": -1.0}})
    msg = str(exc.value)
    assert "endoscope.tip_stiffness" in msg and "-1.0" in msg and "[0.0001, 100.0]" in msg


def test_unknown_setting_is_refused():
    with pytest.raises(ConfigError, match="endoscope.tip_stifness"):
        from_dict(TwinConfig, {"endoscope": {"tip_stifness": 1.0}})


def test_wrong_type_is_refused():
    with pytest.raises(ConfigError, match="camera.fps must be a number"):
        from_dict(TwinConfig, {"camera": {"fps": "fast"}})


def test_nan_is_refused():
    with pytest.raises(ConfigError, match="model_dt"):
        from_dict(TwinConfig, {"model_dt": float("nan")})


def test_choice_is_refused_with_the_allowed_values():
    with pytest.raises(ConfigError, match="both-angles"):
        from_dict(TwinConfig, {"endoscope": {"friction_model": "coulomb"}})


def test_unknown_preset_is_refused():
    with pytest.raises(ConfigError, match="looped-shaft"):
        twin_config("loopy")


def test_presets_differ_where_documented():
    cal, unc, loop = (to_dict(twin_config(p))["endoscope"] for p in ("calibrated", "uncalibrated", "looped-shaft"))
    assert unc["cable_slack"] > cal["cable_slack"] > 0 > loop["cable_slack"]
    assert loop["mu_n"] > cal["mu_n"]


def test_every_field_is_documented():
    rows = describe(TwinConfig)
    assert len(rows) > 30
    assert all(r["doc"] for r in rows), [r["name"] for r in rows if not r["doc"]]
