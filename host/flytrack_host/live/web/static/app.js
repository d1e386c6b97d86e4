// FlyTrack live page: one EventSource on ui/events ("state" events, ~20 Hz), drawn on canvases.
// No libraries: the page must work on a lab PC without internet.
"use strict";
const COLORS = ["#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#42d4f4", "#f032e6", "#9a6324",
                "#469990", "#800000", "#808000", "#000075"];
const color = (id) => COLORS[id % COLORS.length];
const $ = (id) => document.getElementById(id);
// What the tests read: the last state, update times, and how much the page lags the tracker.
window.flytrack = { last: null, updates: 0, updateTimes: [], delays: [], drawnSegments: 0, ended: false };
let bounds = null; // world bounds of everything drawn so far (only grows: a steady picture)

function grow(p) {
  if (p[0] === null || p[1] === null || p[2] === null) return;
  if (!bounds) bounds = { min: [...p], max: [...p] };
  for (let i = 0; i < 3; i++) { bounds.min[i] = Math.min(bounds.min[i], p[i]); bounds.max[i] = Math.max(bounds.max[i], p[i]); }
}

function drawView(canvas, tracks, ax, ay, labels) {
  const g = canvas.getContext("2d"), W = canvas.width, H = canvas.height, pad = 28;
  g.clearRect(0, 0, W, H);
  g.strokeStyle = "#d9dee4"; g.strokeRect(pad, 4, W - pad - 4, H - pad - 4);
  if (!bounds) { g.fillStyle = "#9aa5b1"; g.fillText("no tracks yet", W / 2 - 30, H / 2); return 0; }
  // One scale for both axes so distances look right; a 5 cm minimum span.
  const cx = (bounds.min[ax] + bounds.max[ax]) / 2, cy = (bounds.min[ay] + bounds.max[ay]) / 2;
  const span = Math.max(bounds.max[ax] - bounds.min[ax], bounds.max[ay] - bounds.min[ay], 0.05) * 1.15;
  const s = Math.min(W - pad - 8, H - pad - 8) / span;
  const X = (v) => pad + (W - pad - 4) / 2 + (v - cx) * s, Y = (v) => 4 + (H - pad - 4) / 2 - (v - cy) * s;
  g.fillStyle = "#52606d";
  g.fillText(`${labels[0]} (m)  span ${span.toFixed(2)} m`, pad + 4, H - 8);
  g.save(); g.translate(11, H / 2); g.rotate(-Math.PI / 2); g.fillText(`${labels[1]} (m)`, 0, 0); g.restore();
  let segs = 0;
  for (const t of tracks) {
    const pts = t.trail.filter((p) => p[ax] !== null && p[ay] !== null);
    if (!pts.length) continue;
    g.strokeStyle = color(t.id); g.globalAlpha = t.live ? 1 : 0.35; g.lineWidth = 2;
    g.beginPath();
    pts.forEach((p, i) => (i ? g.lineTo(X(p[ax]), Y(p[ay])) : g.moveTo(X(p[ax]), Y(p[ay]))));
    g.stroke(); segs += pts.length - 1;
    const last = pts[pts.length - 1];
    g.fillStyle = color(t.id); g.beginPath(); g.arc(X(last[ax]), Y(last[ay]), 5, 0, 2 * Math.PI); g.fill();
    g.fillText(String(t.id), X(last[ax]) + 7, Y(last[ay]) - 7);
  }
  g.globalAlpha = 1;
  return segs;
}

function drawHist(lat) {
  const c = $("hist"), g = c.getContext("2d"), W = c.width, H = c.height;
  g.clearRect(0, 0, W, H);
  if (!lat || !lat.counts || !lat.counts.length) return;
  const n = lat.counts.length, max = Math.max(...lat.counts, 1), bw = (W - 40) / n;
  g.fillStyle = "#4363d8";
  lat.counts.forEach((v, i) => { const h = (H - 30) * v / max; g.fillRect(30 + i * bw, H - 20 - h, Math.max(bw - 1, 1), h); });
  g.fillStyle = "#52606d";
  g.fillText("0", 30, H - 6); g.fillText(`${(n * lat.bin_ms).toFixed(1)} ms`, W - 50, H - 6);
  g.fillText(`n ${lat.n}` + (lat.beyond ? `, ${lat.beyond} beyond` : ""), W - 130, 12);
}

function tile(cam) {
  let el = document.querySelector(`.tile[data-index="${cam.index}"]`);
  if (!el) {
    el = document.createElement("div");
    el.className = "tile"; el.dataset.index = cam.index;
    el.innerHTML = `<h3><span class="name"></span><span class="state"></span></h3>
      <div class="nums"><span>fps <b class="fps"></b></span><span>rx <b class="rx"></b></span>
      <span>lost <b class="lost"></b></span><span>late <b class="late"></b></span>
      <span>latency <b class="latency"></b></span><span>points <b class="npts"></b></span></div>
      <canvas width="160" height="120"></canvas><img class="thumbimg" alt="" hidden><div class="thumb"></div>`;
    $("cameras").appendChild(el);
  }
  el.classList.toggle("dead", !cam.alive);
  const set = (sel, v) => { el.querySelector(sel).textContent = v; };
  set(".name", cam.name); set(".state", cam.alive ? "alive" : "DEAD");
  set(".fps", cam.fps === null ? "-" : cam.fps.toFixed(1)); set(".rx", cam.rx);
  set(".lost", cam.lost); set(".late", cam.late);
  set(".latency", cam.latency_ms === null ? "-" : `${cam.latency_ms.toFixed(1)} ms`); set(".npts", cam.n_points);
  const img = el.querySelector(".thumbimg");
  if (cam.thumbnail) {
    const src = `thumb/${cam.index}.png?id=${cam.thumbnail.id}`;
    if (img.getAttribute("src") !== src) img.setAttribute("src", src);
    img.hidden = false;
    set(".thumb", `image of camera frame ${cam.thumbnail.camera_frame}, ${cam.thumbnail.age_s} s ago`);
  } else {
    set(".thumb", "no image from this edge");
  }
  const c = el.querySelector("canvas"), g = c.getContext("2d");
  g.fillStyle = "#111"; g.fillRect(0, 0, c.width, c.height);
  const sx = c.width / (cam.width || 640), sy = c.height / (cam.height || 480);
  g.fillStyle = "#7CFC00";
  for (const p of cam.points) { if (p[0] !== null && p[1] !== null) g.fillRect(p[0] * sx - 2, p[1] * sy - 2, 4, 4); }
}

function render(s) {
  const f = window.flytrack;
  f.last = s; f.updates += 1;
  const now = Date.now() / 1000;
  f.updateTimes.push(now); if (f.updateTimes.length > 600) f.updateTimes.shift();
  // The page's delay: from the newest frame's estimate to now, counted when a new frame arrived.
  if (s.last_estimate_time && (!f.prev || s.frame !== f.prev.frame)) {
    f.delays.push(now - (s.last_estimate_time + (s.wall_offset || 0))); if (f.delays.length > 600) f.delays.shift();
  }
  f.prev = s;
  $("rig").textContent = s.rig || "";
  $("frame").textContent = s.frame;
  $("frames-tracked").textContent = s.frames_tracked ?? s.frames_published;
  $("objects").textContent = s.objects;
  $("births").textContent = `${s.births} / ${s.deaths}`;
  const lat = s.latency || {};
  $("lat").textContent = lat.p50_ms != null ? `${lat.p50_ms.toFixed(2)} / ${lat.p99_ms.toFixed(2)} ms` : "-";
  const d = f.delays.slice(-20).sort((a, b) => a - b);
  $("delay").textContent = d.length ? `${(1000 * d[d.length >> 1]).toFixed(0)} ms` : "-";
  for (const t of s.tracks) for (const p of t.trail) grow(p);
  f.drawnSegments = drawView($("top"), s.tracks, 0, 1, ["x", "y"]) + drawView($("side"), s.tracks, 0, 2, ["x", "z"]);
  drawHist(s.latency);
  for (const cam of s.cameras || []) tile(cam);
  const r = s.recording || {};
  const disk = r.disk || {};
  $("recording").textContent = r.on
    ? `recording to ${r.path}\n${r.status || ""}\nfree disk ${disk.free_gb ?? "?"} of ${disk.total_gb ?? "?"} GB`
    : `not recording${disk.free_gb != null ? `; free disk ${disk.free_gb} GB` : ""}`;
  $("trigger").textContent = (s.trigger && s.trigger.length) ? s.trigger.join("\n") : "no trigger status";
  const sv = s.server || {};
  $("server").textContent = `clients ${sv.clients ?? 0} (${JSON.stringify(sv.clients_by_kind || {})}), ` +
    `dropped slow ${sv.clients_dropped_slow ?? 0}, frames published ${sv.frames_published ?? 0}`;
  const rules = [...(s.rules_fired || []), ...(s.rules || [])];
  $("rules").textContent = rules.length ? rules.join("\n") : "none yet";
  $("log").textContent = (s.log || []).join("\n");
}

function connect() {
  const es = new EventSource("ui/events");
  es.addEventListener("state", (e) => {
    const s = JSON.parse(e.data);
    render(s);
    const conn = $("conn");
    if (s.final) { es.close(); window.flytrack.ended = true; conn.textContent = "run ended"; conn.className = "conn done"; }
    else { conn.textContent = "live"; conn.className = "conn ok"; }
  });
  es.onerror = () => { if (!window.flytrack.ended) { $("conn").textContent = "disconnected, retrying"; $("conn").className = "conn bad"; } };
}
connect();
