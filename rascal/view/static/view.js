// rascal view: draws the latest state the server pushed (Server-Sent Events) on requestAnimationFrame,
// and only when something new came.
// Events only replace "latest" values; drawing happens once per animation frame, so however fast
// updates arrive the page never builds a backlog. window.rascalView exposes what tests check.
"use strict";

const SENSOR_COLOURS = {
  lidar_h_left: "#ff9f1c", lidar_h_right: "#ffd166", lidar_v_left: "#c77dff", lidar_v_right: "#e0aaff",
  esvs: "#4cc9f0", sim: "#f72585", synthetic: "#adb5bd", unknown: "#ffffff",
};
const canvas = document.getElementById("map");
const ctx = canvas.getContext("2d");
const latest = { course: null, scene: null, trail: [], health: null };
const stats = {
  connected: false, events: 0, frames: 0,
  mapReceived: 0, mapDecoded: 0, mapRendered: 0, mapSkippedByServer: 0,
  mapLatestSeq: 0, mapRenderedSeq: 0, mapRenderedIndex: 0, backlog: 0, maxBacklog: 0, lastRenderLagMs: null, maxRenderLagMs: 0, lastDecodeMs: null,
  vehiclePx: null, vehicleWorld: null, modules: [], follow: false, errors: [],
};
window.rascalView = stats;
function noteError(text) { if (stats.errors.length < 20) stats.errors.push(String(text)); }
window.addEventListener("error", (e) => noteError(e.message));
window.addEventListener("unhandledrejection", (e) => noteError(e.reason));

// -- the map: inflate (zlib = "deflate" for DecompressionStream) into an off-screen bitmap ----------
const LUT = new Uint32Array(256); // probability x 255 -> RGBA packed as the platform's bytes
const LUT_BYTES = new Uint8ClampedArray(LUT.buffer);
for (let v = 0; v < 256; v++) {
  const p = v / 255;
  if (p > 0.55) LUT_BYTES.set([235, 50, 40, Math.round(255 * Math.min(1, (p - 0.55) / 0.35))], v * 4);
  else if (p < 0.45) LUT_BYTES.set([70, 170, 90, Math.round(90 * (0.45 - p) / 0.45)], v * 4);
}
let dirty = true; // something new to draw: frames with nothing new cost nothing
let mapImage = null; // {canvas, seq, received, origin_e, origin_n, res, rows, cols}
let mapDecoding = false;
let mapPending = null; // only the newest undecoded snapshot is kept

async function inflate(b64) {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

async function decodeMaps() {
  mapDecoding = true;
  while (mapPending) {
    const snap = mapPending;
    mapPending = null;
    const started = performance.now();
    try {
      const cells = await inflate(snap.zlib_b64);
      if (cells.length !== snap.rows * snap.cols) throw new Error("map size mismatch");
      const image = new ImageData(snap.cols, snap.rows);
      const pixels = new Uint32Array(image.data.buffer);
      for (let r = 0; r < snap.rows; r++) { // row 0 is south: flip so north is up in the bitmap
        const src = r * snap.cols, dst = (snap.rows - 1 - r) * snap.cols;
        for (let c = 0; c < snap.cols; c++) pixels[dst + c] = LUT[cells[src + c]];
      }
      const bitmap = document.createElement("canvas");
      bitmap.width = snap.cols; bitmap.height = snap.rows;
      bitmap.getContext("2d").putImageData(image, 0, 0);
      mapImage = { ...snap, canvas: bitmap, zlib_b64: null };
      dirty = true;
      stats.mapDecoded++;
      stats.lastDecodeMs = Math.round(performance.now() - started);
    } catch (err) {
      noteError(`map snapshot ${snap.seq}: ${err}`);
    }
  }
  mapDecoding = false;
}

function onMap(snap) {
  stats.mapReceived++;
  if (stats.mapLatestSeq && snap.seq > stats.mapLatestSeq + 1) stats.mapSkippedByServer += snap.seq - stats.mapLatestSeq - 1;
  stats.mapLatestSeq = snap.seq;
  snap.received = performance.now();
  snap.index = stats.mapReceived; // the backlog counts maps received since the one drawn
  mapPending = snap;
  if (!mapDecoding) decodeMaps();
}

// -- events -------------------------------------------------------------------------------------
function connect() {
  const source = new EventSource("events");
  source.onopen = () => { stats.connected = true; document.getElementById("conn").textContent = "connected"; };
  source.onerror = () => { stats.connected = false; document.getElementById("conn").textContent = "reconnecting…"; };
  const on = (name, fn) => source.addEventListener(name, (e) => { stats.events++; dirty = true; fn(JSON.parse(e.data)); });
  on("course", (c) => { latest.course = c; document.getElementById("conn").textContent = c.source; });
  on("scene", (s) => { latest.scene = s; });
  on("trail", (t) => { latest.trail = t; });
  on("health", (h) => { latest.health = h; renderHealth(h); });
  on("map", (m) => { if (m) onMap(m); });
}

// -- world to screen ----------------------------------------------------------------------------
let view = { cx: 0, cy: 0, scale: 4 };

function fitView() {
  const w = canvas.width, h = canvas.height;
  const v = latest.scene && latest.scene.vehicle;
  const pts = latest.course && latest.course.waypoints.length ? latest.course.waypoints : null;
  if (stats.follow || !pts) {
    if (v) view = { cx: v.e, cy: v.n, scale: 5 };
    return;
  }
  const pad = Math.max(...latest.course.half_widths_m, 5) + 10;
  const es = pts.map((p) => p[0]), ns = pts.map((p) => p[1]);
  const minE = Math.min(...es) - pad, maxE = Math.max(...es) + pad, minN = Math.min(...ns) - pad, maxN = Math.max(...ns) + pad;
  view = { cx: (minE + maxE) / 2, cy: (minN + maxN) / 2, scale: Math.min(w / (maxE - minE), h / (maxN - minN)) };
}

function toScreen(e, n) {
  return [canvas.width / 2 + (e - view.cx) * view.scale, canvas.height / 2 - (n - view.cy) * view.scale];
}

function polyline(points, colour, width, dash) {
  if (!points || points.length < 2) return;
  ctx.beginPath();
  points.forEach((p, i) => { const [x, y] = toScreen(p[0], p[1]); i ? ctx.lineTo(x, y) : ctx.moveTo(x, y); });
  ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.setLineDash(dash || []); ctx.stroke(); ctx.setLineDash([]);
}

// -- drawing ------------------------------------------------------------------------------------
function drawCourse(course) {
  const pts = course.waypoints;
  ctx.lineCap = "round"; ctx.lineJoin = "round";
  for (let i = 0; i + 1 < pts.length; i++) { // each segment's band: a capsule of its half width
    const [x0, y0] = toScreen(pts[i][0], pts[i][1]), [x1, y1] = toScreen(pts[i + 1][0], pts[i + 1][1]);
    ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1);
    ctx.strokeStyle = "#2f3a46"; ctx.lineWidth = Math.max(2, 2 * course.half_widths_m[i] * view.scale); ctx.stroke();
  }
  polyline(pts, "#5c6b7a", 1, [4, 4]);
}

function drawMap() {
  if (!mapImage) return;
  const m = mapImage;
  const [x, y] = toScreen(m.origin_e, m.origin_n + m.rows * m.res); // the bitmap's top-left is its north-west corner
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(m.canvas, x, y, m.cols * m.res * view.scale, m.rows * m.res * view.scale);
  if (m.seq !== stats.mapRenderedSeq) {
    stats.mapRendered++;
    stats.mapRenderedSeq = m.seq;
    stats.mapRenderedIndex = m.index;
    stats.lastRenderLagMs = Math.round(performance.now() - m.received);
    stats.maxRenderLagMs = Math.max(stats.maxRenderLagMs, stats.lastRenderLagMs);
  }
}

function drawObstacles(bySensor) {
  for (const [sensor, boxes] of Object.entries(bySensor)) {
    ctx.strokeStyle = SENSOR_COLOURS[sensor] || "#fff"; ctx.lineWidth = 1.5;
    for (const b of boxes) {
      const [x, y] = toScreen(b.e, b.n);
      ctx.save(); ctx.translate(x, y); ctx.rotate(-b.yaw);
      const l = Math.max(2, b.l * view.scale), w = Math.max(2, b.w * view.scale);
      ctx.strokeRect(-l / 2, -w / 2, l, w); ctx.restore();
    }
  }
}

function drawVehicle(v) {
  const [x, y] = toScreen(v.e, v.n);
  const size = Math.max(6, 2.5 * view.scale);
  ctx.save(); ctx.translate(x, y); ctx.rotate(-v.yaw);
  ctx.beginPath(); ctx.moveTo(size, 0); ctx.lineTo(-size * 0.6, size * 0.5); ctx.lineTo(-size * 0.6, -size * 0.5); ctx.closePath();
  ctx.fillStyle = "#fafafa"; ctx.fill(); ctx.strokeStyle = "#000"; ctx.lineWidth = 1; ctx.stroke(); ctx.restore();
  stats.vehiclePx = [Math.round(x * 10) / 10, Math.round(y * 10) / 10];
  stats.vehicleWorld = [v.e, v.n];
}

function render() {
  requestAnimationFrame(render);
  const rect = canvas.getBoundingClientRect();
  if (canvas.width !== Math.round(rect.width) || canvas.height !== Math.round(rect.height)) {
    canvas.width = Math.round(rect.width); canvas.height = Math.round(rect.height);
    dirty = true;
  }
  if (!dirty) return;
  dirty = false;
  fitView();
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const scene = latest.scene;
  if (latest.course) drawCourse(latest.course);
  drawMap();
  polyline(latest.trail, "#8d99ae", 1.5);
  if (scene) {
    for (const lines of Object.values(scene.lanes)) lines.forEach((line) => polyline(line, "#f4d35e", 1.5, [6, 4]));
    polyline(scene.path, scene.slow ? "#ff8fab" : "#48cae4", 2);
    drawObstacles(scene.obstacles);
    if (scene.vehicle) drawVehicle(scene.vehicle);
    document.getElementById("clock").textContent = scene.vehicle
      ? `t ${scene.t_s.toFixed(1)} s · ${scene.vehicle.speed.toFixed(1)} m/s` : `t ${scene.t_s.toFixed(1)} s · no vehicle state`;
  }
  stats.frames++;
  stats.backlog = stats.mapReceived - stats.mapRenderedIndex;
  if (stats.mapRendered) stats.maxBacklog = Math.max(stats.maxBacklog, stats.backlog);
  if (stats.frames % 15 === 0) {
    document.getElementById("viewstats").textContent =
      `maps received ${stats.mapReceived}, rendered ${stats.mapRendered}, skipped by server ${stats.mapSkippedByServer}, ` +
      `backlog ${stats.backlog} (max ${stats.maxBacklog}), last render lag ${stats.lastRenderLagMs} ms, decode ${stats.lastDecodeMs} ms`;
    document.getElementById("status").textContent = JSON.stringify(stats);
  }
}

// -- the health panel ---------------------------------------------------------------------------
function cell(row, text, cls) { const td = row.insertCell(); td.textContent = text; if (cls) td.className = cls; return td; }

function renderHealth(h) {
  const body = document.querySelector("#modules tbody");
  body.replaceChildren();
  for (const m of h.modules) {
    const row = body.insertRow();
    row.title = m.detail; row.dataset.module = m.name;
    cell(row, m.name);
    cell(row, m.age_s > 3 ? "SILENT" : m.state, m.age_s > 3 ? "silent" : m.state);
    cell(row, m.age_s.toFixed(1)); cell(row, m.loop_hz); cell(row, m.jitter_ms.toFixed(1)); cell(row, m.overruns);
    cell(row, m.restarts, m.restarts ? "WARNING" : ""); cell(row, m.rx_rejected, m.rx_rejected ? "WARNING" : "");
    cell(row, m.stale.join(", "), "l" + (m.stale.length ? " WARNING" : ""));
  }
  stats.modules = h.modules.map((m) => m.name);
  const rejected = Object.entries(h.rejected).map(([k, v]) => `${k} ${v}`).join(", ");
  const undrawable = Object.entries(h.undrawable).map(([k, v]) => `${k} ${v}`).join(", ");
  document.getElementById("rejected").textContent = (rejected || "none") + (undrawable ? `; not drawn: ${undrawable}` : "");
  const events = document.getElementById("events");
  events.replaceChildren(...h.events.slice().reverse().map((e) => {
    const div = document.createElement("div");
    div.className = e.severity; div.textContent = `${e.t_s.toFixed(1)} ${e.severity} ${e.module}: ${e.code} ${e.text}`;
    div.title = div.textContent; return div;
  }));
  const rates = document.querySelector("#rates tbody");
  rates.replaceChildren();
  for (const [name, hz] of Object.entries(h.rates_hz)) { const row = rates.insertRow(); cell(row, name); cell(row, hz); }
}

function legend() {
  document.getElementById("legend").innerHTML = Object.entries(SENSOR_COLOURS)
    .map(([name, colour]) => `<span><i style="background:${colour}"></i>${name}</span>`).join("") +
    '<span><i style="background:#48cae4"></i>path</span><span><i style="background:#f4d35e"></i>lane borders</span>' +
    '<span><i style="background:#eb3228"></i>hazard</span>';
}

function toggleFollow() {
  stats.follow = !stats.follow;
  dirty = true;
  document.getElementById("follow").textContent = stats.follow ? "fit course" : "follow";
}
document.getElementById("follow").onclick = toggleFollow;
document.addEventListener("keydown", (e) => { if (e.key === "f") toggleFollow(); });
legend();
connect();
requestAnimationFrame(render);
