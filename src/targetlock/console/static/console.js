// targetlock console page: frames and state over WebSockets, actions as POSTs. No build step, no
// external assets. window.tl exposes what the tests and the latency benchmark read.
"use strict";
const tl = window.tl = { frames: 0, latencies: [], status: null, lastFrame: null, errors: [] };
const $ = (id) => document.getElementById(id);
const view = $("view"), vctx = view.getContext("2d");
const wsBase = (location.protocol === "https:" ? "wss://" : "ws://") + location.host;
const HISTORY = 20.0;   // s of plot history

function say(text, bad) { $("message").textContent = text; $("message").style.color = bad ? "#ff6b6b" : "#ffb347"; if (bad) tl.errors.push(text); }

async function act(name, body) {
  try {
    const r = await fetch("/api/" + name, { method: "POST", headers: { "content-type": "application/json" },
                                             body: JSON.stringify(body || {}) });
    const j = await r.json().catch(() => ({ error: r.status + " " + r.statusText }));
    if (!r.ok) { say(name + ": " + (j.error || r.status), true); return null; }
    say(name + " ok", false);
    return j;
  } catch (e) { say(name + ": " + e, true); return null; }
}

// ------------------------------------------------------------------ stop: always visible, never a dialog
function stop() { act("stop"); }
$("stop").addEventListener("click", stop);
document.addEventListener("keydown", (e) => {
  if (e.key === " " || e.key === "Escape") {
    if (e.target.tagName === "INPUT" && e.key === " ") return;   // typing a value is not a stop
    e.preventDefault(); stop();
  }
});
$("engage").onclick = () => act("engage");
$("release").onclick = () => act("release");
$("enable").onclick = () => act("enable");
$("record").onclick = async () => {
  if (tl.status && tl.status.recording) {
    const j = await act("record-stop");
    if (j) say("recorded into " + j.summary.run_folder + " (rms " + (j.summary.rms_px ?? NaN).toFixed?.(1) + " px)");
  } else {
    const j = await act("record-start");
    if (j) say("recording into " + j.folder);
  }
};
$("path").onchange = () => act("target-path", { path: $("path").value });

// ------------------------------------------------------------------ tuning
let tuneFilled = false;
function fillTune(c, kinds, k) {
  const f = $("tune");
  if (!$("kind").options.length) for (const name of kinds) $("kind").add(new Option(name, name));
  for (const el of f.elements) {
    if (!el.name || document.activeElement === el) continue;
    const v = el.name.startsWith("knowledge.") ? (k || {})[el.name.slice(10)] : c[el.name];
    if (v !== undefined) el.value = v;
  }
  tuneFilled = true;
}
$("tune").addEventListener("submit", async (e) => {
  e.preventDefault();
  const body = {};
  for (const el of $("tune").elements) {
    if (!el.name) continue;
    body[el.name] = el.type === "number" ? Number(el.value) : el.value;
  }
  const j = await act("tune", body);
  if (j) { say("controller " + j.controller.kind + " applied"); fillTune(j.controller, [], null); }
});

// ------------------------------------------------------------------ view: frames, overlay, selection
let frameHead = null, frameBitmap = null;
function drawView() {
  if (!frameBitmap) return;
  const h = frameHead;
  if (view.width !== h.width) { view.width = h.width; view.height = h.height; }
  vctx.drawImage(frameBitmap, 0, 0);
  // image centre
  vctx.strokeStyle = "#00e5ff"; vctx.lineWidth = 1.5;
  vctx.beginPath(); vctx.moveTo(h.cx - 14, h.cy); vctx.lineTo(h.cx + 14, h.cy); vctx.moveTo(h.cx, h.cy - 14); vctx.lineTo(h.cx, h.cy + 14); vctx.stroke();
  const st = h.lost ? "lost" : (h.valid ? "tracking" : "missed");
  if (h.x !== null && h.y !== null) {
    const col = h.valid ? "#3f3" : "#fc3";
    vctx.strokeStyle = col; vctx.lineWidth = 2;
    const w = h.window / 2;
    vctx.strokeRect(h.x - w, h.y - w, 2 * w, 2 * w);
    vctx.beginPath(); vctx.arc(h.x, h.y, 5, 0, 2 * Math.PI); vctx.stroke();
    // error vector: from the image centre to the target
    vctx.strokeStyle = "#ff4dd2"; vctx.beginPath(); vctx.moveTo(h.cx, h.cy); vctx.lineTo(h.x, h.y); vctx.stroke();
  }
  vctx.fillStyle = "rgba(0,0,0,0.55)"; vctx.fillRect(0, 0, 300, 22);
  vctx.fillStyle = "#fff"; vctx.font = "13px monospace";
  const err = (h.x !== null && h.valid) ? Math.hypot(h.x - h.cx, h.y - h.cy).toFixed(1) + " px" : "-";
  vctx.fillText(`${st}  conf ${h.confidence.toFixed(2)}  error ${err}`, 6, 15);
  if (drag && drag.moved) {
    vctx.strokeStyle = drag.shift ? "#ff0" : "#fff"; vctx.setLineDash([5, 4]);
    if (drag.shift) { vctx.beginPath(); vctx.moveTo(drag.x0, drag.y0); vctx.lineTo(drag.x1, drag.y1); vctx.stroke(); }
    else vctx.strokeRect(Math.min(drag.x0, drag.x1), Math.min(drag.y0, drag.y1), Math.abs(drag.x1 - drag.x0), Math.abs(drag.y1 - drag.y0));
    vctx.setLineDash([]);
  }
}

function connectFrames() {
  const ws = new WebSocket(wsBase + "/ws/frames");
  ws.binaryType = "arraybuffer";
  ws.onmessage = async (ev) => {
    const buf = ev.data, n = new DataView(buf).getUint32(0);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const bmp = await createImageBitmap(new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" }));
    if (frameBitmap) frameBitmap.close();
    frameHead = head; frameBitmap = bmp;
    drawView();
    tl.frames += 1; tl.lastFrame = head;
    tl.latencies.push(Date.now() - head.wall_ms);   // frame tracked -> drawn on the canvas (ms)
    if (tl.latencies.length > 2000) tl.latencies.shift();
    ws.send("ack");
  };
  ws.onclose = () => setTimeout(connectFrames, 1000);
}

function imagePoint(e) {
  const r = view.getBoundingClientRect();
  return [(e.clientX - r.left) * view.width / r.width, (e.clientY - r.top) * view.height / r.height];
}
let drag = null;
view.addEventListener("mousedown", (e) => { const [x, y] = imagePoint(e); drag = { x0: x, y0: y, x1: x, y1: y, shift: e.shiftKey, moved: false }; });
view.addEventListener("mousemove", (e) => {
  if (!drag) return; const [x, y] = imagePoint(e); drag.x1 = x; drag.y1 = y;
  drag.moved = Math.hypot(x - drag.x0, y - drag.y0) > 4; drawView();
});
window.addEventListener("mouseup", (e) => {
  if (!drag) return; const d = drag; drag = null;
  if (!d.moved) { act("select", { x: d.x0, y: d.y0 }); return; }
  if (d.shift) { act("target-move", { dx: d.x1 - d.x0, dy: d.y1 - d.y0 }); return; }
  const w = Math.max(16, Math.min(512, Math.round(Math.max(Math.abs(d.x1 - d.x0), Math.abs(d.y1 - d.y0)))));
  act("select", { x: (d.x0 + d.x1) / 2, y: (d.y0 + d.y1) / 2, window: w });
});

// ------------------------------------------------------------------ plots
const series = { t: [], err_x: [], err_y: [], err: [], true_err: [], motor_x_deg: [], motor_y_deg: [], tip_x_deg: [], tip_y_deg: [] };
const sigSeries = {};   // name -> [[t, v], ...]
function plot(canvas, title, lines, unit) {
  const c = canvas.getContext("2d"), W = canvas.width, H = canvas.height, L = 46, R = 8, T = 16, B = 18;
  c.fillStyle = "#111"; c.fillRect(0, 0, W, H);
  const t = series.t; if (!t.length) return;
  const t1 = t[t.length - 1], t0 = t1 - HISTORY;
  let lo = Infinity, hi = -Infinity;
  for (const l of lines) for (const [tt, v] of l.pts) if (tt >= t0 && v !== null && isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (!isFinite(lo)) { lo = -1; hi = 1; }
  if (hi - lo < 1e-6) { hi += 1; lo -= 1; }
  const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
  const X = (tt) => L + (tt - t0) / HISTORY * (W - L - R), Y = (v) => T + (hi - v) / (hi - lo) * (H - T - B);
  c.strokeStyle = "#333"; c.fillStyle = "#999"; c.font = "10px monospace"; c.lineWidth = 1;
  for (let k = 0; k <= 4; k++) { const v = lo + k * (hi - lo) / 4; c.beginPath(); c.moveTo(L, Y(v)); c.lineTo(W - R, Y(v)); c.stroke(); c.fillText(v.toFixed(1), 2, Y(v) + 3); }
  for (let s = Math.ceil(t0); s <= t1; s += 5) { c.fillText(s.toFixed(0) + " s", X(s) - 8, H - 4); }
  c.fillStyle = "#ddd"; c.font = "11px sans-serif"; c.fillText(title + " (" + unit + ")", L, 11);
  let lx = L + 170;
  for (const l of lines) {
    c.strokeStyle = l.color; c.lineWidth = l.width || 1.2; c.beginPath(); let pen = false;
    for (const [tt, v] of l.pts) {
      if (tt < t0 || v === null || !isFinite(v)) { pen = false; continue; }
      if (pen) c.lineTo(X(tt), Y(v)); else { c.moveTo(X(tt), Y(v)); pen = true; }
    }
    c.stroke(); c.fillStyle = l.color; c.fillText(l.name, lx, 11); lx += 10 + c.measureText(l.name).width;
  }
}
const zip = (k) => series.t.map((tt, i) => [tt, series[k][i]]);
function drawPlots() {
  plot($("plot-err"), "tracking error", [
    { name: "x", color: "#4da6ff", pts: zip("err_x") }, { name: "y", color: "#ffa64d", pts: zip("err_y") },
    { name: "total", color: "#fff", width: 1.8, pts: zip("err") },
    ...(tl.status && tl.status.rig === "twin" ? [{ name: "true total", color: "#888", pts: zip("true_err") }] : [])], "px");
  plot($("plot-angles"), "angles", [
    { name: "motor x", color: "#4da6ff", pts: zip("motor_x_deg") }, { name: "motor y", color: "#ffa64d", pts: zip("motor_y_deg") },
    { name: "tip x", color: "#8f8", pts: zip("tip_x_deg") }, { name: "tip y", color: "#f8f", pts: zip("tip_y_deg") }], "deg");
  const cols = ["#4da6ff", "#ffa64d", "#8f8", "#f8f", "#ff6", "#6ff"];
  plot($("plot-signals"), "controller signals / estimates", Object.keys(sigSeries).map((k, i) => ({ name: k, color: cols[i % cols.length], pts: sigSeries[k] })), "");
}

// ------------------------------------------------------------------ state
function fmt(v, d = 1) { return v === null || v === undefined ? "-" : Number(v).toFixed(d); }
function showStatus(s) {
  tl.status = s;
  const lock = $("lockstate"); lock.textContent = s.locked ? "ENGAGED" : "released"; lock.className = "badge " + (s.locked ? "on" : "");
  const d = s.drives, ds = $("drivestate");
  ds.textContent = d.enabled ? "drives enabled" : "drives DISABLED: " + d.fault;
  ds.className = "badge " + (d.enabled ? "on" : "fault");
  $("engage").disabled = !d.enabled || s.locked; $("release").disabled = !s.locked; $("enable").disabled = d.enabled;
  $("record").textContent = s.recording ? "Stop recording" : "Start recording";
  for (const el of document.querySelectorAll(".twin-only")) el.style.display = s.rig === "twin" ? "" : "none";
  if (!$("path").options.length) for (const p of s.target_paths) $("path").add(new Option(p, p));
  if (s.target_path && document.activeElement !== $("path")) $("path").value = s.target_path;
  if (!tuneFilled) fillTune(s.controller, s.controllers, s.knowledge);
  const lp = tl.latencies.slice(-100).sort((a, b) => a - b);
  const tr = s.tracker, sel = s.selection, sm = $("selection");
  if (!sel) { sm.textContent = ""; sm.className = "selmsg"; }
  else if (!sel.ok) {
    sm.textContent = "selection failed: " + sel.failure + (sel.kept_previous ? " (still following the target selected before)" : "");
    sm.className = "selmsg fault";
  } else if (sel.warning) { sm.textContent = "target selected, but " + sel.warning; sm.className = "selmsg warn"; }
  else { sm.textContent = "target selected"; sm.className = "selmsg ok"; }
  $("status").textContent =
    `rig ${s.rig}  t ${fmt(s.time, 1)} s  ${s.running ? "loop running" : "LOOP STOPPED " + (s.error || "")}\n` +
    `drives: ${d.enabled ? "enabled" : "disabled"}  homed ${d.homed}  fault ${d.fault || "none"}  holding ${d.holding}\n` +
    `mocap: ${s.mocap ? (s.mocap.connected ? "connected " + fmt(s.mocap.rate_hz, 0) + " Hz" : "NOT connected") : "none (twin)"}\n` +
    `tracker: ${tr ? (tr.lost ? "lost" : tr.valid ? "tracking" : "missed") + " conf " + fmt(tr.confidence, 2) : "none"}\n` +
    `frames ${fmt(s.frame_rate, 1)} fps  video latency ${fmt(s.latency_ms, 0)} ms  to screen p50 ${lp.length ? fmt(lp[lp.length >> 1], 0) : "-"} ms\n` +
    `loop ${fmt(s.loop.rate_hz, 0)} Hz  lateness p50 ${fmt(s.loop.jitter_p50_ms, 2)} p99 ${fmt(s.loop.jitter_p99_ms, 2)} max ${fmt(s.loop.jitter_max_ms, 2)} ms  tick ${fmt(s.loop.tick_ms_p50, 2)} ms\n` +
    `controller ${s.controller.kind}  I ${s.controller.i_gain}  P ${s.controller.p_gain}  ` +
    `target ${fmt(100 * s.knowledge.nearest_depth, 1)}-${fmt(100 * s.knowledge.farthest_depth, 1)} cm away (assumed ${fmt(100 * s.knowledge.depth, 1)})` + (s.recording ? `\nRECORDING into ${s.recording}` : "");
  $("actions").innerHTML = "";
  for (const a of s.actions.slice().reverse()) { const li = document.createElement("li"); li.textContent = `${a.time.slice(11, 23)} ${a.action} ${a.who}`; $("actions").appendChild(li); }
}

let lastPlot = 0;
function connectState() {
  const ws = new WebSocket(wsBase + "/ws/state");
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    const ci = m.columns;
    for (const r of m.rows) ci.forEach((k, i) => series[k].push(r[i]));
    m.signals.forEach((sg, i) => {
      const tt = m.rows[i] ? m.rows[i][0] : null;
      for (const k of Object.keys(sg)) (sigSeries[k] = sigSeries[k] || []).push([tt, sg[k]]);
    });
    const t1 = series.t.length ? series.t[series.t.length - 1] : 0;
    let drop = 0; while (drop < series.t.length && series.t[drop] < t1 - HISTORY - 1) drop++;
    if (drop) for (const k of Object.keys(series)) series[k].splice(0, drop);
    for (const k of Object.keys(sigSeries)) { const a = sigSeries[k]; let j = 0; while (j < a.length && a[j][0] < t1 - HISTORY - 1) j++; if (j) a.splice(0, j); }
    showStatus(m.status);
    const now = performance.now();
    if (now - lastPlot > 190) { lastPlot = now; drawPlots(); }   // 5 Hz is plenty for the eye, and cheap
  };
  ws.onclose = () => setTimeout(connectState, 1000);
}
connectFrames();
connectState();
