"""SIGTERM and SIGHUP end a run like Ctrl-C: drives disabled, data flushed, summary written."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import targetlock
from targetlock.experiments.target_lock import COLUMNS, RunConfig, build_controller, build_rig
from targetlock.loop.runner import ControlLoop
from targetlock.loop.signals import StopSignal, deferred, stop_on_signals

SRC = str(Path(targetlock.__file__).resolve().parent.parent)

CHILD = textwrap.dedent("""
    import sys
    from targetlock.experiments.runfolder import RunFolder
    from targetlock.experiments.target_lock import RunConfig, run_target_lock
    from targetlock.loop.runner import LoopConfig
    from targetlock.loop.signals import StopSignal

    cfg = RunConfig(realtime=True, loop=LoopConfig(seconds=120.0, metrics_after=0.0))
    run = RunFolder("run", cfg, sys.argv[1])
    try:
        run_target_lock(cfg, run)
    except StopSignal as exc:
        print(exc, flush=True)
        sys.exit(exc.exit_code)
""")


def csv_rows(path: Path) -> int:
    try:
        return max(0, len(path.read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_real_process_stopped_by_a_signal_keeps_its_data_and_writes_the_summary(tmp_path, sig):
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        deadline = time.monotonic() + 90
        while csv_rows(out / "timeseries.csv") < 60 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)        # > 1 s of the run on disk: the loop is running
        assert proc.poll() is None, proc.stderr.read()[-2000:]
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, stderr[-2000:]
    assert f"stopped by {sig.name}" in stdout
    assert "drives disabled (confirmed by the drives)" in (out / "run.log").read_text()   # the clear message
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped"] == sig.name and summary["drives_disabled"] is True
    data = np.loadtxt(out / "timeseries.csv", delimiter=",", skiprows=1, ndmin=2)
    assert data.shape == (summary["rows"], len(COLUMNS))                # every row flushed, none torn
    np.testing.assert_allclose(np.diff(data[:, 0]), 0.02, atol=1e-9)    # no tick lost in the middle
    assert summary["recorded_seconds"] == pytest.approx(data[-1, 0], abs=1e-9)
    assert np.isfinite(summary["rms_px"]) and (out / "tracking.png").stat().st_size > 0


def test_a_signal_inside_a_deferred_block_is_raised_when_the_block_ends_and_repeats_are_ignored():
    done = []
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(StopSignal) as info:
        with stop_on_signals():
            with deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGHUP)      # a second signal while stopping
                time.sleep(0.01)
                done.append("rest of the tick")
            done.append("after the tick")
    assert done == ["rest of the tick"]
    assert info.value.signal_name == "SIGTERM" and info.value.exit_code == 143
    assert isinstance(info.value, KeyboardInterrupt)     # every Ctrl-C path handles it
    assert signal.getsignal(signal.SIGTERM) is before            # the previous handler is back


def test_a_stop_signal_in_the_loop_disables_the_drives_after_a_complete_tick():
    cfg = RunConfig()
    rig = build_rig(cfg)
    ticks = []

    def on_tick(tick):
        ticks.append(tick.index)
        if tick.index == 30:
            os.kill(os.getpid(), signal.SIGTERM)   # arrives in the middle of tick 30

    with pytest.raises(StopSignal):
        with stop_on_signals():
            ControlLoop(rig, build_controller(cfg, rig), rate=50).run(5.0, on_tick)
    assert ticks == list(range(1, 31))             # tick 30 finished, no tick after it
    assert rig.drives.is_disabled()
    with pytest.raises(RuntimeError, match="disabled"):
        rig.drives.send_setpoints(np.zeros(2, dtype=np.int64))
