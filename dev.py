#!/usr/bin/env python3
"""One entry point for a fresh machine: set up a virtual environment, then run a job.

    python3 dev.py demo     # set up, then run the default target-lock experiment on the twin
    python3 dev.py test     # set up, then run the whole test suite

Needs only python3 >= 3.11 and access to the package registry. The environment lives in
``.venv``; it installs the exact versions of ``requirements.lock`` (made by ``scripts/lock.py``
from the ranges in ``pyproject.toml``) and is reinstalled only when either file changes.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".targetlock-install-stamp"
LOCK = ROOT / "requirements.lock"
EXTRAS = ("test", "sweep", "gym")


def _python() -> Path:
    return VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def setup() -> Path:
    if sys.version_info < (3, 11):
        sys.exit(f"targetlock needs Python >= 3.11, this is {sys.version.split()[0]}")
    if not LOCK.exists():
        sys.exit(f"{LOCK.name} is missing: run `python3 scripts/lock.py` to resolve the dependency ranges")
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + LOCK.read_bytes()).hexdigest()
    if not _python().exists():
        print(f"[dev] creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    if not STAMP.exists() or STAMP.read_text() != want:
        print(f"[dev] installing targetlock with the locked versions of {LOCK.name}", flush=True)
        pip = [str(_python()), "-m", "pip"]
        subprocess.run([*pip, "install", "-q", "--upgrade", "pip"], check=True)
        subprocess.run([*pip, "install", "-q", "-r", str(LOCK)], check=True)
        # the project itself without resolving again: every dependency comes from the lock
        subprocess.run([*pip, "install", "-q", "--no-deps", "-e", f"{ROOT}[{','.join(EXTRAS)}]"], check=True)
        # the lock must satisfy pyproject's ranges (and itself): a stale lock fails here, not in a test
        check = subprocess.run([*pip, "check"], capture_output=True, text=True)
        if check.returncode != 0:
            sys.exit(f"[dev] {LOCK.name} does not satisfy pyproject.toml: {check.stdout.strip()}\n"
                     "      run `python3 scripts/lock.py` and commit both files")
        STAMP.write_text(want)
    return _python()


# ------------------------------------------------------------------------------ browser for the console tests
CHROMIUM = Path("/usr/bin/chromium")


def ensure_browser() -> None:
    """The console's tests drive Debian's ``chromium`` (headless, through Playwright): install it when
    missing and we are root on Debian, else stop with a message naming the package."""
    if CHROMIUM.exists():
        return
    debian = Path("/etc/debian_version").exists() and shutil.which("apt-get") is not None
    if debian and hasattr(os, "geteuid") and os.geteuid() == 0:
        print("[dev] installing Debian's chromium for the console's browser tests", flush=True)
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        subprocess.run(["apt-get", "update", "-q"], check=True, env=env)
        subprocess.run(["apt-get", "install", "-y", "-q", "chromium"], check=True, env=env)
        if CHROMIUM.exists():
            return
    sys.exit(f"[dev] the console tests need a Chromium browser at {CHROMIUM}: install the Debian package "
             f"'chromium' (apt-get install chromium, as root)")


def main(argv: list[str]) -> int:
    jobs = {
        "demo": ["-m", "targetlock", "run"],
        "test": ["-m", "pytest"],
    }
    if not argv or argv[0] not in jobs:
        print(__doc__)
        return 2
    py = setup()
    if argv[0] == "test":
        ensure_browser()
    cmd = [str(py), *jobs[argv[0]], *argv[1:]]
    print("[dev] " + " ".join(cmd[1:]), flush=True)
    return subprocess.run(cmd, cwd=ROOT).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
