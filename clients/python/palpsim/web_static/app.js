// The station page: live frames, view controls, palpation with mouse or touch, the
// force bar and trace, and timings. Talks only to its gateway (palpsim/web.py), which
// holds every key and token; nothing secret is here.
import { FrameSink } from "./frames.js";

const $ = (id) => document.getElementById(id);
const canvas = $("frame");

// what the page measured, for the status line, tests and the benchmark
const stats = {
  frames: 0, lastSeq: 0, firstShownAt: 0, lastShownAt: 0, fps: 0,
  inputLatencies: [], poseToFrame: [], recent: [], lastPick: null, force: 0, maxForce: 0, contact: false, errors: [],
  mode: "", hello: null,
};
window.palpsimStats = stats;

let ws = null;
let view = null;
let maxForceN = 10;
let depthGoal = 6;
let inputId = 0;
const inputSentAt = new Map();   // input id -> performance.now() when sent
const trace = [];                // recent force magnitudes (N)
let fpsCount = 0, fpsSince = performance.now();

function send(msg) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg));
}

function newInput() {
  inputId += 1;
  inputSentAt.set(inputId, performance.now());
  return inputId;
}

function showError(text) {
  stats.errors.push(text);
  const el = $("errors");
  el.textContent = stats.errors.slice(-5).join("\n");
}

function median(values) {
  if (!values.length) return NaN;
  const s = [...values].sort((a, b) => a - b);
  return s[Math.floor(s.length / 2)];
}

// -- frames ------------------------------------------------------------------------------
const sink = new FrameSink(canvas, (h, now) => {
  stats.frames += 1;
  stats.lastSeq = h.frame_seq;
  if (!stats.firstShownAt) stats.firstShownAt = now;
  stats.lastShownAt = now;
  stats.lastHeader = h;
  fpsCount += 1;
  if (now - fpsSince >= 1000) {
    stats.fps = (fpsCount * 1000) / (now - fpsSince);
    fpsCount = 0;
    fpsSince = now;
    $("fps").textContent = stats.fps.toFixed(1);
  }
  $("p2f").textContent = h.pose_to_frame_ms ? h.pose_to_frame_ms.toFixed(1) : "–";
  $("gp2f").textContent = h.gateway_pose_to_frame_ms != null ? h.gateway_pose_to_frame_ms.toFixed(1) : "–";
  // pose to frame shown, on this machine's wall clock (the gateway's pose time is one)
  if (h.pose_sent_unix_ms != null) {
    const ms = performance.timeOrigin + now - h.pose_sent_unix_ms;
    stats.poseToFrame.push(ms);
    if (stats.poseToFrame.length > 2000) stats.poseToFrame.shift();
    $("bp2f").textContent = median(stats.poseToFrame.slice(-30)).toFixed(1);
  }
  stats.recent.push([now, h.frame_seq, h.pose_seq, h.pose_to_frame_ms]);
  if (stats.recent.length > 2000) stats.recent.shift();
  // the first frame showing a pose sent after an input: input-to-frame latency
  for (const [id, t] of inputSentAt) {
    if (h.input >= id) {
      stats.inputLatencies.push(now - t);
      inputSentAt.delete(id);
    }
  }
  if (stats.inputLatencies.length) $("i2f").textContent = median(stats.inputLatencies.slice(-50)).toFixed(0);
  if (stats.mode === "watch") setContact(h.contact, null);
});

// -- state -------------------------------------------------------------------------------
function setContact(contact, depth) {
  stats.contact = contact;
  $("contact").textContent = contact ? "contact" : "no contact";
  if (depth != null) $("depth").textContent = depth.toFixed(1);
}

function onState(s) {
  const f = Math.hypot(...s.force_n);
  stats.force = f;
  stats.depth = s.depth_mm;
  stats.depthGoal = s.depth_goal_mm;
  stats.maxForce = Math.max(stats.maxForce, f);
  $("force").textContent = f.toFixed(2);
  $("forcefill").style.width = `${Math.min(100, (100 * f) / maxForceN)}%`;
  $("pps").textContent = s.poses_per_s.toFixed(0);
  setContact(s.contact, s.depth_mm);
  trace.push(f);
  if (trace.length > 150) trace.shift();  // 5 s at 30 Hz
  drawTrace();
}

function drawTrace() {
  const c = $("trace"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  g.strokeStyle = "#f08c2e";
  g.beginPath();
  trace.forEach((f, i) => {
    const x = (i / 149) * c.width, y = c.height - (Math.min(f, maxForceN) / maxForceN) * (c.height - 4) - 2;
    if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
  });
  g.stroke();
}

// -- controls ----------------------------------------------------------------------------
function setView(changes) { send({ type: "view", view: changes }); }

function showView(v) {
  view = v;
  $("azimuth").value = ((v.azimuth_deg + 540) % 360) - 180;
  $("elevation").value = v.elevation_deg;
  $("zoom").value = v.zoom;
  $("preset").value = v.preset;
  $("follow").checked = v.look_at_tip;
  ["cx", "cy", "cz"].forEach((id, i) => { $(id).value = v.center_mm[i]; });
}

function bindControls(hello) {
  ["cx", "cy", "cz"].forEach((id, i) => {
    $(id).min = Math.floor(hello.body_min_mm[i]);
    $(id).max = Math.ceil(hello.body_max_mm[i]);
  });
  showView(hello.view);
  $("azimuth").addEventListener("change", (e) => setView({ azimuth_deg: Number(e.target.value) }));
  $("elevation").addEventListener("change", (e) => setView({ elevation_deg: Number(e.target.value) }));
  $("zoom").addEventListener("change", (e) => setView({ zoom: Number(e.target.value) }));
  $("preset").addEventListener("change", (e) => setView({ preset: e.target.value }));
  $("follow").addEventListener("change", (e) => setView({ look_at_tip: e.target.checked }));
  for (const id of ["cx", "cy", "cz"]) {
    $(id).addEventListener("change", () =>
      setView({ look_at_tip: false, center_mm: ["cx", "cy", "cz"].map((k) => Number($(k).value)) }));
  }
  $("depthgoal").addEventListener("input", (e) => setDepth(Number(e.target.value)));
  $("lift").addEventListener("click", () => send({ type: "lift", input: newInput() }));
  document.addEventListener("keydown", (e) => {
    if (!view || e.target.tagName === "INPUT") return;
    const step = { ArrowLeft: [-10, 0], ArrowRight: [10, 0], ArrowUp: [0, 5], ArrowDown: [0, -5] }[e.key];
    if (!step) return;
    setView({ azimuth_deg: view.azimuth_deg + step[0],
              elevation_deg: Math.max(-89, Math.min(89, view.elevation_deg + step[1])) });
  });
}

function setDepth(d) {
  const [lo, hi] = stats.hello.depth_range_mm;
  depthGoal = Math.max(lo, Math.min(hi, d));
  $("depthgoal").value = depthGoal;
  $("depthgoalv").textContent = depthGoal.toFixed(1);
  send({ type: "depth", depth_mm: depthGoal, input: newInput() });
}

// -- palpation: a click picks the skin point, the wheel or a vertical drag sets the depth --
function framePixel(e) {
  const r = canvas.getBoundingClientRect();
  return { x: ((e.clientX - r.left) * canvas.width) / r.width, y: ((e.clientY - r.top) * canvas.height) / r.height };
}

let drag = null;
canvas.addEventListener("pointerdown", (e) => {
  drag = { x: e.clientX, y: e.clientY, depth: depthGoal, moved: false };
  canvas.setPointerCapture(e.pointerId);
});
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const dy = e.clientY - drag.y;
  if (Math.abs(dy) > 4 || Math.abs(e.clientX - drag.x) > 4) drag.moved = true;
  if (drag.moved && stats.lastPick) setDepth(drag.depth + dy * 0.1);  // 0.1 mm per pixel, down pushes in
});
canvas.addEventListener("pointerup", (e) => {
  if (drag && !drag.moved && stats.mode === "palpate") {
    const p = framePixel(e);
    send({ type: "pick", x: p.x, y: p.y, input: newInput() });
  }
  drag = null;
});
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  if (stats.mode === "palpate" && stats.lastPick) setDepth(depthGoal + Math.sign(e.deltaY));  // down: 1 mm deeper a notch
}, { passive: false });

// -- connection --------------------------------------------------------------------------
function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  ws = new WebSocket(`${scheme}://${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  ws.onmessage = (e) => {
    if (typeof e.data !== "string") { sink.push(e.data); return; }
    const m = JSON.parse(e.data);
    if (m.type === "hello") {
      stats.hello = m;
      stats.mode = m.mode;
      maxForceN = m.max_force_n;
      depthGoal = m.depth_mm;
      $("status").textContent = `${m.mode === "watch" ? "watching" : "palpating"} session ${m.session}`;
      bindControls(m);
    } else if (m.type === "state") onState(m);
    else if (m.type === "view") showView(m.view);
    else if (m.type === "pick") {
      if (!m.hit) showError("that pixel shows no body: click on the patient");
      else stats.lastPick = m;
    } else if (m.type === "error") showError(m.message);
  };
  ws.onclose = (e) => {
    $("status").textContent = `disconnected${e.reason ? ": " + e.reason : ""} (code ${e.code}); reload to reconnect`;
  };
}
connect();

// for scripts that drive the page (the browser test, bench/web_bench.py)
window.palpsim = {
  setDepth,
  pick: (x, y) => send({ type: "pick", x, y, input: newInput() }),
};
