// hdrcap serve: live updates of the server-rendered pages (no framework, nothing loaded from elsewhere).
"use strict";

const page = document.body.dataset.page;
const enc = encodeURIComponent;

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === "class") node.className = v;
    else node.setAttribute(k, v);
  }
  for (const c of children) node.append(c instanceof Node ? c : document.createTextNode(c === null || c === undefined ? "" : String(c)));
  return node;
}

function fmtTime(t) {
  return t ? el("time", { datetime: t }, t.slice(0, 19).replace("T", " ")) : "–";
}

function fmtNum(v, digits) {
  if (v === null || v === undefined) return "–";
  return Number(v).toFixed(digits);
}

function fmtSig(v) {
  if (v === null || v === undefined) return "–";
  return Number(v).toPrecision(4);
}

function stateBadge(r) {
  const code = r.exit_code === null || r.exit_code === undefined ? "" : ` (${r.exit_code})`;
  return el("span", { class: `state ${r.state}` }, r.state + code);
}

function framesCell(r) {
  const span = el("span", {}, el("span", { class: "frames" }, r.frames_planned === null ? `${r.frames_done}` : `${r.frames_done} / ${r.frames_planned}`));
  if (r.frames_planned) span.append(el("progress", { max: r.frames_planned, value: r.frames_done }));
  return span;
}

function showLive(on) {
  const live = document.getElementById("live");
  if (live) live.hidden = !on;
}

// ------------------------------------------------------------------ the runs list
function runRow(r) {
  const name = el("td", {}, el("a", { href: `/runs/${enc(r.name)}` }, r.name));
  if (r.job) name.append(el("div", { class: "sub" }, r.job));
  return el(
    "tr",
    { class: r.state },
    name,
    el("td", {}, stateBadge(r)),
    el("td", {}, fmtTime(r.started)),
    el("td", {}, framesCell(r)),
    el("td", { class: "num" }, fmtNum(r.target_snr_db, 1)),
    el("td", { class: "num" }, fmtNum(r.predicted_snr_db, 1)),
    el("td", { class: "num" }, fmtNum(r.achieved_snr_db, 1)),
    el("td", { class: "message" }, r.message || ""),
  );
}

function runsPage() {
  const body = document.getElementById("runs-body");
  const { limit, offset } = document.body.dataset;
  const source = new EventSource(`/api/stream?limit=${enc(limit)}&offset=${enc(offset)}`);
  source.onopen = () => showLive(true);
  source.onerror = () => showLive(false);
  source.addEventListener("runs", (msg) => {
    const data = JSON.parse(msg.data);
    body.replaceChildren(...data.runs.map(runRow));
    if (!data.runs.length) body.append(el("tr", { class: "empty" }, el("td", { colspan: 8 }, "No run folder yet.")));
    document.getElementById("total").textContent = `${data.total} run${data.total === 1 ? "" : "s"}`;
  });
}

// ------------------------------------------------------------------ one run
const MAX_EVENT_ROWS = 500;

function eventDetails(e) {
  const skip = new Set(["time", "event"]);
  if (e.event === "frame") return `${e.done} / ${e.total} ${e.key || ""}${e.eta_s !== null && e.eta_s !== undefined ? `, ${Number(e.eta_s).toFixed(1)} s left` : ""}`;
  if (e.event === "stop") return `exit ${e.exit_code}: ${e.reason}`;
  const parts = [];
  for (const [k, v] of Object.entries(e)) {
    if (skip.has(k)) continue;
    const text = typeof v === "object" && v !== null ? JSON.stringify(v) : String(v);
    parts.push(`${k}: ${text.length > 160 ? text.slice(0, 157) + "…" : text}`);
  }
  return parts.join("; ");
}

async function refreshRun(name) {
  const res = await fetch(`/api/runs/${enc(name)}`, { headers: { Accept: "application/json" } });
  if (!res.ok) return;
  const r = await res.json();
  document.getElementById("run-state").replaceChildren(stateBadge(r));
  document.getElementById("run-frames").replaceChildren(framesCell(r));
  document.getElementById("run-message").textContent = r.message || "–";
  document.getElementById("run-updated").replaceChildren(fmtTime(r.updated));
  const images = document.getElementById("images");
  const have = new Set([...images.querySelectorAll("img")].map((i) => i.dataset.kind));
  const captions = {
    preview: "tone-mapped preview (for looking at only)",
    snr: "SNR, dB: 20 log10(irradiance / sigma); grey: not measured (nexp = 0)",
    sigma: "log10 sigma; grey: not measured (nexp = 0)",
    quality: "quality flags (the lowest flag of each photosite)",
  };
  for (const kind of ["preview", "snr", "sigma", "quality"]) {
    if (!r.links[kind]) continue;
    if (have.has(kind)) {
      const img = images.querySelector(`img[data-kind="${kind}"]`);
      img.src = `${r.links[kind]}?v=${Date.now()}`;
    } else {
      images.append(el("figure", {}, el("img", { src: r.links[kind], alt: captions[kind], "data-kind": kind }), el("figcaption", {}, captions[kind])));
    }
  }
  if (r.links.preview) images.querySelectorAll(".note").forEach((n) => n.remove());
}

function runPage() {
  const name = document.body.dataset.run;
  const body = document.getElementById("events-body");
  let first = true;
  const source = new EventSource(`/api/runs/${enc(name)}/events?tail=200`);
  source.onopen = () => showLive(true);
  source.addEventListener("event", (msg) => {
    const e = JSON.parse(msg.data);
    if (first) {
      body.replaceChildren();
      first = false;
    }
    body.append(el("tr", { class: `ev-${e.event}` }, el("td", {}, fmtTime(e.time)), el("td", {}, e.event), el("td", {}, eventDetails(e))));
    while (body.rows.length > MAX_EVENT_ROWS) body.deleteRow(0);
    if (e.event === "frame" && e.total) {
      const r = { frames_done: e.done, frames_planned: e.total };
      document.getElementById("run-frames").replaceChildren(framesCell(r));
    }
    if (["stop", "done", "merged"].includes(e.event)) refreshRun(name);
  });
  source.addEventListener("end", () => {
    source.close();
    showLive(false);
    if (first) body.replaceChildren(el("tr", { class: "empty" }, el("td", { colspan: 3 }, "No event recorded.")));
    document.getElementById("events-note").textContent = "the last 200; the run is not going on";
    refreshRun(name);
  });
  source.onerror = () => showLive(false);
  filesTable(name);
}

function filesTable(name) {
  const table = document.getElementById("files");
  const body = document.getElementById("files-body");
  const more = document.getElementById("files-more");
  const row = (f) =>
    el(
      "tr",
      {},
      el("td", {}, f.kind === "folder" ? el("a", { href: "#", class: "folder", "data-folder": f.path }, `${f.name}/`) : el("a", { href: `/api/runs/${enc(name)}/files/${f.path.split("/").map(enc).join("/")}` }, f.name)),
      el("td", { class: "num" }, f.bytes === null ? "" : f.bytes),
      el("td", {}, fmtTime(f.modified)),
    );
  async function load(folder, offset, replace) {
    const res = await fetch(`/api/runs/${enc(name)}/files?folder=${enc(folder)}&offset=${offset}&limit=100`);
    if (!res.ok) return;
    const page = await res.json();
    const rows = page.files.map(row);
    if (replace) {
      body.replaceChildren();
      if (folder) {
        const up = folder.split("/").slice(0, -1).join("/");
        body.append(el("tr", {}, el("td", { colspan: 3 }, el("a", { href: "#", class: "folder", "data-folder": up }, "../"))));
      }
    }
    body.append(...rows);
    table.dataset.folder = folder;
    more.hidden = page.next_offset === null;
    more.dataset.next = page.next_offset || 0;
  }
  table.addEventListener("click", (ev) => {
    const a = ev.target.closest("a.folder");
    if (!a) return;
    ev.preventDefault();
    load(a.dataset.folder, 0, true);
  });
  more.addEventListener("click", () => load(table.dataset.folder, Number(more.dataset.next), false));
}

// ------------------------------------------------------------------ an archive
const SVG = "http://www.w3.org/2000/svg";

function svg(tag, attrs, text) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}

function ticks(lo, hi, n) {
  const span = hi - lo || Math.abs(hi) || 1;
  const step0 = span / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(v);
  return out;
}

function plotSeries(plot, data) {
  const W = 640, H = 320, L = 78, R = 14, T = 14, B = 52;
  plot.replaceChildren();
  const pts = data.time.map((t, i) => ({ t: Date.parse(t.endsWith("Z") || /[+-]\d\d:?\d\d$/.test(t) ? t : t + "Z"), y: data.irradiance[i], s: data.sigma[i] })).filter((p) => p.y !== null);
  if (!pts.length) {
    plot.append(svg("text", { x: W / 2, y: H / 2, "text-anchor": "middle", class: "axis" }, "no valid photosite in this region"));
    return;
  }
  let t0 = Math.min(...pts.map((p) => p.t)), t1 = Math.max(...pts.map((p) => p.t));
  if (t1 === t0) { t0 -= 60000; t1 += 60000; }
  let y0 = Math.min(...pts.map((p) => p.y - (p.s || 0))), y1 = Math.max(...pts.map((p) => p.y + (p.s || 0)));
  const pad = (y1 - y0) * 0.08 || Math.abs(y1) * 0.05 || 1;
  y0 -= pad; y1 += pad;
  const X = (t) => L + ((t - t0) / (t1 - t0)) * (W - L - R);
  const Y = (v) => T + (1 - (v - y0) / (y1 - y0)) * (H - T - B);
  for (const v of ticks(y0, y1, 5)) {
    plot.append(svg("line", { x1: L, x2: W - R, y1: Y(v), y2: Y(v), class: "grid" }));
    plot.append(svg("text", { x: L - 6, y: Y(v) + 4, "text-anchor": "end", class: "axis" }, Number(v.toPrecision(4)).toString()));
  }
  const span = t1 - t0;
  const nt = Math.min(5, pts.length + 1);
  for (let k = 0; k < nt; k++) {
    const t = t0 + (span * k) / (nt - 1 || 1);
    const d = new Date(t).toISOString();
    const anchor = k === 0 ? "start" : k === nt - 1 ? "end" : "middle";
    plot.append(svg("text", { x: X(t), y: H - B + 18, "text-anchor": anchor, class: "axis" }, span > 2 * 86400e3 ? d.slice(0, 10) : d.slice(5, 16).replace("T", " ")));
  }
  plot.append(svg("line", { x1: L, x2: L, y1: T, y2: H - B, class: "frame" }));
  plot.append(svg("line", { x1: L, x2: W - R, y1: H - B, y2: H - B, class: "frame" }));
  plot.append(svg("text", { x: 14, y: (H - B + T) / 2, transform: `rotate(-90 14 ${(H - B + T) / 2})`, "text-anchor": "middle", class: "axis" }, data.unit ? `irradiance (${data.unit.split(" (")[0]})` : "irradiance"));
  plot.append(svg("text", { x: (W + L) / 2, y: H - 8, "text-anchor": "middle", class: "axis" }, "run start (UTC)"));
  const path = pts.map((p, i) => `${i ? "L" : "M"}${X(p.t).toFixed(1)},${Y(p.y).toFixed(1)}`).join(" ");
  plot.append(svg("path", { d: path, class: "line" }));
  for (const p of pts) {
    if (p.s) plot.append(svg("line", { x1: X(p.t), x2: X(p.t), y1: Y(p.y - p.s), y2: Y(p.y + p.s), class: "err" }));
    const dot = svg("circle", { cx: X(p.t), cy: Y(p.y), r: 3.5, class: "dot" });
    dot.append(svg("title", {}, `${new Date(p.t).toISOString().slice(0, 19)}: ${fmtSig(p.y)} ± ${fmtSig(p.s)}`));
    plot.append(dot);
  }
}

function archivePage() {
  const { archive, height, width } = document.body.dataset;
  const img = document.getElementById("archive-preview");
  if (!img) return;
  const box = document.getElementById("region-box");
  const sizeSel = document.getElementById("region-size");
  let last = null;
  async function show(y, x) {
    const size = Number(sizeSel.value);
    y = Math.max(0, Math.min(Number(height) - size, y - size / 2));
    x = Math.max(0, Math.min(Number(width) - size, x - size / 2));
    y -= y % 2; x -= x % 2; // whole 2x2 colour filter periods
    last = [y + size / 2, x + size / 2];
    box.hidden = false;
    const sy = img.clientHeight / Number(height), sx = img.clientWidth / Number(width);
    Object.assign(box.style, { top: `${y * sy}px`, left: `${x * sx}px`, width: `${Math.max(3, size * sx)}px`, height: `${Math.max(3, size * sy)}px` });
    const res = await fetch(`/api/archive/series?archive=${enc(archive)}&y=${y}&x=${x}&size=${size}`);
    const data = await res.json();
    if (!res.ok) {
      document.getElementById("series-note").textContent = data.error;
      return;
    }
    document.getElementById("series-title").textContent = `Irradiance of the ${size} × ${size} region at y ${y}, x ${x}`;
    document.getElementById("series-note").textContent = data.sigma_of_mean;
    plotSeries(document.getElementById("series-plot"), data);
    document.getElementById("series-body").replaceChildren(
      ...data.time.map((t, i) => el("tr", {}, el("td", {}, data.run[i]), el("td", {}, fmtTime(t)), el("td", { class: "num" }, fmtSig(data.irradiance[i])), el("td", { class: "num" }, fmtSig(data.sigma[i])), el("td", { class: "num" }, data.n[i]))),
    );
  }
  img.addEventListener("click", (ev) => {
    const rect = img.getBoundingClientRect();
    const y = Math.floor(((ev.clientY - rect.top) / rect.height) * Number(height));
    const x = Math.floor(((ev.clientX - rect.left) / rect.width) * Number(width));
    show(y, x);
  });
  sizeSel.addEventListener("change", () => last && show(...last));
  // a region named in the address (#y=10&x=10&size=4: its centre) is shown at once
  const want = new URLSearchParams(location.hash.slice(1));
  if (want.has("y") && want.has("x")) {
    if (want.has("size")) sizeSel.value = want.get("size");
    const go = () => show(Number(want.get("y")), Number(want.get("x")));
    if (img.complete) go();
    else img.addEventListener("load", go, { once: true });
  }
}

if (page === "runs") runsPage();
else if (page === "run") runPage();
else if (page === "archive") archivePage();
