// n2f2 viewer: picks a camera (training view or orbit), sends queries to the JSON API, and
// draws the server's overlays. All rendering happens on the server; this file only displays.
"use strict";

let SCALE = 2; // display magnification of the rendered images: about 640 px wide on screen
const state = { scene: null, camera: { view: 0 }, orbit: null, lastResults: null, busy: false };
const $ = (id) => document.getElementById(id);

function setLoading(on, text) {
  $("loading").textContent = text || "rendering…";
  $("loading").classList.toggle("on", on);
  state.busy = on;
}

function showError(msg) { $("error").textContent = msg || ""; }
function showWarning(msg) { $("warning").textContent = msg || ""; }

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  };
  const resp = await fetch(path, init);
  const data = await resp.json().catch(() => ({ error: `HTTP ${resp.status}` }));
  if (!resp.ok) throw new Error(data.error || `HTTP ${resp.status}`);
  return data;
}

function loadImage(b64) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = reject;
    img.src = "data:image/png;base64," + b64;
  });
}

async function drawMain(rgbB64, overlayB64, maskB64, loc) {
  const canvas = $("canvas");
  const base = await loadImage(overlayB64 || rgbB64);
  SCALE = Math.max(1, Math.floor(640 / base.width));
  canvas.width = base.width * SCALE;
  canvas.height = base.height * SCALE;
  const ctx = canvas.getContext("2d");
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(base, 0, 0, canvas.width, canvas.height);
  if (maskB64 && $("showMask").checked) {
    const mask = await loadImage(maskB64);
    ctx.globalAlpha = 0.35;
    ctx.drawImage(mask, 0, 0, canvas.width, canvas.height);
    ctx.globalAlpha = 1.0;
  }
  if (loc) {
    // loc is the integer pixel (x = column, y = row) of the render: circle its centre.
    ctx.strokeStyle = "#00ff88";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc((loc[0] + 0.5) * SCALE, (loc[1] + 0.5) * SCALE, 7, 0, 2 * Math.PI);
    ctx.stroke();
  }
}

function cameraBody() {
  return state.orbit ? { orbit: state.orbit } : { view: state.camera.view };
}

async function renderCurrent() {
  setLoading(true, "rendering view…");
  showError("");
  showWarning("");
  try {
    const data = await api("/api/render", { camera: cameraBody() });
    state.lastRgb = data.rgb_png;
    await drawMain(data.rgb_png);
    $("timing").textContent = `render ${data.timing_ms.toFixed(0)} ms${data.cached ? " (cached)" : ""}`;
  } catch (e) {
    showError(e.message);
  } finally {
    setLoading(false);
  }
}

function parseQueries() {
  return $("queries").value.split(/[\n,]/).map((s) => s.trim()).filter((s) => s.length > 0);
}

function currentMode() {
  const checked = document.querySelector("input[name=mode]:checked");
  return checked ? checked.value : undefined;
}

// One radio button per mode the run answers (/api/scene): node only when it has a hierarchy.
function addModes(modes) {
  const box = $("modes");
  box.innerHTML = "";
  modes.forEach((mode, i) => {
    const label = document.createElement("label");
    const input = document.createElement("input");
    input.type = "radio";
    input.name = "mode";
    input.value = mode;
    input.checked = mode === "composite" || (i === 0 && !modes.includes("composite"));
    label.append(input, ` ${mode}`);
    box.appendChild(label);
  });
}

async function runQuery() {
  const queries = parseQueries();
  if (queries.length === 0) { showError("type a query first"); return; }
  setLoading(true, "querying…");
  showError("");
  showWarning("");
  try {
    const data = await api("/api/query", { queries, camera: cameraBody(), mode: currentMode() });
    state.lastResults = data;
    const first = data.results[0];
    await drawMain(data.rgb_png, first.overlay_png, first.mask_png, first.localization);
    const list = $("results");
    list.innerHTML = "";
    for (const r of data.results) {
      const div = document.createElement("div");
      div.className = "result";
      div.dataset.query = r.query;
      div.innerHTML = `<div class="title"></div><img width="${data.width * 1.5}"><div class="stats"></div>` +
        `<div class="warning"></div>`;
      div.querySelector(".title").textContent = r.query;
      div.querySelector("img").src = "data:image/png;base64," + r.overlay_png;
      const nodes = r.nodes ? ` · nodes ${r.nodes.join(", ")} (level ${r.level})` : "";
      div.querySelector(".stats").textContent =
        `max ${r.max_relevancy.toFixed(3)} · mask ${r.mask_area} px · at (${r.localization.join(", ")})` +
        ` · scale ${r.chosen_scale ?? "composite"}${nodes}`;
      // A flat relevancy map carries no signal: the server says so, and so does the page.
      div.querySelector(".warning").textContent = r.warning ? `warning: ${r.warning}` : "";
      div.onclick = () => drawMain(data.rgb_png, r.overlay_png, r.mask_png, r.localization);
      list.appendChild(div);
    }
    $("canvas").dataset.queried = "1";
    $("timing").textContent = `query ${data.timing_ms.toFixed(0)} ms (${data.mode}, box ${data.box_size} px)`;
    const flat = data.results.filter((r) => r.warning).map((r) => `"${r.query}": ${r.warning}`);
    showWarning(flat.length ? `warning: ${flat.join("; ")}` : "");
  } catch (e) {
    showError(e.message);
  } finally {
    setLoading(false);
  }
}

async function downloadSelection() {
  const queries = parseQueries();
  if (queries.length === 0) { showError("type a query first"); return; }
  showError("");
  const resp = await fetch("/api/selection", {
    method: "POST", headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ query: queries[0], mode: currentMode() }),
  });
  if (!resp.ok) {
    const data = await resp.json().catch(() => ({ error: `HTTP ${resp.status}` }));
    showError(data.error);
    return;
  }
  const blob = await resp.blob();
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = "selection.ply";
  a.click();
  $("timing").textContent = `selection: ${resp.headers.get("X-Selected-Gaussians")} Gaussians`;
}

function setupOrbit() {
  let drag = null;
  const stage = $("stage");
  stage.addEventListener("mousedown", (e) => {
    if (state.busy) return;
    const base = state.orbit || state.scene.views[state.camera.view].orbit;
    drag = { x: e.clientX, y: e.clientY, base: { ...base } };
  });
  window.addEventListener("mouseup", async (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    const base = drag.base;
    drag = null;
    if (Math.abs(dx) + Math.abs(dy) < 3) return;
    state.orbit = {
      azimuth: base.azimuth - dx * 0.5,
      elevation: Math.max(-80, Math.min(80, base.elevation + dy * 0.5)),
      radius: base.radius,
    };
    if (state.lastResults) await runQuery(); else await renderCurrent();
  });
}

async function init() {
  try {
    state.scene = await api("/api/scene");
  } catch (e) {
    showError(e.message);
    return;
  }
  $("encoder").textContent = `text encoder: ${state.scene.encoder}`;
  addModes(state.scene.modes);
  for (const v of state.scene.views) {
    const opt = document.createElement("option");
    opt.value = v.index;
    opt.textContent = `${v.index}: ${v.name}`;
    $("view").appendChild(opt);
  }
  $("view").onchange = async () => {
    state.camera = { view: parseInt($("view").value, 10) };
    state.orbit = null;
    if (state.lastResults) await runQuery(); else await renderCurrent();
  };
  $("run").onclick = runQuery;
  $("queries").addEventListener("keydown", (e) => { if (e.key === "Enter") runQuery(); });
  $("download").onclick = downloadSelection;
  $("showMask").onchange = () => state.lastResults && runQuery();
  setupOrbit();
  await renderCurrent();
}

init();
