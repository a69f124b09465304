// livescene view: an orbit / fly camera over a trained run, a slider per object, rendered by the server.
// One render request in flight at a time; the newest wanted view replaces an unsent one, so a drag never queues
// up stale frames. A low-resolution image follows every change, a sharp one comes once things rest.
"use strict";

const TOKEN = new URLSearchParams(location.search).get("token") || "";
const REST_MS = 250; // no change for this long -> ask for the sharp image
const FRAME_MS = 200; // while moving, shrink the low image below its size until a render fits this (5 frames/s)
const MIN_SIDE = 40; // ... but never below this many pixels on the longer side
const $ = (id) => document.getElementById(id);

const S = {
  info: null, states: {}, layer: "rgb",
  cam: { R: null, p: null, t: null, fov: 50 }, // R: columns right, up, back (OpenGL); p: position; t: orbit target
  version: 0, seq: 0, inflight: false, want: null, timer: null,
  shown: { version: -1, sharp: false }, frames: 0, lowFrames: 0, times: [],
  msPerPixel: 0, // running estimate of the server's render time per pixel
};

// ------------------------------------------------------------------------------------------------ small 3D maths
const add = (a, b) => a.map((x, i) => x + b[i]);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const mul = (a, s) => a.map((x) => x * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => mul(a, 1 / (norm(a) || 1));
const col = (R, j) => [R[0][j], R[1][j], R[2][j]];
function rotation(axis, angle) { // Rodrigues: 3x3 rotation about a unit axis
  const [x, y, z] = unit(axis), c = Math.cos(angle), s = Math.sin(angle), C = 1 - c;
  return [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
          [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
          [z * x * C - y * s, z * y * C + x * s, c + z * z * C]];
}
const apply = (M, v) => [dot(M[0], v), dot(M[1], v), dot(M[2], v)];
const matmul = (A, B) => A.map((row) => [0, 1, 2].map((j) => dot(row, col(B, j))));
function orthonormal(R) { // re-orthonormalise after many small rotations (Gram-Schmidt on right, up)
  const r = unit(col(R, 0)), u0 = col(R, 1), u = unit(sub(u0, mul(r, dot(u0, r))));
  const b = [r[1] * u[2] - r[2] * u[1], r[2] * u[0] - r[0] * u[2], r[0] * u[1] - r[1] * u[0]];
  return [0, 1, 2].map((i) => [r[i], u[i], b[i]]);
}

function c2w() { // row-major 16 numbers, as transforms.json
  const { R, p } = S.cam;
  return [R[0][0], R[0][1], R[0][2], p[0], R[1][0], R[1][1], R[1][2], p[1], R[2][0], R[2][1], R[2][2], p[2], 0, 0, 0, 1];
}

function setCamera(m, fov) { // from a row-major 4x4; the orbit target is ahead, at the scene centre's depth
  const R = [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]], p = [m[3], m[7], m[11]];
  const fwd = mul(col(R, 2), -1), info = S.info;
  const depth = Math.max(dot(sub(info.target, p), fwd), 0.2 * info.extent);
  S.cam = { R: orthonormal(R), p, t: add(p, mul(fwd, depth)), fov };
}

function orbit(dx, dy) {
  const { R, p, t } = S.cam, up = S.info.up;
  const Q = matmul(rotation(up, -dx * 0.006), rotation(col(R, 0), -dy * 0.006));
  S.cam.p = add(t, apply(Q, sub(p, t)));
  S.cam.R = orthonormal(matmul(Q, R));
}

function look(dx, dy) { // turn in place (the target turns with the camera)
  const { R, p, t } = S.cam;
  const Q = matmul(rotation(S.info.up, -dx), rotation(col(R, 0), -dy));
  S.cam.t = add(p, apply(Q, sub(t, p)));
  S.cam.R = orthonormal(matmul(Q, R));
}

function pan(dx, dy) {
  const { R, p, t, fov } = S.cam, c = $("view");
  const shown = Math.min(c.clientHeight, (c.clientWidth * c.height) / c.width) || 1; // object-fit: contain
  const k = (norm(sub(t, p)) * 2 * Math.tan((fov * Math.PI) / 360)) / shown;
  const move = add(mul(col(R, 0), -dx * k), mul(col(R, 1), dy * k));
  S.cam.p = add(p, move); S.cam.t = add(t, move);
}

function zoom(delta) {
  const { p, t } = S.cam;
  const d = norm(sub(p, t)), nd = Math.max(d * Math.exp(delta * 0.0015), 0.01 * S.info.extent);
  S.cam.p = add(t, mul(sub(p, t), nd / (d || 1)));
}

function fly(move) { // move = [right, up, forward] in scene units
  const { R } = S.cam;
  const v = add(add(mul(col(R, 0), move[0]), mul(S.info.up, move[1])), mul(col(R, 2), -move[2]));
  S.cam.p = add(S.cam.p, v); S.cam.t = add(S.cam.t, v);
}

// ------------------------------------------------------------------------------------------------------ requests
async function api(path, body) {
  const opts = body === undefined ? { headers: { "X-Livescene-Token": TOKEN } }
    : { method: "POST", headers: { "X-Livescene-Token": TOKEN, "Content-Type": "application/json" }, body: JSON.stringify(body) };
  const r = await fetch(path, opts);
  if (!r.ok && r.status !== 204) {
    let text = await r.text();
    try { text = JSON.parse(text).error || text; } catch (e) { /* plain text */ }
    throw new Error(text);
  }
  return r;
}

function lowSize() { // the low size, shrunk (same aspect) when the renderer is too slow for FRAME_MS at it
  const [w, h] = S.info.sizes.low;
  if (!S.msPerPixel) return [w, h];
  const scale = Math.min(1, Math.sqrt(FRAME_MS / (S.msPerPixel * w * h)));
  const side = Math.max(MIN_SIDE, Math.round(Math.max(w, h) * scale));
  return w >= h ? [side, Math.max(8, Math.round((side * h) / w))] : [Math.max(8, Math.round((side * w) / h)), side];
}

function view(kind) {
  const [w, h] = kind === "low" ? lowSize() : S.info.sizes[kind];
  return { camera: { c2w: c2w(), w, h, fov_y: S.cam.fov }, states: { ...S.states }, layer: S.layer };
}

function changed() {
  S.version += 1;
  document.body.dataset.sharp = "0";
  want("low");
  clearTimeout(S.timer);
  S.timer = setTimeout(() => want("sharp"), REST_MS);
}

function want(kind) {
  S.want = { kind, version: S.version, body: view(kind) };
  pump();
}

async function pump() {
  if (S.inflight || !S.want) return;
  const job = S.want;
  S.want = null;
  S.inflight = true;
  const t0 = performance.now();
  try {
    const r = await api("/api/render", { ...job.body, seq: ++S.seq });
    if (r.status === 200) await show(job, r, performance.now() - t0);
  } catch (e) {
    message(e.message, "error");
  } finally {
    S.inflight = false;
    pump();
  }
}

async function show(job, r, ms) {
  const bitmap = await createImageBitmap(await r.blob());
  const sharp = job.kind === "sharp";
  if (job.version < S.shown.version || (job.version === S.shown.version && S.shown.sharp && !sharp)) return;
  const c = $("view");
  if (c.width !== bitmap.width || c.height !== bitmap.height) { c.width = bitmap.width; c.height = bitmap.height; }
  c.getContext("2d").drawImage(bitmap, 0, 0);
  S.shown = { version: job.version, sharp };
  S.frames += 1;
  if (!sharp) S.lowFrames += 1;
  const now = performance.now();
  S.times = S.times.filter((x) => now - x < 1000).concat([now]);
  const perPixel = +r.headers.get("X-Render-Ms") / (bitmap.width * bitmap.height);
  S.msPerPixel = S.msPerPixel ? 0.5 * S.msPerPixel + 0.5 * perPixel : perPixel;
  const unseen = JSON.parse(r.headers.get("X-Unseen") || "{}");
  $("unseen").textContent = Object.entries(unseen).map(([n, v]) =>
    `${n} at ${S.states[n].toFixed(2)}: no training view near this camera showed it there (they show ${v.toFixed(2)}); it may look blurred`).join(" · ");
  $("timing").textContent = `${bitmap.width}x${bitmap.height} · render ${r.headers.get("X-Render-Ms")} ms · ` +
    `round trip ${ms.toFixed(0)} ms · ${S.times.length} frames/s`;
  $("status").textContent = sharp ? "sharp" : "moving";
  const b = document.body.dataset;
  b.frames = S.frames; b.lowFrames = S.lowFrames; b.shownVersion = job.version; b.version = S.version;
  b.sharp = sharp && job.version === S.version ? "1" : "0";
  b.renderMs = r.headers.get("X-Render-Ms");
  b.ready = "1";
}

function message(text, kind) {
  const m = $("message");
  m.textContent = text; m.dataset.kind = kind || "";
}

// ------------------------------------------------------------------------------------------------------- controls
function buildObjects() {
  const box = $("objects"), sel = $("sweep-object");
  box.textContent = ""; sel.textContent = "";
  S.info.objects.forEach((name, i) => {
    const row = document.createElement("div"), label = document.createElement("label");
    const input = document.createElement("input"), value = document.createElement("span");
    row.className = "object";
    label.textContent = name; label.htmlFor = `state-${i}`;
    input.type = "range"; input.min = "0"; input.max = "1"; input.step = "0.01"; input.id = `state-${i}`;
    input.dataset.name = name;
    value.className = "value";
    input.addEventListener("input", () => { S.states[name] = +input.value; value.textContent = (+input.value).toFixed(2); changed(); });
    row.append(label, input, value);
    box.append(row);
    const opt = document.createElement("option");
    opt.value = name; opt.textContent = name;
    sel.append(opt);
  });
}

function setStates(states) {
  for (const [name, v] of Object.entries(states)) {
    if (!(name in S.states)) continue;
    S.states[name] = v;
    const input = document.querySelector(`input[data-name="${CSS.escape(name)}"]`);
    input.value = String(v);
    input.nextElementSibling.textContent = (+v).toFixed(2);
  }
}

function buildCameras() {
  const sel = $("cameras");
  S.info.cameras.forEach((c) => {
    const opt = document.createElement("option");
    opt.value = String(c.index);
    opt.textContent = `${c.name}${c.held_out ? "  (held out)" : ""}`;
    sel.append(opt);
  });
  sel.addEventListener("change", () => jump(+sel.value));
  $("frame-states").addEventListener("click", () => { setStates(S.info.cameras[+sel.value || 0].states); changed(); });
}

function jump(i) {
  const c = S.info.cameras[i];
  setCamera(c.c2w, c.fov_y);
  $("cameras").value = String(i);
  changed();
}

function bindCanvas() {
  const c = $("view");
  let drag = null;
  c.addEventListener("contextmenu", (e) => e.preventDefault());
  c.addEventListener("pointerdown", (e) => {
    c.focus();
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    c.setPointerCapture(e.pointerId); c.classList.add("dragging");
  });
  c.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) pan(dx, dy); else orbit(dx, dy);
    changed();
  });
  const end = () => { drag = null; c.classList.remove("dragging"); };
  c.addEventListener("pointerup", end);
  c.addEventListener("pointercancel", end);
  c.addEventListener("wheel", (e) => { e.preventDefault(); zoom(e.deltaY); changed(); }, { passive: false });
}

function bindKeys() { // held keys fly the camera at a speed scaled to the scene, once per animation frame
  const held = new Set();
  let fast = false;
  const typing = (e) => ["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName) && e.target.type !== "range";
  window.addEventListener("keydown", (e) => {
    fast = e.shiftKey;
    if (typing(e) || e.ctrlKey || e.metaKey || e.altKey) return;
    const k = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (!"wasdqe".includes(k) && !k.startsWith("Arrow")) return;
    if (e.target.type === "range" && k.startsWith("Arrow")) return; // arrows move a focused slider
    e.preventDefault();
    if (!held.size) requestAnimationFrame(step);
    held.add(k);
  });
  window.addEventListener("keyup", (e) => { fast = e.shiftKey; held.delete(e.key.length === 1 ? e.key.toLowerCase() : e.key); });
  window.addEventListener("blur", () => held.clear());
  let last = null;
  function step(now) {
    if (!held.size) { last = null; return; }
    const dt = last === null ? 1 / 60 : Math.min((now - last) / 1000, 0.1);
    last = now;
    const speed = 0.4 * S.info.extent * dt * (fast ? 3 : 1);
    const h = (k) => (held.has(k) ? 1 : 0);
    const move = [h("d") - h("a"), h("e") - h("q"), h("w") - h("s")];
    if (move.some((x) => x)) fly(mul(move, speed));
    const turn = [h("ArrowLeft") - h("ArrowRight"), h("ArrowUp") - h("ArrowDown")];
    if (turn.some((x) => x)) look(-turn[0] * 1.2 * dt, -turn[1] * 1.2 * dt);
    changed();
    requestAnimationFrame(step);
  }
}

function bindActions() {
  $("layer").addEventListener("change", () => { S.layer = $("layer").value; changed(); });
  $("command-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const text = $("command").value;
    try {
      const out = await (await api("/api/command", { text })).json();
      setStates(out.states);
      message(`${out.verb}: ${Object.entries(out.states).map(([n, v]) => `${n} = ${v}`).join(", ")}`, "ok");
      changed();
    } catch (err) { message(err.message, "error"); }
  });
  $("save").addEventListener("click", async () => {
    $("save").disabled = true;
    message("saving…");
    try {
      const out = await (await api("/api/save", view("save"))).json();
      message(`saved ${out.png} (camera file ${out.json})`, "ok");
    } catch (err) { message(err.message, "error"); }
    $("save").disabled = false;
  });
  $("sweep").addEventListener("click", async () => {
    try {
      const body = { ...view("sharp"), object: $("sweep-object").value, count: +$("sweep-count").value };
      await api("/api/sweep", body);
      pollSweep();
    } catch (err) { message(err.message, "error"); }
  });
}

async function pollSweep() {
  const s = await (await api("/api/sweep")).json();
  const el = $("sweep-status");
  el.dataset.state = s.state;
  if (s.state === "running") {
    $("sweep").disabled = true;
    el.textContent = `rendering ${s.done} / ${s.total} -> ${s.path}`;
    setTimeout(pollSweep, 500);
    return;
  }
  $("sweep").disabled = false;
  el.textContent = s.state === "idle" ? "" : `${s.message}${s.warnings.length ? " · " + s.warnings.join(" · ") : ""}`;
}

async function start() {
  if (!TOKEN) { message("open the URL that `livescene view` printed (it carries the token)", "error"); return; }
  try {
    S.info = await (await api("/api/info")).json();
  } catch (err) { message(err.message, "error"); return; }
  const first = S.info.cameras[S.info.start];
  S.states = { ...first.states };
  buildObjects(); setStates(S.states); buildCameras(); bindCanvas(); bindKeys(); bindActions();
  jump(S.info.start);
  pollSweep();
}

window.viewer = { state: S, view, jump, setStates, changed };
start();
