"""Evaluation: scoring rules and a short end-to-end run."""
import json
from dataclasses import replace

import numpy as np
import pytest

from targetlock.config import ConfigError, validate
from targetlock.vision import EvalSettings, Frame, TrackResult, evaluate, render_sequence, score
from targetlock.vision.evaluate import markdown_tables


def _frame(truth, visible=True):
    return Frame(np.zeros((4, 4, 3), np.uint8), np.array(truth, float), visible)


def _res(pos, valid=True):
    return TrackResult(np.array(pos, float), 1.0 if valid else 0.0, valid, False)


def test_scoring_rules():
    frames = [_frame((10, 10)), _frame((10, 10)), _frame((10, 10)),             # visible
              _frame((50, 50), False), _frame((50, 50), False), _frame((50, 50), False)]  # occluded
    results = [_res((10.5, 10)),           # visible, 0.5 px: correct
               _res((30, 10)),             # visible, 20 px: wrong (false lock)
               _res((10, 10), False),      # visible, no estimate: wrong
               _res((0, 0), False),        # occluded, reports nothing: correct
               _res((52, 50)),             # occluded, inferred within 8 px: correct
               _res((90, 50))]             # occluded, valid but far: wrong (false lock)
    m = score(frames, results, threshold_px=8.0)
    assert m["tracked_fraction"] == pytest.approx(3 / 6)
    assert m["tracked_in_view_fraction"] == pytest.approx(1 / 3)   # issue 14's goal: visible frames only
    assert m["false_lock_fraction"] == pytest.approx(2 / 6)
    assert m["median_px"] == pytest.approx(10.25)          # errors of valid visible estimates: 0.5, 20
    # delta_avg over visible frames (4, 8, 16, 32, 64 px): [1/3, 1/3, 1/3, 2/3, 2/3]
    assert m["delta_avg"] == pytest.approx((3 * (1 / 3) + 2 * (2 / 3)) / 5)
    assert m["visible_frames"] == 3 and m["valid_frames"] == 4


def test_eval_settings_are_validated():
    with pytest.raises(ConfigError, match="sequences"):
        validate(EvalSettings(sequences=("slow", "nonsense")))
    with pytest.raises(ConfigError, match="tracker"):
        validate(EvalSettings(tracker="magic"))


def test_sequences_are_deterministic():
    cfg = EvalSettings(frames=10)
    a = render_sequence("occlusion", cfg, seed=2)
    b = render_sequence("occlusion", cfg, seed=2)
    assert all(np.array_equal(x.image, y.image) for x, y in zip(a, b))
    assert all(np.array_equal(x.truth_px, y.truth_px) for x, y in zip(a, b))


def test_evaluate_short_run_is_json_ready_and_good():
    cfg = EvalSettings(frames=24, sequences=("slow", "occlusion", "rotation"), photos=(), references=())
    out = evaluate(cfg, seed=1)
    json.dumps(out)                                          # CLI --json
    o = out["overall"]
    assert set(out["sequences"]) == {"slow", "occlusion", "rotation"}
    assert o["frames"] == 3 * 23
    assert o["median_px"] < 1.0 and o["tracked_fraction"] >= 0.95 and o["false_lock_fraction"] == 0.0
    assert o["fps"] > 0 and o["render_ms"] > 0  # speed goals: `targetlock bench vision`, not a timed test
    assert o["selection_failures"] == 0 and all(m["selection_failure"] is None for m in out["sequences"].values())
    # The mucosa's windows are textured: no selection warns, so the unwarned share is the whole in-view share.
    assert o["selection_warnings"] == 0 and all(m["selection_warning"] is None for m in out["sequences"].values())
    assert 0.95 <= o["tracked_in_view_fraction"] <= 1.0
    assert o["tracked_in_view_unwarned"] == pytest.approx(o["tracked_in_view_fraction"])
    for m in out["sequences"].values():
        assert m["selected"] and 0.0 <= m["delta_avg"] <= 1.0


def test_occlusion_sequence_really_occludes():
    frames = render_sequence("occlusion", EvalSettings(), seed=0)
    hidden = [f.occluded for f in frames]
    assert 5 <= sum(hidden) <= 30 and not hidden[0] and not hidden[-1]
    leave = render_sequence("leave", EvalSettings(), seed=0)
    assert any(not f.visible and not f.occluded for f in leave) and leave[-1].visible


def test_eval_settings_refuse_unknown_photos_and_references():
    with pytest.raises(ConfigError, match="photos"):
        validate(EvalSettings(photos=("holiday",)))
    with pytest.raises(ConfigError, match="references"):
        validate(EvalSettings(references=("magic",)))


def test_real_photograph_sequences_with_reference_trackers_in_the_same_run():
    """A real photograph (scikit-image's bundled retina, CC0) rendered with known ground truth; the
    OpenCV references run on the very same frames and get the same metrics."""
    cfg = EvalSettings(frames=30, sequences=("slow",), photos=("retina",), references=("mil", "lk"))
    out = evaluate(cfg, seed=0)
    json.dumps(out)
    assert set(out["sequences"]) == {"slow", "retina/slow"}
    assert set(out["content"]) == {"mucosa", "retina"} and "CC0" in out["photo_licences"]["retina"]
    ret = out["content"]["retina"]
    assert ret["tracked_fraction"] >= 0.95 and ret["false_lock_fraction"] == 0.0 and ret["median_px"] < 1.0
    for who in ("mil", "lk"):
        ref = out["references"][who]
        assert ref["overall"]["frames"] == out["overall"]["frames"]          # the same frames
        assert set(ref["content"]) == {"mucosa", "retina"} and ref["overall"]["speed_ratio"] > 0
        assert set(ref["sequences"]) == {"slow", "retina/slow"}                # per sequence, too
        assert ref["sequences"]["retina/slow"]["frames"] == out["sequences"]["retina/slow"]["frames"]
        assert out["overall"]["delta_avg"] >= ref["overall"]["delta_avg"]
    md = markdown_tables(out)   # docs/vision.md's tables
    lines = md.splitlines()
    assert sum(ln.startswith("| retina/slow |") for ln in lines) == 1
    assert sum(ln.startswith("| retina | ") for ln in lines) == 3          # ours, MIL, plain LK
    assert "of 2 sequences (seed 0)" in md


def test_the_trackers_settings_are_part_of_the_evaluation(tmp_path, capsys):
    """`vision-eval --set feature.FIELD=VALUE` reaches the feature tracker, the run folder's config
    records it (a result can be reproduced from its folder alone), and a bad value names the field
    and its range."""
    import tomllib

    from targetlock.cli import main
    from targetlock.vision import TrackerSettings
    argv = ["vision-eval", "--sequences", "slow", "--frames", "12", "--set", "photos=[]", "--set", "references=[]",
            "--json", "-q"]
    assert main([*argv, "--set", "feature.min_inliers=500", "--out", str(tmp_path / "a")]) == 0
    strict = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    default = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # no window has 500 corners: nothing is selected; the default selects and tracks
    assert strict["selection_failures"] == 1 and strict["tracked_fraction"] == 0.0
    assert default["selection_failures"] == 0 and default["tracked_fraction"] >= 0.9
    cfg = tomllib.loads((tmp_path / "a" / "config.toml").read_text())
    assert cfg["feature"]["min_inliers"] == 500
    assert cfg["feature"]["context_isotropy"] == TrackerSettings().context_isotropy   # every field, resolved
    assert main([*argv, "--set", "feature.context_isotropy=2", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "feature.context_isotropy" in err and "[0.0, 1.0]" in err


def test_several_seeds_are_pooled_and_every_scored_frame_is_reported():
    """`seed=[0, 1]` runs each seed's sequences in turn and pools every figure over them: the pooled
    figures are those of the two single-seed runs' frames together, and the per-frame rows
    (``on_frames``) carry the same scoring."""
    from targetlock.vision.evaluate import FRAME_COLUMNS
    cfg = EvalSettings(frames=12, sequences=("slow", "occlusion"), photos=(), references=("lk",))
    rows: list[tuple] = []
    both = evaluate(cfg, seed=[0, 1], on_frames=rows.extend)
    one = [evaluate(cfg, seed=s) for s in (0, 1)]
    assert both["seed"] == [0, 1] and set(both["sequences"]) == {"0:slow", "0:occlusion", "1:slow", "1:occlusion"}
    for s, single in zip((0, 1), one):
        for name, m in single["sequences"].items():
            assert both["sequences"][f"{s}:{name}"]["tracked_fraction"] == m["tracked_fraction"]
    o = both["overall"]
    assert o["frames"] == sum(r["overall"]["frames"] for r in one) == 2 * 2 * 11
    assert o["tracked_fraction"] == pytest.approx(np.mean([r["overall"]["tracked_fraction"] for r in one]))
    for s, single in zip(("0", "1"), one):   # each seed's own figures beside the pooled ones
        assert both["per_seed"][s]["tracked_fraction"] == single["overall"]["tracked_fraction"]
        assert both["per_seed"][s]["median_px"] == single["overall"]["median_px"]
    assert "per_seed" not in one[0]
    assert both["references"]["lk"]["overall"]["frames"] == o["frames"]
    # rows: every scored frame of every sequence, seed and tracker (ours and the reference)
    assert len(rows) == 2 * 2 * 2 * 11 and all(len(r) == len(FRAME_COLUMNS) for r in rows)
    col = {c: i for i, c in enumerate(FRAME_COLUMNS)}
    ours = [r for r in rows if r[col["tracker"]] == "feature"]
    assert {r[col["seed"]] for r in ours} == {0, 1} and len(ours) == o["frames"]
    assert np.mean([r[col["correct"]] for r in ours]) == pytest.approx(o["tracked_fraction"])
    err = [r[col["error_px"]] for r in ours if r[col["valid"]] and r[col["visible"]]]
    assert np.median(err) == pytest.approx(o["median_px"], abs=1e-3)
    hidden = [r for r in ours if not r[col["visible"]]]
    assert hidden and all(r[col["occluded"]] for r in hidden)     # the instrument covers the target
    assert all(np.isnan(r[col["x_px"]]) and np.isnan(r[col["error_px"]]) for r in ours if not r[col["valid"]])
    with pytest.raises(ValueError, match="distinct"):
        evaluate(cfg, seed=[1, 1])


def test_an_evaluation_keeps_only_the_frames_of_the_sequence_it_runs():
    """Pooled scoring keeps each frame's ground truth, not its image: three sequences need about the
    memory of one (``--frames`` in the thousands must not exhaust a lab PC's memory)."""
    import tracemalloc
    cfg = EvalSettings(frames=30, photos=(), references=())

    def peak(sequences: tuple[str, ...]) -> int:
        tracemalloc.start()
        try:
            evaluate(replace(cfg, sequences=sequences), seed=0)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    frames_bytes = 30 * 576 * 720 * 3      # one sequence's images
    one, three = peak(("slow",)), peak(("slow", "tip", "rotation"))
    assert three - one < 0.5 * frames_bytes, (one, three)


def test_vision_eval_writes_every_scored_frame_and_pools_seeds(tmp_path, capsys):
    """`vision-eval --seed 0 2`: one pooled summary over both seeds, and `frames.csv` in the run folder
    with a row per scored frame and tracker (what a researcher reads to find where a tracker fails)."""
    import csv

    from targetlock.cli import main
    from targetlock.vision.evaluate import FRAME_COLUMNS
    out = tmp_path / "e"
    assert main(["vision-eval", "--sequences", "slow", "--frames", "12", "--seed", "0", "2", "--set", "photos=[]",
                 "--set", 'references=["lk"]', "--out", str(out), "--json", "-q"]) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["seed"] == [0, 2] and set(s["sequences"]) == {"0:slow", "2:slow"}
    with (out / "frames.csv").open(newline="") as fh:
        table = list(csv.DictReader(fh))
    assert list(table[0]) == list(FRAME_COLUMNS) and len(table) == 2 * 2 * 11
    ours = [r for r in table if r["tracker"] == "feature"]
    assert np.mean([int(r["correct"]) for r in ours]) == pytest.approx(s["tracked_fraction"])
    assert {r["seed"] for r in ours} == {"0", "2"}


def test_seeds_run_on_worker_processes_give_the_same_figures():
    """`evaluate(executor=...)` (`vision-eval --workers N`): the seeds run in other processes, finish in
    any order, and the merged result and the per-frame rows are those of running them here."""
    from concurrent.futures import ProcessPoolExecutor
    cfg = EvalSettings(frames=12, sequences=("slow", "leave"), photos=(), references=("lk",))
    timed = ("fps", "fps_locked", "fps_lost", "render_ms", "speed_ratio")

    def untimed(d):
        if isinstance(d, dict):
            return {k: untimed(v) for k, v in d.items() if k not in timed}
        return d
    here_rows: list[tuple] = []
    here = evaluate(cfg, seed=[2, 0, 1], on_frames=here_rows.extend)
    away_rows: list[tuple] = []
    with ProcessPoolExecutor(max_workers=2) as pool:
        away = evaluate(cfg, seed=[2, 0, 1], on_frames=away_rows.extend, executor=pool)
    assert json.dumps(untimed(away), sort_keys=True) == json.dumps(untimed(here), sort_keys=True)
    assert list(away["sequences"]) == ["2:slow", "2:leave", "0:slow", "0:leave", "1:slow", "1:leave"]
    assert sorted(map(repr, away_rows)) == sorted(map(repr, here_rows))   # repr: NaN equals NaN


def test_a_stopped_vision_eval_keeps_the_frames_it_scored(tmp_path, capsys, monkeypatch):
    """Ctrl-C during the second sequence: `frames.csv` still holds every row of the first."""
    import csv
    import importlib

    from targetlock.cli import main
    ev = importlib.import_module("targetlock.vision.evaluate")   # the module: the package's `evaluate` is the function
    calls = []
    real = ev._run_tracker

    def interrupted(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **kw)
    monkeypatch.setattr(ev, "_run_tracker", interrupted)
    out = tmp_path / "e"
    assert main(["vision-eval", "--sequences", "slow", "rotation", "--frames", "12", "--set", "photos=[]",
                 "--set", "references=[]", "--out", str(out), "-q"]) != 0
    assert "interrupted" in capsys.readouterr().err
    with (out / "frames.csv").open(newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 11 and {r["sequence"] for r in table} == {"slow"}


def test_a_killed_vision_eval_keeps_every_sequence_it_finished(tmp_path):
    """SIGKILL (no chance to clean up) once the first sequence is scored: `frames.csv` holds whole
    sequences, each row complete (written and flushed as each sequence finishes)."""
    import csv
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / "e"
    frames = 150
    proc = subprocess.Popen([sys.executable, "-m", "targetlock", "vision-eval", "-q", "--sequences", "slow", "rotation",
                             "scale", "--frames", str(frames), "--set", "photos=[]", "--set", "references=[]",
                             "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    path = out / "frames.csv"
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if path.exists() and path.read_text().count("\n") > 1:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    with path.open(newline="") as fh:
        table = list(csv.DictReader(fh))
    assert table and len(table) % (frames - 1) == 0 and len(table) < 3 * (frames - 1)
    assert all(r["selection_warned"] in ("0", "1") for r in table)     # the last row is whole
