"""The console driven in a real browser (headless Chromium from Debian's ``chromium`` package, via Playwright).

One twin session and one server for the module (the twin with rendered frames on the wall clock, static
target); one browser. ``python3 dev.py test`` installs chromium when missing.
"""
from __future__ import annotations

import json
import math
import os
import time
import urllib.error
import urllib.request

import pytest

from targetlock.config import from_dict
from targetlock.console.server import ConsoleServer
from targetlock.console.session import ConsoleSession
from targetlock.experiments.target_lock import RunConfig

CHROMIUM = os.environ.get("TARGETLOCK_CHROMIUM", "/usr/bin/chromium")


def _wait(cond, timeout: float, what: str, every: float = 0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _run_for(session, seconds: float) -> None:
    """Wait until the loop has run ``seconds`` more of its own time (s). Not wall time: on a loaded host
    the loop falls behind the wall clock (it runs every tick late, then catches up)."""
    t0 = session.time
    _wait(lambda: session.time >= t0 + seconds, 30 + 10 * seconds, f"{seconds} s of loop time")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    cfg = from_dict(RunConfig, {"vision": True, "realtime": True, "twin": {"scene": {"path": "static"}}})
    s = ConsoleSession(cfg, runs_root=str(tmp_path_factory.mktemp("runs")))
    s.start()
    yield s
    s.close()


@pytest.fixture(scope="module")
def server(session):
    srv = ConsoleServer(session, host="127.0.0.1", port=0)
    srv.start_in_thread()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.fail(f"{CHROMIUM} not found: install Debian's 'chromium' package (python3 dev.py test does it as root)")
    from playwright.sync_api import sync_playwright
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser, server):
    p = browser.new_page(viewport={"width": 1400, "height": 900})
    p.goto(server.url())
    p.wait_for_function("window.tl.frames >= 3 && window.tl.status !== null", timeout=30000)
    yield p
    p.close()


def _frame(page) -> dict:
    return page.evaluate("window.tl.lastFrame")


def _click_image(page, x: float, y: float) -> None:
    box = page.locator("#view").bounding_box()
    w, h = page.evaluate("[document.getElementById('view').width, document.getElementById('view').height]")
    page.mouse.click(box["x"] + x * box["width"] / w, box["y"] + y * box["height"] / h)


def test_page_loads_with_stop_and_frames_arrive(page, session):
    assert page.title() == "targetlock console"
    assert page.locator("#stop").is_visible()
    n0 = page.evaluate("window.tl.frames")
    page.wait_for_function(f"window.tl.frames >= {n0 + 10}", timeout=15000)
    f = _frame(page)
    cam = session.cfg.twin.camera
    assert (f["width"], f["height"]) == (cam.width, cam.height)
    assert f["valid"] and not f["lost"]
    # the view was drawn: the canvas is not blank
    lit = page.evaluate("""(() => { const c = document.getElementById('view');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let s = 0;
        for (let i = 0; i < d.length; i += 4 * 97) s += d[i] + d[i + 1] + d[i + 2]; return s; })()""")
    assert lit > 0
    assert "loop running" in page.locator("#status").inner_text()


def test_click_selects_target_where_clicked(page, session):
    cam = session.cfg.twin.camera
    x, y = cam.cx + 90.0, cam.cy + 55.0
    _click_image(page, x, y)
    _wait(lambda: session.actions and session.actions[-1]["action"] == "select", 15, "the select action")

    def near():
        f = _frame(page)
        return f["valid"] and f["x"] is not None and math.hypot(f["x"] - x, f["y"] - y) < 6.0
    page.wait_for_function(f"""(() => {{ const f = window.tl.lastFrame;
        return f.valid && f.x !== null && Math.hypot(f.x - {x}, f.y - {y}) < 6; }})()""", timeout=10000)
    assert near()


def test_a_click_that_cannot_be_tracked_says_why_and_keeps_the_target(page, session):
    cam = session.cfg.twin.camera
    x, y = cam.cx + 90.0, cam.cy + 55.0
    _click_image(page, x, y)
    page.wait_for_function("document.getElementById('selection').textContent.startsWith('target selected')",
                           timeout=15000)
    _click_image(page, 4.0, 4.0)              # the dark corner outside the endoscope's round view
    page.wait_for_function("document.getElementById('selection').textContent.startsWith('selection failed')",
                           timeout=15000)
    text = page.locator("#selection").inner_text()
    assert "field of view" in text and "still following the target selected before" in text
    n0 = page.evaluate("window.tl.frames")
    page.wait_for_function(f"window.tl.frames >= {n0 + 5}", timeout=15000)
    f = _frame(page)
    assert f["valid"] and math.hypot(f["x"] - x, f["y"] - y) < 6.0


def test_engage_brings_error_down(page, session):
    cam = session.cfg.twin.camera
    x, y = cam.cx - 80.0, cam.cy + 60.0
    _click_image(page, x, y)
    page.wait_for_function(f"""(() => {{ const f = window.tl.lastFrame;
        return f.valid && Math.hypot(f.x - {x}, f.y - {y}) < 6; }})()""", timeout=10000)
    before = math.hypot(_frame(page)["x"] - cam.cx, _frame(page)["y"] - cam.cy)
    assert before > 80
    page.locator("#engage").click()
    page.wait_for_function("window.tl.status.locked === true", timeout=15000)
    page.wait_for_function(f"""(() => {{ const f = window.tl.lastFrame;
        return f.valid && Math.hypot(f.x - {cam.cx}, f.y - {cam.cy}) < 10; }})()""", timeout=30000)
    f = _frame(page)
    assert math.hypot(f["x"] - cam.cx, f["y"] - cam.cy) < 10 < before / 8
    assert "ENGAGED" in page.locator("#lockstate").inner_text()


def test_gain_change_takes_effect_and_bad_gain_is_refused(page, session):
    page.fill("input[name=i_gain]", "-5")
    page.locator("#apply").click()
    page.wait_for_function("window.tl.errors.length > 0", timeout=15000)
    msg = page.locator("#message").inner_text()
    assert "controller.i_gain = -5.0 is out of range; allowed: [-1.0, 100000.0]" in msg
    assert session.switch.inner.cfg.integral_gain == 300.0      # unchanged: the controller's own default
    page.fill("input[name=i_gain]", "150")
    page.select_option("#kind", "pi")
    page.locator("#apply").click()
    # the loop swapped in the new controller at a tick (no restart), and the page shows it
    _wait(lambda: session.switch.inner.cfg.i_gain == 150.0 and session.switch.inner.cfg.kind == "pi", 15, "the new controller")
    page.wait_for_function("window.tl.status.controller.i_gain === 150 && window.tl.status.controller.kind === 'pi'",
                           timeout=15000)
    assert any(a["action"] == "tune" and a.get("i_gain") == 150 for a in session.actions)


def test_the_nearest_the_target_can_be_is_stated_on_the_page(page, session):
    """A stated working distance reaches the controller's knowledge (its caution); one that contradicts
    the assumed distance is refused with the config's message."""
    assert page.input_value("input[name='knowledge.nearest_depth']") == "0.01"
    page.fill("input[name='knowledge.nearest_depth']", "0.5")
    n0 = page.evaluate("window.tl.errors.length")
    page.locator("#apply").click()
    page.wait_for_function(f"window.tl.errors.length > {n0}", timeout=15000)
    assert "knowledge.depth = 0.12 m lies outside knowledge.nearest_depth" in page.locator("#message").inner_text()
    assert session.cfg.knowledge.nearest_depth == 0.01
    page.fill("input[name='knowledge.nearest_depth']", "0.05")
    page.locator("#apply").click()
    _wait(lambda: session.switch.inner.knowledge.depth_range == (0.05, 0.15), 15, "the stated distance")
    page.wait_for_function("window.tl.status.knowledge.nearest_depth === 0.05", timeout=15000)
    assert "target 5.0-15.0 cm away" in page.locator("#status").inner_text()
    assert any(a["action"] == "tune" and a.get("knowledge.nearest_depth") == 0.05 for a in session.actions)


def test_stop_key_disables_drives_until_explicit_enable(page, session):
    if not session.switch.locked:
        page.locator("#engage").click()
        _wait(lambda: session.switch.locked, 15, "engaged")
    page.locator("body").press("Space")
    page.wait_for_function("window.tl.status.drives.enabled === false", timeout=15000)
    assert session.safe.tripped
    assert "operator stop" in session.safe.fault()
    assert not session.switch.locked
    _run_for(session, 0.3)      # the handle finishes the motion it had when stopped (drive lag, a few ticks)
    refused = session.drives.refused
    pos = session.safe.positions().copy()
    _run_for(session, 0.5)
    assert session.drives.refused > refused            # the loop runs on, no set-point reaches the drives
    assert (abs(session.safe.positions() - pos) <= 2).all()
    assert page.locator("#engage").is_disabled()
    assert session.safe.tripped                        # nothing re-enables by itself
    page.locator("#enable").click()
    page.wait_for_function("window.tl.status.drives.enabled === true", timeout=15000)
    assert not session.safe.tripped and not session.switch.locked   # re-enabled, lock still released


def test_stop_button_is_a_single_click(page, session):
    dialogs = []
    page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
    page.locator("#stop").click()
    page.wait_for_function("window.tl.status.drives.enabled === false", timeout=15000)
    assert dialogs == []
    page.locator("#enable").click()
    page.wait_for_function("window.tl.status.drives.enabled === true", timeout=15000)


def test_not_on_loopback_every_request_needs_the_token(browser, session):
    srv = ConsoleServer(session, host="0.0.0.0", port=0, token="s3cret-token")
    srv.start_in_thread()
    try:
        base = f"http://127.0.0.1:{srv.port}"
        for path in ("/", "/api/state", "/static/console.js"):
            with pytest.raises(urllib.error.HTTPError) as exc:
                urllib.request.urlopen(base + path, timeout=5)
            assert exc.value.code == 401
        req = urllib.request.Request(base + "/api/stop", data=b"{}", method="POST")
        with pytest.raises(urllib.error.HTTPError) as exc:
            urllib.request.urlopen(req, timeout=5)
        assert exc.value.code == 401 and not session.safe.tripped
        ok = urllib.request.Request(base + "/api/state", headers={"X-Targetlock-Token": "s3cret-token"})
        assert json.load(urllib.request.urlopen(ok, timeout=5))["rig"] == "twin"
        # a WebSocket needs the token too, and is refused from a foreign origin even with it
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect
        with pytest.raises(InvalidStatus):
            connect(f"ws://127.0.0.1:{srv.port}/ws/state", open_timeout=5)
        with pytest.raises(InvalidStatus):
            connect(f"ws://127.0.0.1:{srv.port}/ws/state?token=s3cret-token", origin="http://evil.example",
                    open_timeout=5)
        # the browser: refused without the token, works with the printed address (cookie for the sockets)
        p = browser.new_page()
        try:
            assert p.goto(base + "/").status == 401
            assert p.goto(srv.url().replace("0.0.0.0", "127.0.0.1")).status == 200
            p.wait_for_function("window.tl.frames >= 2 && window.tl.status !== null", timeout=20000)
        finally:
            p.close()
    finally:
        srv.stop()


def test_record_writes_a_run_folder(page, session):
    page.locator("#record").click()
    page.wait_for_function("window.tl.status.recording !== null", timeout=15000)
    folder = session.status()["recording"]
    _run_for(session, 1.5)
    page.locator("#record").click()
    page.wait_for_function("window.tl.status.recording === null", timeout=15000)
    from pathlib import Path
    run = Path(folder)
    for name in ("config.toml", "timeseries.csv", "tracking.png", "summary.json"):
        assert (run / name).is_file(), name
    rows = (run / "timeseries.csv").read_text().splitlines()
    assert rows[0].startswith("t,err_x,err_y,err")
    # Every tick the loop ran while recording, once (on a loaded host the loop runs fewer ticks than
    # 50 per second of its own time, so the count is checked against the loop's own ticks).
    recorded = [float(r.split(",")[0]) for r in rows[1:]]
    assert recorded == sorted(recorded) and recorded[-1] - recorded[0] >= 1.0
    _, loop_rows, _ = session.rows_since(-1)
    ran = [r[0] for r in loop_rows if recorded[0] - 1e-3 <= r[0] <= recorded[-1] + 1e-3]
    assert len(recorded) == len(ran)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["controller"] == session.cfg.controller.kind and summary["seconds"] > 1.0
    assert any(a["action"] == "record-start" for a in summary["actions"])


def test_twin_target_path_changes_without_a_jump(page, session):
    scene = session.rig.scene
    before = scene.target_position(session.time)
    page.select_option("#path", "ellipse")
    _wait(lambda: scene.path == "ellipse", 15, "the ellipse path")
    t = session.time
    assert float(abs(scene.target_position(t) - before).max()) < 0.01     # m: continuous
    _run_for(session, 2.5)
    assert float(abs(scene.target_position(session.time) - before).max()) > 0.002   # and it moves now
    page.select_option("#path", "static")
    _wait(lambda: scene.path == "static", 15, "the static path")


def test_shift_drag_moves_the_twin_target_by_the_dragged_pixels(page, session):
    scene = session.rig.scene
    base = scene.base.copy()
    box = page.locator("#view").bounding_box()
    w = page.evaluate("document.getElementById('view').width")
    k = box["width"] / w                                   # CSS px per image px
    x0, y0 = box["x"] + 200 * k, box["y"] + 200 * k
    page.keyboard.down("Shift")
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move(x0 + 20 * k, y0 + 10 * k, steps=5)
    page.mouse.move(x0 + 40 * k, y0 - 30 * k, steps=5)
    page.mouse.up()
    page.keyboard.up("Shift")
    _wait(lambda: session.actions[-1]["action"] == "target-move", 15, "the target-move action")
    a = session.actions[-1]
    assert a["dx"] == pytest.approx(40, abs=1.5) and a["dy"] == pytest.approx(-30, abs=1.5)
    cam, d = session.cfg.twin.camera, session.cfg.twin.scene.distance
    moved = scene.base - base
    assert moved[0] == pytest.approx(a["dx"] * d / cam.fx, rel=1e-6) and moved[1] == pytest.approx(a["dy"] * d / cam.fy, rel=1e-6)


def _frame_seq(message: bytes) -> int:
    """The frame number in a /ws/frames message (4-byte header length, JSON header, JPEG)."""
    n = int.from_bytes(message[:4], "big")
    return json.loads(message[4:4 + n])["seq"]


def test_a_page_that_stops_reading_never_holds_the_loop(server, session):
    import contextlib

    from websockets.sync.client import connect
    url = f"ws://127.0.0.1:{server.port}/ws/frames"
    with contextlib.ExitStack() as stack:
        stalled = [stack.enter_context(connect(url, open_timeout=5, max_size=None)) for _ in range(2)]
        stalled[0].recv(timeout=10)       # one frame, then never acknowledge; the other never reads at all
        i0, _, _ = session.rows_since(1 << 62)
        # A page that does read still gets new frames, one after each acknowledgement.
        reader = stack.enter_context(connect(url, open_timeout=5, max_size=None))
        seqs = []
        for _ in range(5):
            seqs.append(_frame_seq(reader.recv(timeout=30)))
            reader.send("ack")
        assert all(b > a for a, b in zip(seqs, seqs[1:])), seqs
        # The loop ticks on while both stay stalled: a second's worth of ticks. The bound is generous on
        # purpose: on a loaded 2-core host the loop gets a fraction of a core and runs seconds behind the wall
        # clock (then catches up), but a loop held by the stalled pages never gets there.
        _wait(lambda: session.rows_since(1 << 62)[0] - i0 >= session.cfg.loop.rate, 30,
              "a second's worth of loop ticks while two pages stall")
        assert session.status()["running"] and session.error is None
