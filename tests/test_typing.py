"""The type check runs with the test suite: `mypy` with the configuration in pyproject.toml."""
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None, reason="mypy not installed (pip install -e .[test])")
def test_package_passes_mypy():
    res = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]


def test_package_ships_its_type_marker():
    assert (ROOT / "src" / "targetlock" / "py.typed").is_file()
    assert "py.typed" in (ROOT / "pyproject.toml").read_text()
