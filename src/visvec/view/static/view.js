// visvec live view: polls /api/state for the rows and /frame.jpg for the picture.
// Everything shown comes from the sensor's rows; the page only keeps the last 60 s.
"use strict";

const WINDOW_S = 60;
const STATE_EVERY_MS = 250;
const FRAME_EVERY_MS = 100;
const $ = (id) => document.getElementById(id);

let seq = 0;
let info = null;
let cols = null;            // {values: [...], sigmas: [...]}
const data = { t: [], v: [], s: [], ft: [], fv: [] };  // rows, and fused rows
let plots = [];
let lastPlot = 0;

function unit(col) {
  if (col.endsWith("_deg")) return "deg";
  if (col.endsWith("_mm")) return "mm";
  if (col.endsWith("_dps")) return "deg/s";
  return "";
}
function label(col) { return col.replace(/_(deg|mm|dps)$/, ""); }
function pct(x, digits) { return x == null ? "–" : (100 * x).toFixed(digits) + " %"; }

function setupPlots() {
  const box = $("plots");
  box.innerHTML = "";
  plots = cols.values.map((c, i) => {
    const div = document.createElement("div");
    div.className = "plot";
    div.dataset.col = c;
    box.appendChild(div);
    const series = [
      {},
      { label: label(c), stroke: "#1f5fbf", width: 1.5, spanGaps: false },
      { label: "-1σ", stroke: "rgba(31,95,191,0)", points: { show: false } },
      { label: "+1σ", stroke: "rgba(31,95,191,0)", points: { show: false } },
      { label: "fused", stroke: "#d0611f", width: 1.5, spanGaps: true },
    ];
    const opts = {
      width: Math.max(box.clientWidth - 8, 300), height: 170,
      series, legend: { show: false },
      bands: [{ series: [3, 2], fill: "rgba(31,95,191,0.18)" }],
      // the y range from the values shown (uPlot's own takes an empty series as 0)
      scales: { x: { time: false }, y: { range: yRange } },
      axes: [
        { label: "time (s)", size: 36 },
        { label: label(c) + " (" + unit(c) + ")", size: 78, space: 16,
          values: (u, vals) => vals.map((v) => (v == null ? "" : String(+v.toPrecision(6)))) },
      ],
      cursor: { show: false },
    };
    return new uPlot(opts, [[], [], [], [], []], div);
  });
}

function yRange(u) {
  let lo = Infinity, hi = -Infinity;
  for (let k = 1; k < u.data.length; k++) {
    for (const y of u.data[k]) if (y != null) { if (y < lo) lo = y; if (y > hi) hi = y; }
  }
  if (lo > hi) return [-1, 1];
  const pad = Math.max((hi - lo) * 0.08, Math.abs(hi) * 1e-6, 1e-6);
  return [lo - pad, hi + pad];
}

function trim(t, arrays) {
  if (!t.length) return;
  const from = t[t.length - 1] - WINDOW_S;
  let k = 0;
  while (k < t.length && t[k] < from) k++;
  if (k) { t.splice(0, k); for (const a of arrays) for (const b of a) b.splice(0, k); }
}

// the rows' own time; with fused rows (camera and IMU on their own clocks), the time at
// which the sensor made each row
function when(r) { return hostClock ? r._host_s : r.time_s; }
let hostClock = false;

function addRows(rows, fused) {
  if (fused.length && !hostClock) {
    hostClock = true;
    data.t = []; data.v = cols.values.map(() => []); data.s = cols.values.map(() => []);
  }
  for (const r of rows) {
    if (data.t.length && when(r) < data.t[data.t.length - 1]) {  // a new run's clock
      data.t = []; data.v = cols.values.map(() => []); data.s = cols.values.map(() => []);
    }
    data.t.push(when(r));
    cols.values.forEach((c, i) => {
      data.v[i].push(r[c]);
      const s = r[cols.sigmas[i]];
      data.s[i].push(r[c] == null || s == null ? null : s);
    });
  }
  if (fused.length) $("fusedkey").textContent = "; orange: fused with the IMU";
  for (const r of fused) {
    data.ft.push(when(r));
    cols.values.forEach((c, i) => data.fv[i].push(r[c]));
  }
  trim(data.t, [data.v, data.s]);
  trim(data.ft, [data.fv]);
}

// yaw and heading wrap at +-180 deg: plotted unwrapped, so a turn through 180 is a
// line, not a jump across the plot (the table shows the rows' own values)
function unwrapped(col, v) {
  if (col !== "yaw_deg" && col !== "heading_deg") return v;
  let off = 0, prev = null;
  return v.map((y) => {
    if (y == null) return null;
    if (prev != null) {
      const d = y + off - prev;
      if (d > 180) off -= 360; else if (d < -180) off += 360;
    }
    prev = y + off;
    return prev;
  });
}

function redraw() {
  const n = data.t.length;
  document.body.dataset.points = String(n);
  plots.forEach((u, i) => {
    // rows and fused rows on one time axis: each series null where it has no row
    let x, v, lo, hi, f;
    if (!data.ft.length) {
      x = data.t; v = unwrapped(cols.values[i], data.v[i]);
      lo = v.map((y, k) => (y == null || data.s[i][k] == null ? null : y - data.s[i][k]));
      hi = v.map((y, k) => (y == null || data.s[i][k] == null ? null : y + data.s[i][k]));
      f = x.map(() => null);
    } else {
      const merged = [];
      data.t.forEach((t, k) => merged.push([t, data.v[i][k], data.s[i][k], null]));
      data.ft.forEach((t, k) => merged.push([t, null, null, data.fv[i][k]]));
      merged.sort((a, b) => a[0] - b[0]);
      x = merged.map((m) => m[0]); v = unwrapped(cols.values[i], merged.map((m) => m[1]));
      lo = v.map((y, k) => (y == null || merged[k][2] == null ? null : y - merged[k][2]));
      hi = v.map((y, k) => (y == null || merged[k][2] == null ? null : y + merged[k][2]));
      f = unwrapped(cols.values[i], merged.map((m) => m[3]));
    }
    u.setData([x, v, lo, hi, f]);
  });
}

function showLast(st) {
  const last = st.last;
  const el = $("status");
  if (!last) return;
  el.textContent = last.words;
  el.className = "status " + (last.status === "ok" ? "ok" : "notok");
  el.dataset.status = last.status;
  const body = $("values").tBodies[0];
  body.innerHTML = "";
  cols.values.forEach((c, i) => {
    const tr = body.insertRow();
    tr.dataset.col = c;
    const v = last[c], s = last[cols.sigmas[i]];
    tr.insertCell().textContent = label(c);
    const tv = tr.insertCell(); tv.className = "v"; tv.textContent = v == null ? "–" : String(v);
    const ts = tr.insertCell(); ts.className = "s";
    ts.textContent = s == null ? "" : "± " + String(s) + " " + unit(c);
  });
  $("rowframe").textContent = String(last.frame) + " at " + last.time_s.toFixed(3) + " s";
  const run = st.run;
  $("rows").textContent = String(run.rows);
  $("okshare").textContent = pct(run.ok_share, 1) + " (" + run.ok + ")";
  $("rate").textContent = run.rows_per_s == null ? "–" : run.rows_per_s.toFixed(1);
  $("latency").textContent = run.latency_ms == null ? "–" : run.latency_ms.toFixed(2) + " ms (median)";
}

function showAids(a) {
  if (!a) return;
  const c = $("hist"), g = c.getContext("2d");
  const w = c.width, h = c.height, n = a.histogram.length;
  g.clearRect(0, 0, w, h);
  const top = Math.max(...a.histogram, 1e-9);
  a.histogram.forEach((y, k) => {
    g.fillStyle = k === n - 1 && a.clipped > 0.001 ? "#c62828" : "#4a5875";
    const bh = Math.sqrt(y / top) * (h - 4);   // square root: the small bins stay visible
    g.fillRect((k * w) / n, h - bh, w / n - 1, bh);
  });
  const clip = $("clipped");
  clip.textContent = pct(a.clipped, 2);
  clip.className = a.clipped > 0.001 ? "warn" : "";
  $("dark").textContent = pct(a.dark, 2);
  $("sharpness").textContent = a.sharpness == null ? "no target" :
    a.sharpness.toFixed(3) + " /px (higher is sharper: focus for the largest)";
  const m = $("margin");
  if (a.margin_px == null) { m.textContent = "no target found"; m.className = "warn"; }
  else {
    m.textContent = (a.margin_px >= 0 ? "yes, " : "no, ") + a.points + " points; the nearest " +
      Math.abs(a.margin_px).toFixed(0) + " px " + (a.margin_px >= 0 ? "inside" : "outside") + " the border";
    m.className = a.margin_px < 10 ? "warn" : "";
  }
}

async function poll() {
  try {
    const r = await fetch("/api/state?since=" + seq, { cache: "no-store" });
    const st = await r.json();
    if (!cols) {
      cols = { values: st.values, sigmas: st.sigmas };
      data.v = cols.values.map(() => []); data.s = cols.values.map(() => []);
      data.fv = cols.values.map(() => []);
      setupPlots();
    }
    if (st.seq < seq) { seq = 0; }  // the sensor restarted
    seq = st.seq;
    addRows(st.history, st.fused);
    showLast(st);
    showAids(st.aids);
    const now = performance.now();
    if (now - lastPlot > 500) { redraw(); lastPlot = now; }
    const pill = $("runstate");
    pill.textContent = st.run.ended ? "run ended" : "live";
    pill.className = "pill " + (st.run.ended ? "ended" : "live");
    if (!info || info.join("\n") !== st.info.join("\n")) {
      info = st.info;
      $("info").innerHTML = "";
      for (const line of info) { const li = document.createElement("li"); li.textContent = line; $("info").appendChild(li); }
    }
    setTimeout(poll, st.run.ended ? 1000 : STATE_EVERY_MS);
  } catch (e) {
    const pill = $("runstate");
    pill.textContent = "sensor not answering"; pill.className = "pill lost";
    setTimeout(poll, 1000);
  }
}

let frameUrl = null;
async function frameLoop() {
  const t0 = performance.now();
  let wait = FRAME_EVERY_MS;
  try {
    const r = await fetch("/frame.jpg", { cache: "no-store" });
    if (r.status === 200) {
      const f = r.headers.get("X-Visvec-Frame");
      const blob = await r.blob();
      const url = URL.createObjectURL(blob);
      const img = $("frame");
      const old = frameUrl;
      img.onload = () => { if (old) URL.revokeObjectURL(old); };
      img.src = url; frameUrl = url;
      $("framecap").textContent = "frame " + f;
      document.body.dataset.frame = f;
    }
  } catch (e) { wait = 1000; }
  setTimeout(frameLoop, Math.max(wait - (performance.now() - t0), 20));
}

window.addEventListener("resize", () => {
  const w = Math.max($("plots").clientWidth - 8, 300);
  plots.forEach((u) => u.setSize({ width: w, height: 170 }));
});
poll();
frameLoop();
