// interreal annotate: the page. Plain JS, no build step, no network access beyond this server.
// Every edit is sent at once with the version of what it was based on; the server merges or answers 409.
"use strict";

const PALETTE = ["#42d4f4", "#f58231", "#3cb44b", "#f032e6", "#4363d8", "#e6194b", "#911eb4", "#bfef45",
  "#fabed4", "#469990", "#dcbeff", "#9a6324", "#fffac8", "#800000", "#aaffc3", "#808000", "#ffd8b1", "#000075"];
const params = new URLSearchParams(location.search);
const TOKEN = params.get("token") || "";
const POLL_MS = parseInt(params.get("poll") || "4000", 10);  // picks up other tabs' edits; 0 = off

const S = {
  frames: [], objects: [], labels: {}, labelme: [], labelsVersion: "0", mappingVersion: "0", keyframes: [], kfStamps: {},
  masks: [], suggested: [], prompts: {},
  cur: 0, obj: 0, tool: "polygon", mode: "paint",
  kf: null,          // {fid, versions, index: Uint8Array | null}
  mask: null,        // {fid, index: Uint8Array} propagated mask of the current frame
  w: 0, h: 0, pts: [], drag: null, sliding: false, loadSeq: 0, polling: null,
  clicks: null,      // the click tool's session: {fid, obj, list: [[x, y, positive], ...]}; the server is stateless
};
const $ = (id) => document.getElementById(id);
// the ignore class (people, hands: value 254 in a keyframe PNG, the transient layer once propagated) is grey
const IGNORE_VALUE = 254, IGNORE_OBJ = { id: -1, name: null };
const IGNORE_COLOR = "#9e9e9e";
const color = (oid) => (oid < 0 ? IGNORE_COLOR : PALETTE[oid % PALETTE.length]);
const selected = () => (S.obj === -1 ? IGNORE_OBJ : S.objects[S.obj]);
const cur = () => S.frames[S.cur];

// ------------------------------------------------------------------------------------------------ server calls
class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

async function api(path, body) {
  const opts = { headers: { "X-Interreal-Token": TOKEN }, credentials: "same-origin", cache: "no-store" };
  if (body !== undefined) {
    opts.method = "POST";
    opts.headers["Content-Type"] = "application/json";
    opts.body = JSON.stringify(body);
  }
  const sep = path.includes("?") ? "&" : "?";
  const res = await fetch(path + sep + "token=" + encodeURIComponent(TOKEN), opts);
  let data = null;
  try { data = await res.json(); } catch (e) { data = null; }
  if (!res.ok) {
    let msg = (data && (data.error || data.detail)) || res.statusText;
    if (typeof msg !== "string") msg = JSON.stringify(msg);
    throw new ApiError(res.status, msg);
  }
  return data;
}

function setSave(state, text) {
  const el = $("save-status");
  el.dataset.state = state;
  el.textContent = text;
}

let toastTimer = null;
function toast(msg, kind) {
  const el = $("toast");
  el.textContent = msg;
  el.className = "toast" + (kind === "info" ? " info" : "");
  el.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { el.hidden = true; }, kind === "info" ? 3000 : 9000);
}

// Runs an edit; shows saving / saved / the refusal message. A 409 reloads what changed so the user sees it.
// Edits of one tab run one after another, so each is based on what the previous one saved.
let queue = Promise.resolve();
function edit(what, fn) {
  const run = async () => {
    setSave("saving", "saving…");
    try {
      const out = await fn();
      setSave("saved", "saved ✓ " + new Date().toLocaleTimeString());
      document.body.dataset.saves = String((+document.body.dataset.saves || 0) + 1);  // a counter tests wait on
      return out;
    } catch (e) {
      setSave("error", "not saved");
      if (e.status === 409) {
        toast("Not saved — " + e.message);
        await refreshState(true).catch(() => {});
      } else {
        toast(what + " failed: " + e.message);
      }
      return null;
    }
  };
  const p = queue.then(run);
  queue = p.catch(() => null);
  return p;
}

// ------------------------------------------------------------------------------------------------ state
function applyState(st) {
  S.frames = st.frames;
  S.objects = st.objects;
  S.labels = st.labels;
  S.labelsVersion = st.labels_version;
  setBadLabels(st.bad_labels);
  S.mappingVersion = st.mapping_version;
  S.keyframes = st.keyframes;
  S.kfStamps = st.keyframe_stamps || {};
  S.labelme = st.labelme || [];
  S.masks = st.masks;
  S.suggested = st.suggested;
  S.prompts = st.prompts || {};
  if (S.obj >= S.objects.length) S.obj = Math.max(0, S.objects.length - 1);
  $("frame-slider").max = Math.max(0, S.frames.length - 1);
  renderObjects();
  renderLists();
  renderThumbMarks();
  showPropagation(st.propagation);
}

async function refreshState(reloadFrame) {
  const before = JSON.stringify([S.kfStamps[cur() && cur().fid], S.masks.includes(cur() && cur().fid)]);
  const st = await api("/api/state");
  const thumbsChanged = st.frames.length !== S.frames.length;
  applyState(st);
  if (thumbsChanged) buildThumbs();
  const after = JSON.stringify([S.kfStamps[cur() && cur().fid], S.masks.includes(cur() && cur().fid)]);
  if ((reloadFrame || before !== after) && !S.pts.length && !S.drag) await loadOverlays();
}

// ------------------------------------------------------------------------------------------------ frames
function frameFromHash() {
  const m = /f=(\d+)/.exec(location.hash);
  if (!m) return 0;
  const i = S.frames.findIndex((f) => f.fid === m[1]);
  return i < 0 ? 0 : i;
}

async function goto(i) {
  if (!S.frames.length) return;
  i = Math.max(0, Math.min(S.frames.length - 1, i));
  S.cur = i;
  S.pts = []; S.drag = null; S.clicks = null;
  const f = cur();
  history.replaceState(null, "", location.pathname + location.search + "#f=" + f.fid);
  $("frame-slider").value = i;
  $("frame-title").textContent = f.key;
  $("state-frame").textContent = f.key;
  $("frame-counter").textContent = `${i + 1} / ${S.frames.length}  (frame ${f.index})`;
  document.querySelectorAll(".thumb.current").forEach((t) => t.classList.remove("current"));
  const th = document.querySelector(`.thumb[data-fid="${f.fid}"]`);
  if (th) { th.classList.add("current"); th.scrollIntoView({ block: "nearest", inline: "nearest" }); }
  renderObjects();
  renderLists();
  await loadFrame();
}

function loadImage(src) {
  return new Promise((resolve, reject) => {
    const im = new Image();
    im.onload = () => resolve(im);
    im.onerror = () => reject(new Error("could not load " + src));
    im.src = src;
  });
}

async function decodeIndex(src, w, h) {
  const im = await loadImage(src);
  const c = document.createElement("canvas");
  c.width = w; c.height = h;
  const ctx = c.getContext("2d", { willReadFrequently: true });
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(im, 0, 0, w, h);
  const px = ctx.getImageData(0, 0, w, h).data;
  const out = new Uint8Array(w * h);
  for (let i = 0; i < out.length; i++) out[i] = px[i * 4];
  return out;
}

async function loadFrame() {
  const seq = ++S.loadSeq;
  const f = cur();
  const im = await loadImage(`/api/image/${f.fid}?token=${encodeURIComponent(TOKEN)}`);
  if (seq !== S.loadSeq) return;
  S.w = im.naturalWidth; S.h = im.naturalHeight;
  for (const id of ["img-canvas", "overlay-canvas", "draw-canvas"]) {
    const c = $(id); c.width = S.w; c.height = S.h;
  }
  fitStage();
  $("img-canvas").getContext("2d").drawImage(im, 0, 0);
  await loadOverlays();
}

async function loadOverlays() {
  const seq = S.loadSeq;
  const f = cur();
  const kf = await api(`/api/keyframe/${f.fid}`);
  let mask = null;
  if (S.masks.includes(f.fid)) {
    try { mask = await decodeIndex(`/api/mask/${f.fid}?token=${encodeURIComponent(TOKEN)}&v=${Date.now()}`, S.w, S.h); }
    catch (e) { mask = null; }
  }
  const index = kf.png ? await decodeIndex(kf.png, S.w, S.h) : null;
  if (seq !== S.loadSeq) return;
  S.kf = { fid: f.fid, versions: kf.versions, index, readOnly: !!kf.read_only };
  S.mask = mask ? { fid: f.fid, index: mask } : null;
  renderOverlay();
  renderDraw();
}

function fitStage() {
  const wrap = document.querySelector(".stage-wrap");
  const scale = Math.min((wrap.clientWidth - 4) / S.w, (wrap.clientHeight - 4) / S.h);
  const stage = $("stage");
  stage.style.width = Math.max(1, Math.floor(S.w * scale)) + "px";
  stage.style.height = Math.max(1, Math.floor(S.h * scale)) + "px";
}

// ------------------------------------------------------------------------------------------------ overlay
function hexRgb(hex) {
  const n = parseInt(hex.slice(1), 16);
  return [(n >> 16) & 255, (n >> 8) & 255, n & 255];
}

function renderOverlay() {
  const c = $("overlay-canvas");
  const ctx = c.getContext("2d");
  const img = ctx.createImageData(S.w, S.h);
  const px = img.data;
  const alpha = Math.round(255 * parseFloat($("opacity").value));
  const rgb = S.objects.map((o) => hexRgb(color(o.id)));
  rgb[IGNORE_VALUE - 1] = hexRgb(IGNORE_COLOR);
  const kf = $("show-keyframe").checked && S.kf ? S.kf.index : null;
  const mk = $("show-masks").checked && S.mask ? S.mask.index : null;
  const w = S.w, h = S.h;
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const i = y * w + x;
      let v = 0, a = 0;
      if (kf && kf[i] > 0 && kf[i] !== 255) {
        v = kf[i];
        const edge = (x > 0 && kf[i - 1] !== v) || (x < w - 1 && kf[i + 1] !== v) ||
          (y > 0 && kf[i - w] !== v) || (y < h - 1 && kf[i + w] !== v);
        a = edge ? 255 : alpha;
      } else if (mk && mk[i] > 0) {
        v = mk[i];  // propagated: lighter fill, dotted outline
        const edge = (x > 0 && mk[i - 1] !== v) || (x < w - 1 && mk[i + 1] !== v) ||
          (y > 0 && mk[i - w] !== v) || (y < h - 1 && mk[i + w] !== v);
        a = edge ? (((x + y) >> 1) & 1 ? 230 : 0) : Math.round(alpha * 0.75);
      }
      if (v && rgb[v - 1]) {
        const o = i * 4, c3 = rgb[v - 1];
        px[o] = c3[0]; px[o + 1] = c3[1]; px[o + 2] = c3[2]; px[o + 3] = a;
      }
    }
  }
  ctx.putImageData(img, 0, 0);
}

function renderDraw(mouse) {
  const c = $("draw-canvas");
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  const o = selected();
  const col = S.mode === "erase" ? "#ffffff" : (o ? color(o.id) : "#ffffff");
  const lw = Math.max(1.5, S.w / 400);
  ctx.lineWidth = lw;
  ctx.strokeStyle = col;
  ctx.fillStyle = col + "44";
  if (S.mode === "erase") ctx.setLineDash([6 * lw, 4 * lw]);
  if (S.tool === "polygon" && S.pts.length) {
    ctx.beginPath();
    ctx.moveTo(S.pts[0][0], S.pts[0][1]);
    for (const p of S.pts.slice(1)) ctx.lineTo(p[0], p[1]);
    if (mouse) ctx.lineTo(mouse[0], mouse[1]);
    ctx.stroke();
    for (const p of S.pts) { ctx.fillStyle = col; ctx.fillRect(p[0] - 2 * lw, p[1] - 2 * lw, 4 * lw, 4 * lw); }
  }
  if (S.tool === "click" && sessionClicks().length) {
    ctx.setLineDash([]);
    for (const [x, y, positive] of sessionClicks()) {
      ctx.beginPath();
      ctx.arc(x, y, 4 * lw, 0, 2 * Math.PI);
      ctx.fillStyle = positive ? "#35c46a" : "#ff5a5a";
      ctx.fill();
      ctx.strokeStyle = "#ffffff";
      ctx.stroke();
    }
  }
  if (S.tool === "box" && S.drag) {
    const [x0, y0] = S.drag.from, [x1, y1] = S.drag.to;
    ctx.fillRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0));
    ctx.strokeRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0));
  }
}

// ------------------------------------------------------------------------------------------------ drawing
function imagePoint(ev) {
  const c = $("draw-canvas");
  const r = c.getBoundingClientRect();
  const x = (ev.clientX - r.left) * (S.w / r.width);
  const y = (ev.clientY - r.top) * (S.h / r.height);
  return [Math.max(0, Math.min(S.w, x)), Math.max(0, Math.min(S.h, y))];
}

function screenDist(a, b) {
  const r = $("draw-canvas").getBoundingClientRect();
  const s = r.width / S.w;
  return Math.hypot((a[0] - b[0]) * s, (a[1] - b[1]) * s);
}

async function submitShape(shape, points) {
  const o = selected();
  if (!o) { toast("Add an object first (right panel), then draw its mask."); return; }
  const f = cur();
  const body = { object: o.id, name: o.name, shape, points, mode: S.mode };
  const res = await edit("saving the mask", async () => {
    const mine = S.kf && S.kf.fid === f.fid;
    const r = await api(`/api/keyframe/${f.fid}`, { ...body, versions: mine ? S.kf.versions : {} });
    if (mine) S.kf.versions = r.versions;  // at once: the next queued stroke is based on this one
    return r;
  });
  await showKeyframe(f, res);
}

// The keyframe as an edit answered it (the answer of a frame left meanwhile is not shown)
async function showKeyframe(f, res) {
  if (!res || cur().fid !== f.fid) return;
  S.kf = { fid: f.fid, versions: res.versions, index: res.png ? await decodeIndex(res.png, S.w, S.h) : null };
  S.keyframes = res.keyframes;
  renderOverlay();
  renderLists();
  renderThumbMarks();
}

// ------------------------------------------------------------------------------------------------ click tool
// Left click: on the object; shift+click or right click: not the object. Each click sends the whole session
// (this frame, this object) and the server answers the object's new mask on the keyframe.
function sessionClicks() {
  const o = selected(), f = cur();
  if (!S.clicks || !o || !f || S.clicks.fid !== f.fid || S.clicks.obj !== o.id) return [];
  return S.clicks.list;
}

async function addClick(p, positive) {
  const o = selected();
  if (!o) { toast("Add an object first (right panel), then click on it."); return; }
  const f = cur();
  if (!sessionClicks().length) S.clicks = { fid: f.fid, obj: o.id, list: [] };
  const list = S.clicks.list;
  const click = [Math.min(p[0], S.w - 0.5), Math.min(p[1], S.h - 0.5), positive];
  list.push(click);
  const clicks = list.slice();
  renderDraw();
  const res = await edit("segmenting from the clicks", async () => {
    const mine = S.kf && S.kf.fid === f.fid;
    const r = await api(`/api/keyframe/${f.fid}/click`, { object: o.id, name: o.name, clicks, versions: mine ? S.kf.versions : {} });
    if (mine) S.kf.versions = r.versions;
    return r;
  });
  if (!res && list.includes(click)) { list.splice(list.indexOf(click), 1); renderDraw(); return; }
  await showKeyframe(f, res);
}

async function undoStroke() {
  const f = cur();
  if (S.pts.length) { S.pts.pop(); renderDraw(); return; }  // first take back polygon corners
  const res = await edit("undo", async () => {
    const r = await api(`/api/keyframe/${f.fid}/undo`, { versions: S.kf && S.kf.fid === f.fid ? S.kf.versions : {} });
    if (S.kf && S.kf.fid === f.fid) S.kf.versions = r.versions;
    return r;
  });
  if (res && S.tool === "click") { sessionClicks().pop(); renderDraw(); }  // the click that stroke answered
  await showKeyframe(f, res);
}

function closePolygon() {
  const pts = S.pts.filter((p, i) => i === 0 || screenDist(p, S.pts[i - 1]) > 1.5);
  S.pts = [];
  renderDraw();
  if (pts.length < 3) { if (pts.length) toast("A polygon needs at least three corners.", "info"); return; }
  submitShape("polygon", pts);
}

function setupDrawing() {
  const c = $("draw-canvas");
  c.addEventListener("mousedown", (ev) => {
    if (ev.button !== 0) return;
    c.focus();
    const p = imagePoint(ev);
    if (S.tool === "box") { S.drag = { from: p, to: p }; renderDraw(); }
  });
  c.addEventListener("mousemove", (ev) => {
    const p = imagePoint(ev);
    if (S.tool === "box" && S.drag) { S.drag.to = p; renderDraw(); }
    else if (S.tool === "polygon" && S.pts.length) renderDraw(p);
  });
  window.addEventListener("mouseup", (ev) => {
    if (S.tool !== "box" || !S.drag) return;
    const d = S.drag; S.drag = null;
    d.to = imagePoint(ev);
    renderDraw();
    if (Math.abs(d.to[0] - d.from[0]) >= 1 && Math.abs(d.to[1] - d.from[1]) >= 1) submitShape("box", [d.from, d.to]);
  });
  c.addEventListener("click", (ev) => {
    if (S.tool === "found") { submitShape("found", [imagePoint(ev)]); return; }
    if (S.tool === "click") { addClick(imagePoint(ev), !ev.shiftKey); return; }
    if (S.tool !== "polygon") return;
    const p = imagePoint(ev);
    if (S.pts.length >= 3 && screenDist(p, S.pts[0]) < 8) { closePolygon(); return; }
    S.pts.push(p);
    renderDraw(p);
  });
  c.addEventListener("contextmenu", (ev) => {
    if (S.tool !== "click") return;
    ev.preventDefault();
    addClick(imagePoint(ev), false);
  });
  c.addEventListener("dblclick", (ev) => { ev.preventDefault(); if (S.tool === "polygon") closePolygon(); });
  $("close-polygon").addEventListener("click", closePolygon);
  $("cancel-shape").addEventListener("click", () => { S.pts = []; S.drag = null; renderDraw(); });
  for (const b of document.querySelectorAll(".tool")) b.addEventListener("click", () => setTool(b.dataset.tool));
  for (const b of document.querySelectorAll(".mode")) b.addEventListener("click", () => setMode(b.dataset.mode));
  $("object-select").addEventListener("change", (ev) => selectObject(parseInt(ev.target.value, 10)));
  $("undo").addEventListener("click", undoStroke);
  $("delete-keyframe").addEventListener("click", async () => {
    const f = cur();
    if (!S.kf || !S.kf.index) { toast("This frame has no keyframe mask.", "info"); return; }
    if (S.kf.readOnly) { toast(`This keyframe is keyframes/${f.fid}.json (LabelMe): delete that file to replace it.`, "info"); return; }
    if (!confirm(`Delete the keyframe mask of ${f.key}?`)) return;
    const res = await edit("deleting the keyframe", () => api(`/api/keyframe/${f.fid}/delete`, { versions: S.kf.versions }));
    if (res) { S.keyframes = res.keyframes; S.kf = { fid: f.fid, versions: {}, index: null }; renderOverlay(); renderLists(); renderThumbMarks(); }
  });
  for (const id of ["show-masks", "show-keyframe", "opacity"]) $(id).addEventListener("input", renderOverlay);
}

function setTool(t) {
  S.tool = t; S.pts = []; S.drag = null; S.clicks = null;
  document.querySelectorAll(".tool").forEach((b) => b.classList.toggle("active", b.dataset.tool === t));
  $("hint").textContent = t === "click"
    ? "Click on the object; shift+click or right click on what is not. Each click refines its mask (ctrl+z takes one back)."
    : "Draw every object visible on a keyframe: pixels not drawn count as background.";
  $("close-polygon").disabled = t !== "polygon";
  renderDraw();
}

function setMode(m) {
  S.mode = m;
  document.querySelectorAll(".mode").forEach((b) => b.classList.toggle("active", b.dataset.mode === m));
  renderDraw();
}

function selectObject(i) {
  if (i < -1 || i >= S.objects.length) return;  // -1: the ignore class (a person, a hand)
  S.obj = i;
  renderObjects();
  renderDraw();
}

// ------------------------------------------------------------------------------------------------ objects + states
// Entries of key_frame_value.yaml that are not a state in [0, 1] (typed by hand): shown with "!" in the states
// table; setting the state of that object on that frame (or clearing it) replaces the entry.
function setBadLabels(bad) {
  const before = (S.badLabels || []).map((b) => b.problem).join("\n");
  S.badLabels = bad || [];
  const now = S.badLabels.map((b) => b.problem).join("\n");
  if (now && now !== before) {
    toast(`${S.badLabels.length} unreadable state(s) in key_frame_value.yaml (marked ! in the states table): `
      + S.badLabels[0].problem);
  }
}

function badLabelOf(key, name) {
  return (S.badLabels || []).find((b) => b.frame === key && (b.object === name || b.object === ""));
}

function labelOf(key, name) {
  const e = S.labels[key];
  return e && Object.prototype.hasOwnProperty.call(e, name) ? e[name] : null;
}

async function setState(name, value) {
  const f = cur();
  const res = await edit("saving the state", async () => {
    const r = await api("/api/labels", {
      version: S.labelsVersion, edits: [{ frame: f.key, object: name, value, base: labelOf(f.key, name) }],
    });
    S.labels = r.labels; S.labelsVersion = r.version;
    setBadLabels(r.bad_labels);
    return r;
  });
  if (res && res.merged) toast("Merged with changes made in another tab.", "info");
  renderObjects();
  renderLists();
  renderThumbMarks();
}

function renderObjects() {
  const sel = $("object-select");
  sel.innerHTML = "";
  S.objects.forEach((o, i) => {
    const opt = document.createElement("option");
    opt.value = i; opt.textContent = `${i + 1}. ${o.name}`;
    sel.appendChild(opt);
  });
  const ign = document.createElement("option");
  ign.value = -1; ign.textContent = "ignore (person / hand)";
  ign.title = "people, hands, arms: left out of poses, motions and training";
  sel.appendChild(ign);
  sel.value = S.obj;
  const box = $("objects");
  // never rebuild under the user's hand: a slider being dragged or a name being typed would lose its edit
  if (S.sliding) return;
  if (box.contains(document.activeElement) && document.activeElement.tagName === "INPUT" && document.activeElement.type === "text") return;
  box.innerHTML = "";
  if (!S.objects.length) {
    box.innerHTML = '<div class="hint">No objects yet: add the first one below.</div>';
    return;
  }
  const f = cur();
  S.objects.forEach((o, i) => {
    const v = f ? labelOf(f.key, o.name) : null;
    const div = document.createElement("div");
    div.className = "obj" + (i === S.obj ? " selected" : "") + (v === null ? " unset" : "");
    div.dataset.object = o.name;
    div.innerHTML = `
      <div class="row"><span class="swatch"></span>
        <span class="name" title="select for drawing"></span>
        <button class="small rename" title="rename">rename</button></div>
      <div class="row state"><span class="dim">closed</span>
        <input type="range" min="0" max="1" step="0.01" class="state-slider">
        <span class="dim">open</span><span class="value"></span>
        <button class="small clear" title="remove this label">clear</button></div>`;
    div.querySelector(".name").textContent = o.name;
    div.querySelector(".swatch").style.background = color(o.id);
    if (S.prompts[o.name]) div.querySelector(".name").title = S.prompts[o.name];
    const slider = div.querySelector(".state-slider");
    slider.setAttribute("aria-label", "state of " + o.name);
    slider.value = v === null ? 0.5 : v;
    div.querySelector(".value").textContent = v === null ? "—" : v.toFixed(2);
    slider.addEventListener("input", () => { div.querySelector(".value").textContent = parseFloat(slider.value).toFixed(2); });
    slider.addEventListener("pointerdown", () => { S.sliding = true; });
    slider.addEventListener("change", () => { S.sliding = false; setState(o.name, parseFloat(slider.value)); });
    div.querySelector(".clear").addEventListener("click", () => { if (v !== null) setState(o.name, null); });
    div.querySelector(".clear").disabled = v === null;
    div.querySelector(".name").addEventListener("click", () => selectObject(i));
    div.querySelector(".rename").addEventListener("click", () => startRename(div, o));
    box.appendChild(div);
  });
}

function startRename(div, o) {
  const span = div.querySelector(".name");
  span.innerHTML = "";
  const inp = document.createElement("input");
  inp.type = "text"; inp.value = o.name; inp.className = "rename-input"; inp.maxLength = 100;
  span.appendChild(inp);
  inp.focus(); inp.select();
  let done = false;
  const finish = async (save) => {
    if (done) return;
    done = true;
    inp.blur();
    const name = inp.value.trim();
    if (save && name && name !== o.name) {
      const st = await edit("renaming", () => api("/api/objects/rename", { old: o.name, new: name }));
      if (st) { applyState(st); toast(`Renamed “${o.name}” to “${name}” in the mapping, labels and keyframes.`, "info"); return; }
    }
    renderObjects();
  };
  inp.addEventListener("keydown", (ev) => {
    if (ev.key === "Enter") { ev.preventDefault(); finish(true); }
    if (ev.key === "Escape") finish(false);
    ev.stopPropagation();
  });
  inp.addEventListener("blur", () => finish(true));
}

// ------------------------------------------------------------------------------------------------ lists
function li(text, why, fid) {
  const el = document.createElement("li");
  el.textContent = text;
  if (why) { const s = document.createElement("span"); s.className = "why"; s.textContent = why; el.appendChild(s); }
  if (fid !== undefined) {
    el.dataset.fid = fid;
    if (cur() && cur().fid === fid) el.classList.add("current");
    el.addEventListener("click", () => gotoFid(fid));
  }
  return el;
}

function gotoFid(fid) {
  const i = S.frames.findIndex((f) => f.fid === fid);
  if (i >= 0) goto(i);
}

function renderLists() {
  const sg = $("suggested"); sg.innerHTML = "";
  if (!S.suggested.length) sg.appendChild(li(S.masks.length ? "no suggestions in the masks report" : "run propagation to get suggestions"));
  for (const s of S.suggested) {
    const el = li("frame " + s.fid, s.reason, s.fid);
    if (s.fix) {  // a label the geometry disagrees with: one click sets the measured state
      const b = document.createElement("button");
      b.className = "fix"; b.textContent = `use measured ${s.fix.value.toFixed(2)}`;
      b.title = `set '${s.fix.object}' on this frame to the state its measured motion gives`;
      b.addEventListener("click", async (ev) => { ev.stopPropagation(); gotoFid(s.fid); await setState(s.fix.object, s.fix.value); });
      el.appendChild(b);
    }
    sg.appendChild(el);
  }
  sg.querySelectorAll("li:not([data-fid])").forEach((e) => e.classList.add("empty"));
  const kl = $("keyframes"); kl.innerHTML = "";
  $("kf-count").textContent = `(${S.keyframes.length})`;
  if (!S.keyframes.length) { const e = li("none yet: draw a mask on a frame"); e.classList.add("empty"); kl.appendChild(e); }
  for (const fid of S.keyframes) kl.appendChild(li("frame " + fid, S.labelme.includes(fid) ? "LabelMe, read-only" : "", fid));
  const t = $("labels"); t.innerHTML = "";
  const names = S.objects.map((o) => o.name);
  const keys = [...new Set([...Object.keys(S.labels), ...(S.badLabels || []).map((b) => b.frame)])].sort();
  let n = 0;
  const head = document.createElement("thead");
  head.innerHTML = "<tr><th>frame</th></tr>";
  for (const nm of names) { const th = document.createElement("th"); th.textContent = nm; head.firstChild.appendChild(th); }
  t.appendChild(head);
  const body = document.createElement("tbody");
  for (const k of keys) {
    const tr = document.createElement("tr");
    const fr = S.frames.find((f) => f.key === k);
    if (fr && cur() && fr.fid === cur().fid) tr.className = "current";
    const td = document.createElement("td"); td.textContent = k; tr.appendChild(td);
    for (const nm of names) {
      const c = document.createElement("td");
      const v = labelOf(k, nm);
      const bad = v === null ? badLabelOf(k, nm) : null;
      c.textContent = bad ? "!" : v === null ? "·" : v.toFixed(2);
      if (bad) { c.className = "bad"; c.title = bad.value + ": " + bad.problem; }
      if (v !== null) n++;
      tr.appendChild(c);
    }
    if (fr) tr.addEventListener("click", () => gotoFid(fr.fid));
    body.appendChild(tr);
  }
  t.appendChild(body);
  $("label-count").textContent = `(${n})`;
}

function buildThumbs() {
  const box = $("thumbs");
  box.innerHTML = "";
  for (const f of S.frames) {
    const d = document.createElement("div");
    d.className = "thumb"; d.dataset.fid = f.fid; d.title = f.key;
    const im = document.createElement("img");
    im.loading = "lazy"; im.alt = f.key;
    im.src = `/api/thumb/${f.fid}?token=${encodeURIComponent(TOKEN)}`;
    d.appendChild(im);
    const tag = document.createElement("span"); tag.className = "tag"; tag.textContent = f.index; d.appendChild(tag);
    const marks = document.createElement("span"); marks.className = "marks"; d.appendChild(marks);
    d.addEventListener("click", () => gotoFid(f.fid));
    box.appendChild(d);
  }
  renderThumbMarks();
}

function renderThumbMarks() {
  const kf = new Set(S.keyframes), sg = new Set(S.suggested.map((s) => s.fid));
  const labelled = new Set(S.frames.filter((f) => S.labels[f.key] && Object.keys(S.labels[f.key]).length).map((f) => f.fid));
  for (const d of document.querySelectorAll(".thumb")) {
    const fid = d.dataset.fid, m = d.querySelector(".marks");
    m.innerHTML = (kf.has(fid) ? '<i class="kf" title="keyframe mask"></i>' : "") +
      (labelled.has(fid) ? '<i class="lb" title="state label"></i>' : "") +
      (sg.has(fid) ? '<i class="sg" title="suggested"></i>' : "");
  }
}

// ------------------------------------------------------------------------------------------------ propagation
function showPropagation(p) {
  if (!p) return;
  const bar = $("prop-progress");
  bar.dataset.state = p.state;
  bar.dataset.indeterminate = p.total > 0 ? "0" : "1";
  $("prop-bar").style.width = p.state === "running" && p.total > 0 ? `${(100 * p.done / p.total).toFixed(1)}%` : "";
  $("propagate").disabled = p.state === "running";
  let text = "";
  if (p.state === "running") text = `propagating… ${p.total ? p.done + "/" + p.total + " frames" : ""} ${p.elapsed_s}s`;
  if (p.state === "done") {
    const r = p.result || {};
    const bits = [];
    if (typeof r.frames === "number") bits.push(`${r.frames} frames`);
    if (typeof r.fps === "number") bits.push(`${r.fps.toFixed(1)} frames/s`);
    if (typeof r.reused_frames === "number" && r.reused_frames > 0) bits.push(`${r.reused_frames} kept from the last run`);
    const conf = r.confidence_mean;
    if (conf && typeof conf === "object") {
      bits.push("mean confidence " + Object.entries(conf).map(([n, c]) => `${n} ${(+c).toFixed(2)}`).join(", "));
    }
    const next = r.suggested_frames || r.suggested;
    if (Array.isArray(next) && next.length) bits.push("annotate next: " + next.slice(0, 5).join(", "));
    text = `propagation done in ${p.elapsed_s}s` + (bits.length ? " · " + bits.join(" · ") : "");
  }
  if (p.state === "failed") text = "propagation failed: " + p.message;
  $("prop-text").textContent = text;
  $("prop-text").title = text;
}

async function pollPropagation() {
  clearTimeout(S.polling);
  let p;
  try { p = await api("/api/propagate"); } catch (e) { S.polling = setTimeout(pollPropagation, 1500); return; }
  showPropagation(p);
  if (p.state === "running") { S.polling = setTimeout(pollPropagation, 400); return; }
  if (p.state === "failed") toast("Propagation failed: " + p.message);
  await refreshState(true);
}

async function runPropagation() {
  const res = await edit("starting propagation", () => api("/api/propagate", {}));
  if (res) { showPropagation({ state: "running", done: 0, total: 0, elapsed_s: 0 }); pollPropagation(); }
}

// ------------------------------------------------------------------------------------------------ start
function setupKeys() {
  // after the slider's own change event (same task), never before it
  window.addEventListener("pointerup", () => { if (S.sliding) setTimeout(() => { S.sliding = false; renderObjects(); }, 50); });
  window.addEventListener("keydown", (ev) => {
    const tag = (ev.target && ev.target.tagName) || "";
    if (tag === "INPUT" || tag === "SELECT" || tag === "TEXTAREA") return;
    if ((ev.ctrlKey || ev.metaKey) && ev.key === "z") { ev.preventDefault(); undoStroke(); return; }
    if (ev.ctrlKey || ev.metaKey || ev.altKey) return;
    if (ev.key === "ArrowLeft") { ev.preventDefault(); goto(S.cur - 1); }
    else if (ev.key === "ArrowRight") { ev.preventDefault(); goto(S.cur + 1); }
    else if (ev.key === "p") setTool("polygon");
    else if (ev.key === "b") setTool("box");
    else if (ev.key === "f") setTool("found");
    else if (ev.key === "c") setTool("click");
    else if (ev.key === "e") setMode(S.mode === "erase" ? "paint" : "erase");
    else if (ev.key === "Enter" && S.tool === "polygon" && S.pts.length) { ev.preventDefault(); closePolygon(); }
    else if (ev.key === "Escape") { S.pts = []; S.drag = null; renderDraw(); }
    else if (/^[1-9]$/.test(ev.key)) selectObject(parseInt(ev.key, 10) - 1);
  });
}

async function start() {
  if (!TOKEN) { setSave("error", "no token"); toast("Open the exact URL that `interreal annotate` printed (it carries the access token)."); return; }
  setupDrawing();
  setupKeys();
  setTool("polygon");
  setMode("paint");
  $("frame-slider").addEventListener("input", (ev) => goto(parseInt(ev.target.value, 10)));
  $("prev").addEventListener("click", () => goto(S.cur - 1));
  $("next").addEventListener("click", () => goto(S.cur + 1));
  $("propagate").addEventListener("click", runPropagation);
  $("add-object-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const name = $("new-object").value.trim();
    if (!name) return;
    const st = await edit("adding the object", () => api("/api/objects", { name, description: $("new-object-desc").value.trim() }));
    if (st) {
      $("new-object").value = ""; $("new-object-desc").value = "";
      applyState(st);
      selectObject(S.objects.length - 1);
    }
  });
  // the stage follows its box: window resizes and toolbar / panel reflows alike
  new ResizeObserver(() => { if (S.w) fitStage(); }).observe(document.querySelector(".stage-wrap"));
  try {
    const st = await api("/api/state");
    applyState(st);
  } catch (e) { setSave("error", "cannot load"); toast("Cannot load the dataset: " + e.message); return; }
  buildThumbs();
  await goto(frameFromHash());
  setSave("idle", "ready");
  document.body.dataset.ready = "1";
  // another tab (or the CLI) may edit the same dataset: pick its changes up
  if (POLL_MS > 0) setInterval(() => { if (!document.hidden) refreshState(false).catch(() => {}); }, POLL_MS);
  const p = await api("/api/propagate");
  if (p.state === "running") pollPropagation();
}

start();
