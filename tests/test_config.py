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


def test_fixed_length_tuples_are_checked_and_variable_ones_are_not():
    from targetlock.experiments.hysteresis import HysteresisConfig
    for bad in ([1.0, 2.0, 3.0], [], [5.0]):
        with pytest.raises(ConfigError, match=r"scene.start_tip_deg = .* needs exactly 2 values"):
            from_dict(TwinConfig, {"scene": {"start_tip_deg": bad}})
    assert from_dict(HysteresisConfig, {"held_angles_deg": [0.0, 10.0, 20.0]}).held_angles_deg == (0.0, 10.0, 20.0)


def test_all_problems_are_reported_at_once():
    with pytest.raises(ConfigError) as exc:
        from_dict(TwinConfig, {"camera": {"fps": 0, "latency": "x"}, "model_dt": -1, "scene": 5, "nope": 1})
    assert len(exc.value.errors) == 5
    msg = str(exc.value)
    for part in ("camera.fps = 0.0", "camera.latency must be a number", "model_dt = -1.0", "scene must be a table",
                 "unknown setting nope"):
        assert part in msg


def test_cross_field_rules():
    from targetlock.experiments.target_lock import RunConfig
    with pytest.raises(ConfigError, match=r"loop.metrics_after = 2 s .* loop.seconds = 1 s"):
        from_dict(RunConfig, {"loop": {"seconds": 1.0}})
    with pytest.raises(ConfigError, match=r"camera.cy = 600 px lies outside the image"):
        from_dict(TwinConfig, {"camera": {"cy": 600.0}})
    assert from_dict(TwinConfig, {"camera": {"cx": 720.0, "cy": 0.0}}).camera.cx == 720.0


def test_replace_path_names_the_full_field_and_applies_cross_field_rules():
    from targetlock.config import replace_path
    from targetlock.experiments.target_lock import RunConfig
    cfg = RunConfig()
    assert replace_path(cfg, "loop.seconds", 10.0).loop.seconds == 10.0
    with pytest.raises(ConfigError, match=r"^loop.seconds = -1.0 is out of range"):
        replace_path(cfg, "loop.seconds", -1.0)
    with pytest.raises(ConfigError, match="metrics_after"):
        replace_path(cfg, "loop.seconds", 1.0)


def test_field_info_gives_type_range_and_default():
    from targetlock.config import field_info
    from targetlock.experiments.target_lock import RunConfig
    tp, meta, default = field_info(RunConfig, "twin.camera.latency")
    assert tp is float and meta["unit"] == "s" and (meta["lo"], meta["hi"]) == (0.0, 5.0) and default == 0.4
    with pytest.raises(ConfigError, match="unknown setting"):
        field_info(RunConfig, "twin.camera.latncy")


def test_toml_files_with_a_bom_load_and_bad_files_name_themselves(tmp_path):
    from targetlock.errors import InputFileError
    p = tmp_path / "c.toml"
    p.write_bytes(b"\xef\xbb\xbf[camera]\nfps = 30\n")
    assert load_toml(TwinConfig, p).camera.fps == 30.0
    p.write_bytes(b"[camera]\nfps = 0\nlatency = -1\n")
    with pytest.raises(ConfigError, match=r"config file .*c.toml: 2 problems"):
        load_toml(TwinConfig, p)
    with pytest.raises(InputFileError, match="no such file"):
        load_toml(TwinConfig, tmp_path / "none.toml")
