"""The small top-level Python API (docs/api.md): cheap to import, lazy, and it runs the twin."""
import json
import subprocess
import sys

import pytest

import targetlock


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True).stdout
    return set(json.loads(out.strip().splitlines()[-1]))


def test_import_and_help_do_not_load_numba_or_numpy():
    assert not {"numba", "numpy"} & _modules_after("import targetlock")
    mods = _modules_after("import contextlib, io\nfrom targetlock.cli import main\n"
                          "with contextlib.redirect_stdout(io.StringIO()):\n"
                          "    try:\n        main(['--help'])\n    except SystemExit:\n        pass")
    assert "numba" not in mods and "targetlock.model.twin" not in mods


def test_every_public_name_resolves():
    for name in targetlock.__all__:
        assert getattr(targetlock, name) is not None, name
    with pytest.raises(AttributeError):
        targetlock.no_such_name  # noqa: B018


def test_run_validates_and_runs_the_twin(tmp_path):
    with pytest.raises(targetlock.ConfigError, match="loop.seconds = -1.0"):
        targetlock.run({"loop": {"seconds": -1.0}})
    s = targetlock.run({"loop": {"seconds": 4.0, "metrics_after": 1.0}, "twin": {"scene": {"path": "static"}}},
                       out=tmp_path / "r")
    assert s["rms_px"] < 5.0          # a static target stays locked
    cfg = targetlock.load_config(tmp_path / "r" / "config.toml")
    assert isinstance(cfg, targetlock.RunConfig) and cfg.loop.seconds == 4.0
    assert (tmp_path / "r" / "run.log").exists()
