// bench4d annotate: the page. Plain ES modules, a 2D canvas, nothing fetched from elsewhere.
//
// Masks live here as Uint8Array(W*H) per (mask-owning query, frame index); the canvas only shows
// them. Edits are saved about a second after they happen (and at once on frame change) as a batch
// tagged with the revision the page last saw; the server refuses a stale batch (409).

import { Api, HttpError, readToken } from "./api.js";
import * as M from "./mask.js";
import { Review } from "./review.js";
import { Timeline, endAt, normalise, removeAt } from "./timeline.js";

const COLOURS = [[255, 64, 96], [64, 160, 255], [80, 220, 120], [255, 200, 40], [200, 100, 255], [0, 220, 220],
  [255, 128, 0], [230, 230, 230]];
const PROPOSAL_RGB = [0, 255, 255];
const UNDO_LIMIT = 60;
const IMAGE_CACHE = 24;
const ACTIVE_GAP_MS = 30000; // pauses longer than this do not count as annotation time

const $ = (sel) => document.querySelector(sel);

const S = {
  api: null,
  info: null,          // /api/state
  frames: [],
  queries: [],
  revision: 0,
  cur: 0,
  qid: null,           // selected query
  store: new Map(),    // "owner:frame" -> {mask: Uint8Array | null}   (null: not annotated)
  loaded: new Set(),   // frames whose masks came from the server
  status: {},          // owner -> {frame: 1 (mask) | 0 (absent)}
  history: new Map(),  // key -> {undo: [{stamp, value}], redo: [...]}; key "owner:frame" or "iv:qid"
  stamp: 0,
  proposals: new Map(),// "owner:frame" -> Uint8Array
  assist: new Map(),   // "owner:frame" -> {box, clicks}
  dirtyMasks: new Set(),
  dirtyIntervals: new Set(),
  timing: {},
  lastActivity: 0,
  saving: false,
  saveTimer: null,
  again: false,
  conflict: false,
  leaving: false,
  tool: "box",
  brush: 8,
  pending: new Map(),  // qid -> pending interval start
  timelineQid: null,
  images: new Map(),
  img: null,
  overlayDirty: true,
  drag: null,
  polygon: [],
  hover: null,
  zoom: 1,
  overlayAll: true,    // outline every query's mask, not only the selected one's
  overlayDrawn: [],    // owners drawn in the overlay at the last render
};

// ------------------------------------------------------------------------------------------
// helpers
// ------------------------------------------------------------------------------------------
function frameSize(i) { const f = S.frames[i]; return [f.width, f.height]; }
function queryById(id) { return S.queries.find((q) => q.id === id); }
function ownerOf(qid) { const q = queryById(qid); return q && q.kind === "sensitive" && q.base !== null ? q.base : qid; }
function keyOf(owner, frame) { return `${owner}:${frame}`; }
function curKey() { return S.qid === null ? null : keyOf(ownerOf(S.qid), S.cur); }
function entry(key) { return S.store.get(key); }
function colourOf(owner) {
  const idx = Math.max(0, S.queries.filter((q) => q.kind === "agnostic").findIndex((q) => q.id === owner));
  if (idx < COLOURS.length) return COLOURS[idx];
  // past the fixed palette: hues a golden angle apart, so no two queries share a colour
  const hue = ((idx - COLOURS.length) * 137.508 + 20) % 360;
  return hslToRgb(hue, 0.85, idx % 2 ? 0.62 : 0.5);
}
function hslToRgb(h, s, l) {
  const c = (1 - Math.abs(2 * l - 1)) * s, x = c * (1 - Math.abs(((h / 60) % 2) - 1)), m = l - c / 2;
  const [r, g, b] = h < 60 ? [c, x, 0] : h < 120 ? [x, c, 0] : h < 180 ? [0, c, x] : h < 240 ? [0, x, c]
    : h < 300 ? [x, 0, c] : [c, 0, x];
  return [r, g, b].map((v) => Math.round((v + m) * 255));
}
// frames of the session where ``owner`` has an annotation (a mask or "absent")
function doneCount(owner) { return Object.keys(S.status[owner] || {}).length; }
function message(text) { $("#message").textContent = text; }
function timeOfFrame(i) { return S.frames[i].time_index; }

function setSaveStatus() {
  const el = $("#save-status");
  let state, text;
  if (S.conflict) { state = "conflict"; text = "conflict: not saved"; }
  else if (S.saveError) { state = "error"; text = `● unsaved (${S.saveError}; retrying)`; }
  else if (S.saving) { state = "saving"; text = "saving…"; }
  else if (S.dirtyMasks.size || S.dirtyIntervals.size) { state = "dirty"; text = "● unsaved"; }
  else { state = "saved"; text = `saved · rev ${S.revision}`; }
  el.dataset.state = state;
  el.textContent = text;
}

function isDirty() { return S.dirtyMasks.size > 0 || S.dirtyIntervals.size > 0 || S.saving; }

// ------------------------------------------------------------------------------------------
// loading
// ------------------------------------------------------------------------------------------
function applyState(state) {
  S.info = state;
  S.frames = state.frames;
  S.queries = state.queries;
  S.revision = state.revision;
  S.status = {};
  for (const [q, d] of Object.entries(state.status)) {
    S.status[+q] = {};
    for (const [i, v] of Object.entries(d)) S.status[+q][+i] = v;
  }
  if (S.qid === null || !queryById(S.qid)) S.qid = S.queries.length ? S.queries[0].id : null;
  $("#scene-name").textContent = `${state.scene} · ${state.file}`;
  $("#frames-offered").textContent = state.frames_offered || "";
  $("#scrubber").max = String(S.frames.length - 1);
  fillFormatSelect("#export-format", state.export_formats);
  fillFormatSelect("#import-format", state.import_formats);
  renderQueries();
  setSaveStatus();
}

function fillFormatSelect(sel, formats) {
  const el = $(sel);
  if (el.options.length) return;
  for (const [k, v] of Object.entries(formats)) {
    const o = document.createElement("option");
    o.value = k; o.textContent = k; o.title = v;
    el.append(o);
  }
}

function loadImage(i) {
  if (S.images.has(i)) return S.images.get(i);
  const img = new Image();
  img.decoding = "async";
  const p = new Promise((resolve, reject) => {
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error(`frame ${i} failed to load`));
  });
  img.src = `/api/frame/${i}.jpg`;
  S.images.set(i, p);
  while (S.images.size > IMAGE_CACHE) S.images.delete(S.images.keys().next().value);
  p.catch(() => S.images.delete(i));
  return p;
}

async function loadMasks(i) {
  if (S.loaded.has(i)) return;
  const res = await S.api.get(`/api/masks/${i}`);
  const [w, h] = frameSize(i);
  for (const [q, payload] of Object.entries(res.masks)) {
    const key = keyOf(+q, i);
    if (S.store.has(key)) continue; // a local edit is newer than the server's copy
    S.store.set(key, { mask: payload ? M.decodeRuns(payload.counts, w, h) : null, madeBy: payload?.made_by ?? null });
  }
  S.loaded.add(i);
}

async function gotoFrame(i) {
  i = Math.max(0, Math.min(S.frames.length - 1, i));
  if (i !== S.cur && (S.dirtyMasks.size || S.dirtyIntervals.size)) flush();
  cancelInteraction();
  S.cur = i;
  sessionStorage.setItem("bench4d-frame", String(i));
  $("#scrubber").value = String(i);
  const f = S.frames[i];
  $("#frame-info").textContent = `frame ${i + 1}/${S.frames.length} · t=${f.time_index} · ${f.name} (${f.split})`;
  const [img] = await Promise.all([loadImage(i), loadMasks(i)]);
  if (S.cur !== i) return;
  S.img = img;
  fitCanvas();
  S.overlayDirty = true;
  render();
  renderQueries();
  S.timeline.draw();
  for (const j of [i + 1, i - 1, i + 2]) if (j >= 0 && j < S.frames.length) loadImage(j);
}

// ------------------------------------------------------------------------------------------
// drawing
// ------------------------------------------------------------------------------------------
const view = () => $("#view");
let overlayCanvas = null, overlayData = null;

function fitCanvas() {
  const [w, h] = frameSize(S.cur);
  const c = view();
  if (c.width !== w || c.height !== h) { c.width = w; c.height = h; overlayCanvas = null; }
  const wrap = $("#canvas-wrap");
  const fit = Math.min((wrap.clientWidth - 4) / w, (wrap.clientHeight - 4) / h, 4);
  const scale = Math.max(0.1, fit) * S.zoom;
  c.style.width = `${Math.round(w * scale)}px`;
  c.style.height = `${Math.round(h * scale)}px`;
}

// Zoom to ``zoom`` keeping the image point under (clientX, clientY) where it is on screen.
function zoomAt(zoom, clientX, clientY) {
  const wrap = $("#canvas-wrap");
  const before = view().getBoundingClientRect();
  const fx = (clientX - before.left) / before.width, fy = (clientY - before.top) / before.height;
  S.zoom = Math.max(1, Math.min(8, zoom));
  fitCanvas();
  const after = view().getBoundingClientRect();
  wrap.scrollLeft += after.left + fx * after.width - clientX;
  wrap.scrollTop += after.top + fy * after.height - clientY;
  message(S.zoom > 1 ? `zoom ${S.zoom.toFixed(2)}x (Z resets, middle-drag pans)` : "zoom: fit");
}

function resetZoom() {
  S.zoom = 1;
  fitCanvas();
  $("#canvas-wrap").scrollTo(0, 0);
  message("zoom: fit");
}

function render() {
  const c = view();
  const g = c.getContext("2d");
  const [w, h] = frameSize(S.cur);
  g.imageSmoothingEnabled = false;
  g.clearRect(0, 0, w, h);
  if (S.img) g.drawImage(S.img, 0, 0, w, h);
  if (!overlayCanvas) {
    overlayCanvas = document.createElement("canvas");
    overlayCanvas.width = w; overlayCanvas.height = h;
    overlayData = overlayCanvas.getContext("2d").createImageData(w, h);
    S.overlayDirty = true;
  }
  const key = curKey();
  if (S.overlayDirty) {
    overlayData.data.fill(0);
    const e = key ? entry(key) : null;
    const prop = key ? S.proposals.get(key) : null;
    S.overlayDrawn = [];
    if (S.overlayAll) {
      // every other query's mask on this frame as an outline in its colour, under the selected one
      for (const q of S.queries) {
        if (q.kind !== "agnostic" || q.id === ownerOf(S.qid)) continue;
        const other = entry(keyOf(q.id, S.cur));
        if (other && other.mask && !M.isEmpty(other.mask)) {
          M.paintOutline(overlayData, other.mask, colourOf(q.id));
          S.overlayDrawn.push(q.id);
        }
      }
    }
    if (e && e.mask) {
      const rgb = colourOf(ownerOf(S.qid));
      S.overlayDrawn.push(ownerOf(S.qid));
      M.paint(overlayData, e.mask, rgb, 110);
      M.paintOutline(overlayData, e.mask, rgb);
    } else if (prop) {
      M.paint(overlayData, prop, PROPOSAL_RGB, 120, "hatch");
      M.paintOutline(overlayData, prop, PROPOSAL_RGB);
    }
    overlayCanvas.getContext("2d").putImageData(overlayData, 0, 0);
    S.overlayDirty = false;
  }
  g.drawImage(overlayCanvas, 0, 0);
  // interaction marks (display only)
  const lw = Math.max(1, w / parseFloat(view().style.width || w));
  g.lineWidth = lw;
  if (S.drag && S.drag.kind === "box") {
    const [x0, y0] = S.drag.start, [x1, y1] = S.drag.end;
    g.strokeStyle = "#ffff00";
    g.strokeRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0));
  }
  const a = key ? S.assist.get(key) : null;
  if (a && S.tool === "box") {
    if (a.box) {
      g.setLineDash([4 * lw, 4 * lw]);
      g.strokeStyle = "#ffff00";
      const [x0, y0, x1, y1] = a.box;
      g.strokeRect(x0, y0, x1 - x0, y1 - y0);
      g.setLineDash([]);
    }
    for (const [x, y, lbl] of a.clicks) {
      g.fillStyle = lbl ? "#40ff60" : "#ff4040";
      g.beginPath(); g.arc(x, y, 4 * lw, 0, 2 * Math.PI); g.fill();
    }
  }
  if (S.polygon.length) {
    g.strokeStyle = "#ffffff";
    g.beginPath();
    S.polygon.forEach(([x, y], k) => (k ? g.lineTo(x, y) : g.moveTo(x, y)));
    if (S.hover) g.lineTo(S.hover[0], S.hover[1]);
    g.stroke();
  }
  if ((S.tool === "brush" || S.tool === "eraser") && S.hover) {
    g.strokeStyle = S.tool === "brush" ? "#ffffff" : "#ff8080";
    g.beginPath(); g.arc(S.hover[0], S.hover[1], S.brush, 0, 2 * Math.PI); g.stroke();
  }
  updateMaskState();
}

function updateMaskState() {
  const key = curKey();
  let text = "no query";
  if (key) {
    const e = entry(key);
    if (!S.loaded.has(S.cur)) text = "loading…";
    else if (e && e.mask) text = M.isEmpty(e.mask) ? "absent in this frame" : `mask (${M.area(e.mask)} px)`;
    else if (S.proposals.has(key)) text = "proposal: Enter accepts";
    else text = "not annotated";
  }
  $("#mask-state").textContent = text;
  $("#mask-state").dataset.state = text.split(" ")[0];
}

function renderQueries() {
  const ul = $("#queries");
  ul.textContent = "";
  if (!S.queries.length) {
    const hint = document.createElement("li");
    hint.className = "hint";
    hint.textContent = "Start here: add a query below (e.g. \"cookie\"), then drag a box around it on the image.";
    ul.append(hint);
  }
  S.queries.forEach((q, n) => {
    const li = document.createElement("li");
    li.dataset.qid = String(q.id);
    if (q.id === S.qid) li.className = "selected";
    const sw = document.createElement("span");
    sw.className = "swatch";
    const rgb = colourOf(ownerOf(q.id));
    sw.style.background = `rgb(${rgb.join(",")})`;
    const label = document.createElement("span");
    label.textContent = `${queryKey(n)}${q.text}`;
    const parts = [sw, label];
    if (q.review === "draft") {
      const draft = document.createElement("span");
      draft.className = "draft";
      draft.textContent = "draft";
      draft.title = "not yet reviewed: made by a program or a person and not checked";
      parts.push(draft);
    }
    const kind = document.createElement("span");
    kind.className = "kind";
    kind.textContent = q.kind === "sensitive" ? `when · masks of "${queryById(q.base)?.text}"` : (q.level || "");
    const st = document.createElement("span");
    st.className = "qstate";
    const v = S.status[ownerOf(q.id)]?.[S.cur];
    st.textContent = v === 1 ? "mask" : v === 0 ? "absent" : "–";
    const progress = document.createElement("span");
    progress.className = "progress";
    progress.textContent = `${doneCount(ownerOf(q.id))}/${S.frames.length}`;
    progress.title = "frames annotated (mask or absent) of the frames offered";
    li.append(...parts, kind, st, progress);
    li.addEventListener("click", () => selectQuery(q.id));
    ul.append(li);
  });
  $("#mark-reviewed").hidden = queryById(S.qid)?.review !== "draft";
  drawScrubberMarks();
  const base = $("#new-base");
  base.textContent = "";
  for (const q of S.queries.filter((x) => x.kind === "agnostic")) {
    const o = document.createElement("option");
    o.value = String(q.id); o.textContent = `base: ${q.text}`;
    base.append(o);
  }
}

// "1. " .. "9. ", "0. " for the tenth; later queries are reached with Q / Shift+Q
function queryKey(n) { return n < 9 ? `${n + 1}. ` : n === 9 ? "0. " : ""; }

// One tick per frame under the scrubber: the selected query's mask (its colour), absent (grey),
// not annotated (nothing).
function drawScrubberMarks() {
  const c = $("#scrubber-marks");
  if (!c || !S.frames.length) return;
  c.width = S.frames.length;
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const owner = S.qid === null ? null : ownerOf(S.qid);
  const st = owner === null ? {} : S.status[owner] || {};
  const rgb = owner === null ? [0, 0, 0] : colourOf(owner);
  for (const [f, v] of Object.entries(st)) {
    g.fillStyle = v ? `rgb(${rgb.join(",")})` : "#888";
    g.fillRect(+f, 0, 1, c.height);
  }
  c.dataset.done = String(Object.keys(st).length);
}

function cycleQuery(step) {
  if (!S.queries.length) return;
  const i = S.queries.findIndex((q) => q.id === S.qid);
  selectQuery(S.queries[(i + step + S.queries.length) % S.queries.length].id);
}

function selectQuery(qid) {
  if (!queryById(qid)) return;
  cancelInteraction();
  S.qid = qid;
  if (queryById(qid).kind === "sensitive") S.timelineQid = qid;
  S.overlayDirty = true;
  renderQueries();
  render();
  S.timeline.draw();
}

// ------------------------------------------------------------------------------------------
// editing (every change goes through setMask / setIntervals: undo + autosave)
// ------------------------------------------------------------------------------------------
function hist(key) {
  let h = S.history.get(key);
  if (!h) { h = { undo: [], redo: [] }; S.history.set(key, h); }
  return h;
}

function copyMask(m) { return m ? m.slice() : null; }

// Each undo step keeps the box and clicks shown before the edit: undoing a click takes its marker
// back too, so the next click does not silently redo it.
// How a mask was made, saved with it (``made_by``): an edit of a propagated mask makes it "corrected".
function madeByAfter(previous, how) {
  if (how === null || how === "absent" || how === "propagated") return how;
  return previous === "propagated" || previous === "corrected" ? "corrected" : how;
}

function setMask(key, mask, { record = true, before = undefined, assistBefore = undefined, how = null } = {}) {
  const e = entry(key) || { mask: null };
  const prev = before !== undefined ? before : copyMask(e.mask);
  if (record) {
    const h = hist(key);
    const assist = assistBefore !== undefined ? assistBefore : (S.assist.get(key) || null);
    h.undo.push({ stamp: ++S.stamp, value: prev, assist });
    if (h.undo.length > UNDO_LIMIT) h.undo.shift();
    h.redo = [];
  }
  S.store.set(key, { mask, madeBy: mask === null ? null : madeByAfter(e.madeBy ?? null, how) });
  markMaskDirty(key);
}

function markMaskDirty(key) {
  const [owner, frame] = key.split(":").map(Number);
  const e = entry(key);
  S.status[owner] = S.status[owner] || {};
  if (!e || e.mask === null) delete S.status[owner][frame];
  else S.status[owner][frame] = M.isEmpty(e.mask) ? 0 : 1;
  S.dirtyMasks.add(key);
  S.overlayDirty = true;
  scheduleSave();
  if (frame === S.cur) { render(); renderQueries(); } else drawScrubberMarks();
  S.timeline.draw();
}

function setIntervals(qid, ivs, { record = true } = {}) {
  const q = queryById(qid);
  if (!q) return;
  const next = normalise(ivs);
  if (JSON.stringify(next) === JSON.stringify(q.intervals)) { S.timeline.draw(); return; }
  if (record) {
    const h = hist(`iv:${qid}`);
    h.undo.push({ stamp: ++S.stamp, value: q.intervals.map((iv) => iv.slice()) });
    h.redo = [];
  }
  q.intervals = next;
  S.dirtyIntervals.add(qid);
  scheduleSave();
  S.timeline.draw();
}

// Undo the most recent edit of this frame's mask or of any timeline.
function undoRedo(which) {
  const other = which === "undo" ? "redo" : "undo";
  const keys = [];
  const key = curKey();
  if (key) keys.push(key);
  for (const q of S.queries) if (q.kind === "sensitive") keys.push(`iv:${q.id}`);
  let best = null;
  for (const k of keys) {
    const h = S.history.get(k);
    if (!h || !h[which].length) continue;
    const top = h[which][h[which].length - 1];
    if (!best || top.stamp > best.top.stamp) best = { k, h, top };
  }
  if (!best) { message(`nothing to ${which}`); return; }
  const { k, h } = best;
  const item = h[which].pop();
  if (k.startsWith("iv:")) {
    const qid = Number(k.slice(3));
    const q = queryById(qid);
    h[other].push({ stamp: ++S.stamp, value: q.intervals.map((iv) => iv.slice()) });
    q.intervals = item.value;
    S.dirtyIntervals.add(qid);
    scheduleSave();
    S.timeline.draw();
  } else {
    const e = entry(k) || { mask: null };
    h[other].push({ stamp: ++S.stamp, value: copyMask(e.mask), assist: S.assist.get(k) || null });
    if (item.assist) S.assist.set(k, item.assist);
    else S.assist.delete(k);
    S.store.set(k, { mask: item.value });
    markMaskDirty(k);
  }
  message(which === "undo" ? "undone" : "redone");
}

function editableKey() {
  const key = curKey();
  if (!key) { message("add or select a query first"); return null; }
  if (!S.loaded.has(S.cur)) { message("frame still loading"); return null; }
  return key;
}

function markAbsent() {
  const key = editableKey();
  if (!key) return;
  const [w, h] = frameSize(S.cur);
  setMask(key, M.emptyMask(w, h), { how: "absent" });
  S.assist.delete(key);
  message("marked absent in this frame");
}

function clearAnnotation() {
  const key = editableKey();
  if (!key) return;
  if (entry(key)?.mask === null || !entry(key)) { message("already not annotated"); return; }
  setMask(key, null);
  S.assist.delete(key);
  message("back to not annotated");
}

// ------------------------------------------------------------------------------------------
// autosave
// ------------------------------------------------------------------------------------------
function scheduleSave() {
  setSaveStatus();
  if (S.saveTimer === null) S.saveTimer = setTimeout(flush, S.info.autosave_delay_ms);
}

function buildChanges(keys, qids) {
  const changes = [];
  for (const key of keys) {
    const [owner, frame] = key.split(":").map(Number);
    const [w, h] = frameSize(frame);
    const e = entry(key);
    const m = e?.mask ?? null;
    let mask = null;
    if (m) mask = M.isEmpty(m) ? { absent: true } : { counts: M.encodeRuns(m, w, h) };
    changes.push({ type: "mask", query: owner, frame, mask, made_by: m ? e.madeBy ?? null : null });
  }
  for (const qid of qids) changes.push({ type: "intervals", query: qid, intervals: queryById(qid).intervals });
  return changes;
}

async function flush() {
  if (S.saveTimer !== null) { clearTimeout(S.saveTimer); S.saveTimer = null; }
  if (S.conflict) return;
  if (S.saving) { S.again = true; return; }
  const keys = [...S.dirtyMasks], qids = [...S.dirtyIntervals];
  const timing = S.timing;
  if (!keys.length && !qids.length) return;
  S.dirtyMasks.clear(); S.dirtyIntervals.clear(); S.timing = {};
  S.saving = true;
  setSaveStatus();
  try {
    const res = await S.api.post("/api/save", { revision: S.revision, changes: buildChanges(keys, qids), timing });
    S.revision = res.revision;
    S.saveError = null;
  } catch (err) {
    for (const k of keys) S.dirtyMasks.add(k);
    for (const q of qids) S.dirtyIntervals.add(q);
    for (const [f, s] of Object.entries(timing)) S.timing[f] = (S.timing[f] || 0) + s;
    if (err instanceof HttpError && err.status === 409) {
      S.conflict = true;
      $("#conflict").hidden = false;
    } else {
      S.saveError = err instanceof HttpError ? `HTTP ${err.status}: ${err.message}` : "server unreachable";
      setTimeout(scheduleSave, 1500);
    }
  } finally {
    S.saving = false;
    setSaveStatus();
  }
  if (S.again) { S.again = false; await flush(); }
}

// Resolve once everything edited so far is on disk (or a save failed).
async function flushNow() {
  for (let n = 0; n < 50; n++) {
    if (S.saving) { await new Promise((r) => setTimeout(r, 20)); continue; }
    if (!S.dirtyMasks.size && !S.dirtyIntervals.size) return !S.conflict && !S.saveError;
    await flush();
    if (S.conflict || S.saveError) return false;
  }
  return false;
}

function noteActivity() {
  const now = performance.now();
  const gap = now - S.lastActivity;
  if (S.lastActivity && gap < ACTIVE_GAP_MS) S.timing[S.cur] = (S.timing[S.cur] || 0) + gap / 1000;
  S.lastActivity = now;
}

// ------------------------------------------------------------------------------------------
// assisted segmentation and propagation
// ------------------------------------------------------------------------------------------
async function runSegment(key, frame, assist, assistBefore = null) {
  const [w, h] = frameSize(frame);
  const cur = entry(key)?.mask;
  const current = assist.clicks.length && cur && !M.isEmpty(cur) ? { counts: M.encodeRuns(cur, w, h) } : null;
  message("segmenting…");
  try {
    const res = await S.api.post("/api/segment", { frame, box: assist.box, clicks: assist.clicks, current });
    setMask(key, M.decodeRuns(res.counts, w, h), { assistBefore, how: assist.clicks.length ? "clicks" : "box" });
    message(`${res.segmenter}: ${(res.seconds * 1000).toFixed(0)} ms`);
  } catch (err) {
    message(`segmentation failed: ${err.message}`);
  }
}

async function propagate(direction) {
  const key = editableKey();
  if (!key) return;
  const e = entry(key);
  if (!e || !e.mask || M.isEmpty(e.mask)) { message("draw a mask on this frame first"); return; }
  if (!(await flushNow())) { message("cannot propagate: the mask is not saved"); return; }
  const owner = ownerOf(S.qid);
  const count = Math.max(1, parseInt($("#prop-count").value, 10) || 10);
  message("propagating…");
  try {
    const res = await S.api.post("/api/propagate", { query: owner, frame: S.cur, direction, count });
    for (const p of res.proposals) {
      const [w, h] = frameSize(p.frame);
      S.proposals.set(keyOf(owner, p.frame), M.decodeRuns(p.counts, w, h));
    }
    const methods = {};
    for (const p of res.proposals) methods[p.method] = (methods[p.method] || 0) + 1;
    const desc = Object.entries(methods).map(([m, n]) => `${n} ${m}`).join(", ");
    $("#prop-info").textContent = `${res.proposals.length} proposals (${desc || "none"}) in ${res.seconds.toFixed(2)} s`;
    message(`${res.proposals.length} proposals: step through and press Enter to accept`);
  } catch (err) {
    message(`propagation failed: ${err.message}`);
  }
}

function acceptProposal() {
  const key = editableKey();
  if (!key) return;
  const p = S.proposals.get(key);
  if (!p) { message("no proposal on this frame"); return; }
  setMask(key, p, { how: "propagated" });
  S.proposals.delete(key);
  message("proposal accepted");
}

const AREA_JUMP = 1.5; // a proposal whose area changes more than this from its neighbour needs a look

// Frames whose proposal's area jumps from the frame before it (the mask or proposal there), in
// frame order: a proposal that bridged a gap or lost a part.
function areaJumps(owner) {
  const frames = [...S.proposals.keys()].filter((k) => k.startsWith(`${owner}:`))
    .map((k) => Number(k.split(":")[1])).sort((a, b) => a - b);
  const jumps = [];
  for (const f of frames) {
    const prev = S.proposals.get(keyOf(owner, f - 1)) || entry(keyOf(owner, f - 1))?.mask
      || S.proposals.get(keyOf(owner, f + 1)) || entry(keyOf(owner, f + 1))?.mask;
    const a = M.area(S.proposals.get(keyOf(owner, f)));
    const b = prev ? M.area(prev) : 0;
    if (a && b && Math.max(a, b) > AREA_JUMP * Math.min(a, b)) jumps.push({ frame: f, area: a, neighbour: b });
  }
  return jumps;
}

// "Accept all" stores every proposal of the selected query. When some proposal's area jumps, the
// first press only lists those frames (the proposals stay shown hatched, to be looked at); a second
// press with the same proposals accepts them.
function acceptAll() {
  const owner = ownerOf(S.qid);
  const jumps = areaJumps(owner);
  const armed = jumps.map((j) => `${j.frame}:${j.area}`).join(",");
  if (jumps.length && S.acceptAllArmed !== armed) {
    S.acceptAllArmed = armed;
    const list = jumps.slice(0, 6).map((j) => `frame ${j.frame + 1} (${j.area} px against ${j.neighbour})`).join(", ");
    message(`area jumps: ${list}${jumps.length > 6 ? ", …" : ""}; look at them, then press Accept all again`);
    $("#accept-all-btn").dataset.warned = "1";
    return;
  }
  S.acceptAllArmed = null;
  delete $("#accept-all-btn").dataset.warned;
  let n = 0;
  for (const [key, p] of [...S.proposals]) {
    if (!key.startsWith(`${owner}:`)) continue;
    const e = entry(key);
    if (e && e.mask) { S.proposals.delete(key); continue; } // annotated meanwhile: keep the annotation
    setMask(key, p, { before: null, how: "propagated" });
    S.proposals.delete(key);
    n++;
  }
  message(`accepted ${n} proposals`);
}

function discardProposals(all) {
  if (all) { S.proposals.clear(); message("proposals discarded"); }
  else if (curKey()) S.proposals.delete(curKey());
  S.overlayDirty = true;
  render();
}

// ------------------------------------------------------------------------------------------
// pointer interaction on the canvas
// ------------------------------------------------------------------------------------------
function imagePoint(e) {
  const c = view();
  const r = c.getBoundingClientRect();
  return [((e.clientX - r.left) / r.width) * c.width, ((e.clientY - r.top) / r.height) * c.height];
}

function cancelInteraction() {
  S.drag = null;
  S.polygon = [];
}

function onPointerDown(e) {
  noteActivity();
  view().focus();
  if (e.button === 1) {  // middle button: pan the zoomed image
    e.preventDefault();
    const wrap = $("#canvas-wrap");
    S.drag = { kind: "pan", x: e.clientX, y: e.clientY, left: wrap.scrollLeft, top: wrap.scrollTop };
    view().setPointerCapture(e.pointerId);
    return;
  }
  const key = editableKey();
  if (!key) return;
  const p = imagePoint(e);
  const [w, h] = frameSize(S.cur);
  if (S.tool === "box") {
    S.drag = { kind: "box", start: p, end: p, button: e.button, key };
    view().setPointerCapture(e.pointerId);
  } else if (S.tool === "brush" || S.tool === "eraser") {
    const value = S.tool === "brush" && e.button === 0 ? 1 : 0;
    const before = copyMask(entry(key)?.mask ?? null);
    const mask = entry(key)?.mask ? entry(key).mask.slice() : M.emptyMask(w, h);
    M.stampDisk(mask, w, h, p[0], p[1], S.brush, value);
    S.store.set(key, { mask, madeBy: entry(key)?.madeBy ?? null });
    S.drag = { kind: "stroke", last: p, value, before, key };
    S.overlayDirty = true;
    view().setPointerCapture(e.pointerId);
    render();
  } else if (S.tool === "polygon" && e.button === 0) {
    S.polygon.push(p);
    render();
  }
}

function onPointerMove(e) {
  S.hover = imagePoint(e);
  const d = S.drag;
  if (d && d.kind === "pan") {
    const wrap = $("#canvas-wrap");
    wrap.scrollLeft = d.left - (e.clientX - d.x);
    wrap.scrollTop = d.top - (e.clientY - d.y);
    return;
  }
  if (d && d.kind === "box") d.end = S.hover;
  if (d && d.kind === "stroke") {
    const [w, h] = frameSize(S.cur);
    const mask = entry(d.key).mask;
    M.strokeSegment(mask, w, h, d.last[0], d.last[1], S.hover[0], S.hover[1], S.brush, d.value);
    d.last = S.hover;
    S.overlayDirty = true;
  }
  render();
}

function onPointerUp(e) {
  const d = S.drag;
  S.drag = null;
  if (!d || d.kind === "pan") return;
  if (d.kind === "stroke") {
    const after = entry(d.key).mask;
    if (d.before && M.equal(d.before, after)) { render(); return; }
    // one stroke = one undo step
    setMask(d.key, after, { before: d.before, how: "drawn" });
    return;
  }
  if (d.kind === "box") {
    const [x0, y0] = d.start, [x1, y1] = d.end;
    const isBox = Math.abs(x1 - x0) > 3 && Math.abs(y1 - y0) > 3 && d.button === 0;
    let a = S.assist.get(d.key);
    const assistBefore = a || null;
    if (isBox) {
      a = { box: [Math.min(x0, x1), Math.min(y0, y1), Math.max(x0, x1), Math.max(y0, y1)], clicks: [] };
    } else {
      a = a || { box: null, clicks: [] };
      a = { box: a.box, clicks: [...a.clicks, [x1, y1, d.button === 2 ? 0 : 1]] };
    }
    S.assist.set(d.key, a);
    render();
    runSegment(d.key, S.cur, a, assistBefore);
  }
}

function closePolygon(subtract) {
  const key = editableKey();
  if (!key || S.polygon.length < 3) { message("a polygon needs 3 points"); return; }
  const [w, h] = frameSize(S.cur);
  const mask = entry(key)?.mask ? entry(key).mask.slice() : M.emptyMask(w, h);
  M.fillPolygon(mask, w, h, S.polygon, subtract ? 0 : 1);
  S.polygon = [];
  setMask(key, mask, { how: "drawn" });
}

// ------------------------------------------------------------------------------------------
// keys
// ------------------------------------------------------------------------------------------
function setTool(tool) {
  S.tool = tool;
  cancelInteraction();
  for (const r of document.querySelectorAll('input[name="tool"]')) r.checked = r.value === tool;
  render();
}

function setBrush(r) {
  S.brush = Math.max(1, Math.min(60, r));
  $("#brush-size").value = String(S.brush);
  $("#brush-size-val").textContent = String(S.brush);
  render();
}

function nextUnfinished() {
  const agn = S.queries.filter((q) => q.kind === "agnostic");
  if (!agn.length) { message("no time-agnostic query yet"); return; }
  const n = S.frames.length;
  for (let k = 1; k <= n; k++) {
    const j = (S.cur + k) % n;
    if (agn.some((q) => S.status[q.id]?.[j] === undefined)) { gotoFrame(j); return; }
  }
  message("every frame is annotated for every query");
}

function timelineQuery() {
  const q = queryById(S.qid);
  if (q && q.kind === "sensitive") return q;
  const t = queryById(S.timelineQid);
  if (t) return t;
  return S.queries.find((x) => x.kind === "sensitive") || null;
}

function intervalKey(kind) {
  const q = timelineQuery();
  if (!q) { message("no time-sensitive query: add one (kind 'when')"); return; }
  const t = timeOfFrame(S.cur);
  if (kind === "start") {
    S.pending.set(q.id, t);
    message(`"${q.text}": interval starts at t=${t}; press ] at its last frame`);
  } else if (kind === "end") {
    const start = S.pending.has(q.id) ? S.pending.get(q.id) : null;
    S.pending.delete(q.id);
    setIntervals(q.id, endAt(q.intervals, t, start));
    message(`"${q.text}": ${q.intervals.map(([a, b]) => `[${a}, ${b}]`).join(" ")}`);
  } else {
    S.pending.delete(q.id);
    setIntervals(q.id, removeAt(q.intervals, t));
    message(`"${q.text}": interval at t=${t} removed`);
  }
  S.timeline.draw();
}

// keys that only move, select or switch modes: the ones left on in review mode
const REVIEW_KEYS = /^(Arrow(Left|Right)|[.,]|Page(Up|Down)|Home|End|[nNvVqQoOzZ0-9]|Escape)$/;

function onKey(e) {
  if (e.target.closest && e.target.closest("input, select, textarea") && e.target.type !== "range" && e.target.type !== "radio") return;
  noteActivity();
  const k = e.key;
  const ctrl = e.ctrlKey || e.metaKey;
  let handled = true;
  if (!$("#review").hidden && (ctrl || !REVIEW_KEYS.test(k))) {
    // review is for looking: a stray key must not edit the frame being reviewed
    if (!["Shift", "Control", "Alt", "Meta"].includes(k)) message("review mode: editing keys are off (V to edit)");
    e.preventDefault();
    return;
  }
  if (ctrl && (k === "z" || k === "Z")) undoRedo(e.shiftKey ? "redo" : "undo");
  else if (ctrl && (k === "y" || k === "Y")) undoRedo("redo");
  else if (ctrl) handled = false;
  else if (k === "ArrowRight" || k === ".") gotoFrame(S.cur + (e.shiftKey ? 10 : 1));
  else if (k === "ArrowLeft" || k === ",") gotoFrame(S.cur - (e.shiftKey ? 10 : 1));
  else if (k === "PageDown") gotoFrame(S.cur + 10);
  else if (k === "PageUp") gotoFrame(S.cur - 10);
  else if (k === "Home") gotoFrame(0);
  else if (k === "End") gotoFrame(S.frames.length - 1);
  else if (k === "n" || k === "N") nextUnfinished();
  else if (k === "b" || k === "B") setTool("box");
  else if (k === "r" || k === "R") setTool("brush");
  else if (k === "e" || k === "E") setTool("eraser");
  else if (k === "g" || k === "G") setTool("polygon");
  else if (k === "a" || k === "A") markAbsent();
  else if (k === "Delete") clearAnnotation();
  else if (k === "Backspace") { if (S.polygon.length) { S.polygon.pop(); render(); } else clearAnnotation(); }
  else if (k === "p") propagate(1);
  else if (k === "P") propagate(-1);
  else if (k === "Enter") { if (S.polygon.length) closePolygon(e.shiftKey); else acceptProposal(); }
  else if (k === "Escape") {
    if (e.shiftKey) discardProposals(true);
    else if (S.polygon.length || S.drag) { cancelInteraction(); render(); }
    else discardProposals(false);
  }
  else if (k === "[") intervalKey("start");
  else if (k === "]") intervalKey("end");
  else if (k === "\\") intervalKey("remove");
  else if (k === "-") setBrush(S.brush - 1);
  else if (k === "=" || k === "+") setBrush(S.brush + 1);
  else if (k === "v" || k === "V") toggleReview();
  else if (k === "z" || k === "Z") resetZoom();
  else if (/^[0-9]$/.test(k)) { const q = S.queries[k === "0" ? 9 : +k - 1]; if (q) selectQuery(q.id); }
  else if (k === "q" || k === "Q") cycleQuery(e.shiftKey ? -1 : 1);
  else if (k === "o" || k === "O") { S.overlayAll = !S.overlayAll; S.overlayDirty = true; render(); }
  else handled = false;
  if (handled) e.preventDefault();
}

// ------------------------------------------------------------------------------------------
// queries, files, review
// ------------------------------------------------------------------------------------------
async function addQuery(ev) {
  ev.preventDefault();
  const text = $("#new-text").value.trim();
  const kind = $("#new-kind").value;
  const base = kind === "sensitive" ? Number($("#new-base").value) : null;
  const level = $("#new-level").value || null;
  if (!(await flushNow())) { message("save pending edits first"); return; }
  try {
    const res = await S.api.post("/api/queries/add", { revision: S.revision, text, kind, base, level });
    mergeState(res.state);
    selectQuery(res.id);
    $("#new-text").value = "";
    message(`added "${text}"`);
  } catch (err) {
    handleWriteError(err, "adding the query");
  }
}

async function deleteQuery() {
  const q = queryById(S.qid);
  if (!q) return;
  if (!window.confirm(`Delete "${q.text}" and all its masks?`)) return;
  if (!(await flushNow())) { message("save pending edits first"); return; }
  try {
    const res = await S.api.post("/api/queries/delete", { revision: S.revision, query: q.id });
    for (const key of [...S.store.keys()]) if (key.startsWith(`${q.id}:`)) S.store.delete(key);
    S.qid = null;
    mergeState(res.state);
    message(`deleted "${q.text}"`);
  } catch (err) {
    handleWriteError(err, "deleting the query");
  }
}

async function markReviewed() {
  const q = queryById(S.qid);
  if (!q || q.review !== "draft") return;
  if (!(await flushNow())) { message("save pending edits first"); return; }
  try {
    const res = await S.api.post("/api/queries/reviewed", { revision: S.revision, query: q.id });
    mergeState(res.state);
    message(`"${q.text}" marked reviewed`);
  } catch (err) {
    handleWriteError(err, "marking the query reviewed");
  }
}

// Take the server's queries and revision, keeping local masks (the server's equal them: all saved).
function mergeState(state) {
  applyState(state);
  S.overlayDirty = true;
  render();
  S.timeline.draw();
}

function handleWriteError(err, what) {
  if (err instanceof HttpError && err.status === 409) { S.conflict = true; $("#conflict").hidden = false; setSaveStatus(); }
  message(`${what} failed: ${err.message}`);
}

async function doExport() {
  if (!(await flushNow())) { message("cannot export: edits not saved"); return; }
  const fmt = $("#export-format").value;
  message(`exporting ${fmt}…`);
  try {
    const res = await S.api.post("/api/export", { format: fmt });
    $("#file-info").textContent = `wrote ${res.files.join(", ")} (checked)`;
    message(`exported ${fmt}`);
  } catch (err) {
    message(`export failed: ${err.message}`);
  }
}

function readAsBase64(file) {
  return new Promise((resolve, reject) => {
    const r = new FileReader();
    r.onload = () => resolve(String(r.result).replace(/^data:[^,]*,/, ""));
    r.onerror = () => reject(r.error);
    r.readAsDataURL(file);
  });
}

async function doImport() {
  const input = $("#import-file");
  const file = input.files && input.files[0];
  if (!file) return;
  const fmt = $("#import-format").value;
  if (!(await flushNow())) { message("cannot import: edits not saved"); input.value = ""; return; }
  message(`importing ${file.name}…`);
  try {
    const data = await readAsBase64(file);
    const res = await S.api.post("/api/import", { revision: S.revision, format: fmt, filename: file.name, data });
    S.store.clear(); S.loaded.clear(); S.history.clear(); S.proposals.clear(); S.assist.clear(); S.pending.clear();
    applyState(res.state);
    await gotoFrame(S.cur);
    $("#file-info").textContent = `imported ${file.name}: ${res.queries} queries, ${res.masks} masks` +
      (res.backup ? ` (previous file kept as ${res.backup})` : "");
    message(`imported ${fmt}`);
  } catch (err) {
    handleWriteError(err, "import");
  } finally {
    input.value = "";
  }
}

function toggleReview(force) {
  const on = force !== undefined ? force : $("#review").hidden;
  $("#review").hidden = !on;
  $("#main").hidden = on;
  $("#mode-toggle").textContent = on ? "Annotate" : "Review";
  if (on) { flushNow().then(() => S.review.refresh()); }
  else { fitCanvas(); render(); S.timeline.draw(); }
}

// ------------------------------------------------------------------------------------------
// start
// ------------------------------------------------------------------------------------------
async function main() {
  const token = readToken();
  S.api = new Api(token);
  if (!token) message("no token: open the address the server printed (edits cannot be saved)");
  applyState(await S.api.get("/api/state"));

  S.timeline = new Timeline($("#timeline"), {
    rows: () => S.queries.filter((q) => q.kind === "sensitive"),
    numSteps: () => S.info.num_time_steps || 1,
    currentTime: () => timeOfFrame(S.cur),
    selected: () => timelineQuery()?.id ?? null,
    select: (qid) => { S.timelineQid = qid; renderQueries(); },
    jump: (t) => {
      const j = S.frames.findIndex((f) => f.time_index >= t && f.camera_id === S.frames[S.cur].camera_id && f.split === S.frames[S.cur].split);
      gotoFrame(j >= 0 ? j : S.frames.findIndex((f) => f.time_index >= t));
    },
    changed: (qid, ivs) => setIntervals(qid, ivs),
    pending: (qid) => (S.pending.has(qid) ? S.pending.get(qid) : null),
    baseMarks: (q) => {
      const d = S.status[q.base] || {};
      return Object.entries(d).map(([i, v]) => [timeOfFrame(+i), v]);
    },
  });
  S.review = new Review($("#review"), {
    api: S.api,
    queries: () => S.queries,
    frames: () => S.frames,
    ownerOf,
    statusOf: (owner, frame) => S.status[owner]?.[frame],
    revision: () => S.revision,
    open: (qid, frame) => { toggleReview(false); selectQuery(qid); gotoFrame(frame); },
  });

  const c = view();
  c.addEventListener("pointerdown", onPointerDown);
  c.addEventListener("pointermove", onPointerMove);
  c.addEventListener("pointerup", onPointerUp);
  c.addEventListener("pointerleave", () => { S.hover = null; render(); });
  c.addEventListener("contextmenu", (e) => e.preventDefault());
  c.addEventListener("dblclick", () => { if (S.tool === "polygon" && S.polygon.length >= 3) closePolygon(false); });
  $("#canvas-wrap").addEventListener("wheel", (e) => {
    if (!e.ctrlKey) return;
    e.preventDefault();
    zoomAt(S.zoom * (e.deltaY < 0 ? 1.25 : 0.8), e.clientX, e.clientY);
  }, { passive: false });
  // the canvas follows its frame's size, not the window's alone: the header or side bar changing
  // height must not resize the image between frames
  new ResizeObserver(() => fitCanvas()).observe($("#canvas-wrap"));
  window.addEventListener("keydown", onKey);
  window.addEventListener("resize", () => { fitCanvas(); S.timeline.draw(); });
  window.addEventListener("beforeunload", (e) => {
    if (isDirty() && !S.leaving) { flush(); e.preventDefault(); e.returnValue = ""; }
  });
  document.addEventListener("visibilitychange", () => { if (document.visibilityState === "hidden") flush(); });

  for (const r of document.querySelectorAll('input[name="tool"]')) r.addEventListener("change", () => setTool(r.value));
  $("#brush-size").addEventListener("input", (e) => setBrush(+e.target.value));
  $("#absent-btn").addEventListener("click", markAbsent);
  $("#clear-btn").addEventListener("click", clearAnnotation);
  $("#undo-btn").addEventListener("click", () => undoRedo("undo"));
  $("#redo-btn").addEventListener("click", () => undoRedo("redo"));
  $("#prop-fwd").addEventListener("click", () => propagate(1));
  $("#prop-back").addEventListener("click", () => propagate(-1));
  $("#accept-btn").addEventListener("click", acceptProposal);
  $("#accept-all-btn").addEventListener("click", acceptAll);
  $("#discard-btn").addEventListener("click", () => discardProposals(true));
  $("#add-query-form").addEventListener("submit", addQuery);
  $("#delete-query").addEventListener("click", deleteQuery);
  $("#mark-reviewed").addEventListener("click", markReviewed);
  $("#export-btn").addEventListener("click", doExport);
  $("#import-file").addEventListener("change", doImport);
  $("#mode-toggle").addEventListener("click", () => toggleReview());
  $("#scrubber").addEventListener("input", (e) => gotoFrame(+e.target.value));
  $("#conflict-reload").addEventListener("click", () => { S.leaving = true; window.location.reload(); });

  const saved = parseInt(sessionStorage.getItem("bench4d-frame") || "0", 10);
  await gotoFrame(Number.isFinite(saved) ? saved : 0);
  S.timeline.draw();
}

// A small handle for scripted sessions and tests (reads state; edits go through the UI).
window.bench4d = {
  S,
  flush: flushNow,
  frame: () => S.cur,
  goto: gotoFrame,
  select: selectQuery,
  maskArea: (qid, frame) => { const e = entry(keyOf(ownerOf(qid), frame)); return e && e.mask ? M.area(e.mask) : null; },
  ready: null,
};
window.bench4d.ready = main().then(() => { document.body.dataset.ready = "1"; }).catch((err) => {
  message(`failed to start: ${err.message}`);
  document.body.dataset.ready = "error";
  throw err;
});
