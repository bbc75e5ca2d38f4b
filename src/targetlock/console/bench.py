"""Benchmark of the console (``targetlock console --bench``): does watching cost the loop anything?

On the twin (rendered frames, feature tracker, lock engaged on a moving target) it measures, over
windows of ``seconds`` each:

* the loop's lateness per tick (ms; p50, p99, max) with no page attached and with ``pages`` pages
  of headless Chromium attached;
* the CPU time of the console's process (loop + server, in % of one core) in both cases: the
  difference is the cost of serving the pages (JPEG encoding, WebSockets);
* frame-to-screen latency in the browser (ms, p50/p95): from the moment the tracker finished a
  frame to the moment the page drew it on its canvas (both clocks are this machine's).

The viewers run on the same machine, each group in a process of its own session: on Linux (autogroups)
their CPU is then shared like another user's, as with a browser on the operator's desktop.
"""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..config import from_dict
from ..experiments.target_lock import RunConfig
from .server import ConsoleServer
from .session import ConsoleSession

__all__ = ["bench_console"]


def _thread_cpu() -> dict[int, float]:
    """CPU time (s) of each thread of this process (Linux /proc), by native thread id."""
    hz = os.sysconf("SC_CLK_TCK")
    out = {}
    for d in Path("/proc/self/task").iterdir():
        with contextlib.suppress(OSError, IndexError, ValueError):
            f = (d / "stat").read_text().rsplit(")", 1)[1].split()
            out[int(d.name)] = (int(f[11]) + int(f[12])) / hz   # utime + stime
    return out


def _window(session: ConsoleSession, server: ConsoleServer, seconds: float) -> dict:
    assert session._thread is not None and server._thread is not None
    loop_tid, http_tid = session._thread.native_id or 0, server._thread.native_id or 0
    threads0, cpu0, wall0 = _thread_cpu(), time.process_time(), time.perf_counter()
    time.sleep(seconds)
    threads1, cpu, wall = _thread_cpu(), time.process_time() - cpu0, time.perf_counter() - wall0
    used = {tid: threads1[tid] - threads0.get(tid, 0.0) for tid in threads1}
    loop_cpu = used.get(loop_tid, 0.0)
    serve_cpu = cpu - loop_cpu    # the HTTP/WebSocket thread, JPEG encoder threads, everything but the loop
    late = session.lateness_ms()[-int(seconds * session.cfg.loop.rate):]
    return {"lateness_p50_ms": float(np.percentile(late, 50)), "lateness_p99_ms": float(np.percentile(late, 99)),
            "lateness_max_ms": float(late.max()), "ticks": int(late.size), "cpu_percent": 100.0 * cpu / wall,
            "loop_thread_cpu_percent": 100.0 * loop_cpu / wall, "other_threads_cpu_percent": 100.0 * serve_cpu / wall,
            "http_thread_cpu_percent": 100.0 * used.get(http_tid, 0.0) / wall,
            "load_average_1min": os.getloadavg()[0]}


def _ws_clients(port: int, n: int, seconds: float) -> None:
    """``n`` plain WebSocket viewers (frames acknowledged at once, state read), for ``seconds``; run in a
    separate process so that only the serving side is measured in the console's process."""
    import threading
    from websockets.sync.client import connect

    def viewer(kind: str) -> None:
        end = time.monotonic() + seconds
        with connect(f"ws://127.0.0.1:{port}/ws/{kind}", max_size=None, open_timeout=10) as ws:
            while time.monotonic() < end:
                ws.recv(timeout=5)
                if kind == "frames":
                    ws.send("ack")
    threads = [threading.Thread(target=viewer, args=(k,)) for _ in range(n) for k in ("frames", "state")]
    for th in threads:
        th.start()
    for th in threads:
        th.join()


def _browser_pages(url: str, n: int, seconds: float, chromium: str, screenshot: str | None) -> None:
    """``n`` headless Chromium pages on ``url``: prints "ready" once frames flow, keeps them open ``seconds``,
    then prints their frame-to-screen latencies (JSON). Run in a process of its own session."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--disable-gpu"])
        tabs = [browser.new_context(viewport={"width": 1400, "height": 900}).new_page() for _ in range(n)]
        for page in tabs:
            page.goto(url)
        for page in tabs:
            page.wait_for_function("window.tl.frames >= 5", timeout=60000)
            page.evaluate("window.tl.latencies = []; window.tl.frames = 0")
        print("ready", flush=True)
        tabs[0].wait_for_timeout(1000 * seconds)
        lat = [x for page in tabs for x in page.evaluate("window.tl.latencies")]
        frames = [page.evaluate("window.tl.frames") for page in tabs]
        if screenshot:
            tabs[0].screenshot(path=screenshot, full_page=True)
        browser.close()
    print(json.dumps({"latencies": lat, "frames": frames}), flush=True)


def _spawn(code: str) -> subprocess.Popen[str]:
    """A Python child in a session of its own: its CPU is shared like another user's (Linux autogroups),
    not taken from the console's share, as a browser on the operator's desktop would be."""
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)


def bench_console(seconds: float = 5.0, pages: int = 3, chromium: str = "/usr/bin/chromium",
                  screenshot: str | None = None,
                  loop_nice: int | None = -10) -> dict:
    cfg = from_dict(RunConfig, {"vision": True, "realtime": True, "twin": {"scene": {"path": "linear"}}})
    session = ConsoleSession(cfg)
    server = ConsoleServer(session, port=0)
    session.start(loop_nice=loop_nice)
    server.start_in_thread()
    out: dict = {"seconds": seconds, "pages": pages, "loop_nice": loop_nice}
    try:
        time.sleep(1.0)
        session.engage("bench")
        time.sleep(2.0)
        out["no_page"] = _window(session, server, seconds)
        viewers = _spawn(f"from targetlock.console.bench import _ws_clients; _ws_clients({server.port}, {pages}, "
                         f"{seconds + 3.0})")
        end = time.monotonic() + 30.0
        while server.hub.watchers < pages and time.monotonic() < end:   # all viewers connected
            time.sleep(0.05)
        time.sleep(0.5)
        out["ws_viewers"] = _window(session, server, seconds)
        viewers.wait(timeout=60)
        pages_proc = _spawn(f"from targetlock.console.bench import _browser_pages; _browser_pages({server.url()!r}, "
                            f"{pages}, {seconds + 1.0}, {chromium!r}, {screenshot!r})")
        assert pages_proc.stdout is not None
        if pages_proc.stdout.readline().strip() != "ready":
            raise RuntimeError("the browser pages did not start")
        enc0, n0 = server.hub.encode_seconds, server.hub.encoded_frames
        out["with_pages"] = _window(session, server, seconds)
        n = max(server.hub.encoded_frames - n0, 1)
        out["jpeg_encode_ms"] = 1e3 * (server.hub.encode_seconds - enc0) / n
        res = json.loads(pages_proc.stdout.readline())
        pages_proc.wait(timeout=60)
        lat = np.asarray(res["latencies"], float)
        out["frame_to_screen_ms"] = {"p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95)),
                                     "samples": int(lat.size)}
        out["frames_per_page"] = res["frames"]
        out["camera_fps"] = cfg.twin.camera.fps
        out["serving_cpu_percent"] = (out["with_pages"]["other_threads_cpu_percent"]
                                      - out["no_page"]["other_threads_cpu_percent"])
    finally:
        server.stop()
        session.close()
    return out
