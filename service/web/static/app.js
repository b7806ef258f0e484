// cellcal web page: plain JavaScript over the REST API, with the same API key (session storage).
"use strict";

const FORMATS = ["json", "opencv-yaml", "ros-camera-info", "urdf", "ur-pose", "ros2-static-tf"];
const $ = (selector) => document.querySelector(selector);
let key = sessionStorage.getItem("cellcal-key") || "";
let currentRun = null;
let stream = null;
// A calibrate request of this page is in flight: its button stays disabled whatever a run
// refresh (on each event of the followed run) says about the run.
let calibrating = false;

function setStatus(text) { $("#status").textContent = text; }

async function api(method, path, body, headers = {}) {
  const options = { method, headers: { Authorization: `Bearer ${key}`, ...headers } };
  if (body !== undefined) {
    options.headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  const response = await fetch(path, options);
  if (!response.ok) throw await failure(response);
  return response;
}

async function failure(response) {
  const error = await response.json().catch(() => ({ detail: response.statusText }));
  return new Error(`${response.status}: ${error.detail}`);
}

const json = async (method, path, body, headers) =>
  (await api(method, path, body, headers)).json();

// A new Idempotency-Key: the service answers a start repeated with it (a double click, a
// retry after a lost answer) with the first answer instead of starting the work again.
// (crypto.randomUUID needs a secure context; a plant page is often plain http.)
function idempotencyKey() {
  const bytes = crypto.getRandomValues(new Uint8Array(16));
  return [...bytes].map((b) => b.toString(16).padStart(2, "0")).join("");
}

function cell(row, text, cls) {
  const td = row.insertCell();
  td.textContent = text ?? "–";
  if (cls) td.className = cls;
  return td;
}

function short(id) { return id.slice(0, 8); }

// The devices line is read again every DEVICES_REFRESH_MS, so a robot or camera that comes,
// goes or moves shows without a reload.
const DEVICES_REFRESH_MS = 5000;
let devicesTimer = null;

async function loadDevices() {
  const d = await json("GET", "/devices");
  const tcp = d.robot.tcp_pose
    ? `, TCP at ${d.robot.tcp_pose.slice(0, 3).map((v) => (v * 1000).toFixed(1)).join(" ")} mm`
    : "";
  const robot = d.robot.error ? `error: ${d.robot.error.detail}`
    : `${d.robot.connected ? "connected" : "not connected"}, ${d.robot.mode ?? ""}${tcp}`;
  const camera = d.camera.error ? `error: ${d.camera.error.detail}`
    : d.camera.opened ? `open ${(d.camera.resolution ?? []).join("x")}`
      : d.robot.error ? "not opened (it is opened once the robot connects)" : "closed";
  const checked = new Date().toLocaleTimeString();
  $("#devices").textContent =
    `Robot ${d.robot.url}: ${robot}. Camera ${d.camera.url}: ${camera}. (checked ${checked})`;
}

function watchDevices() {
  if (devicesTimer !== null) return;
  devicesTimer = setInterval(() => loadDevices().catch((error) => {
    $("#devices").textContent = `Devices: ${error.message}`;
  }), DEVICES_REFRESH_MS);
}

async function loadRuns() {
  const runs = await json("GET", "/runs?limit=20");
  const body = $("#runs tbody");
  body.replaceChildren();
  for (const run of runs) {
    const row = body.insertRow();
    row.dataset.id = run.id;
    cell(row, short(run.id));
    cell(row, run.mode);
    cell(row, run.state, run.state);
    cell(row, run.stations_captured);
    cell(row, run.stations_skipped);
    cell(row, run.stations_planned);
    cell(row, new Date(run.created_at).toLocaleString());
    row.addEventListener("click", () => openRun(run.id));
  }
}

// ``runId`` may be a unique prefix (a short id from an address): the page then works with
// the full id the service answers.
async function openRun(runId) {
  currentRun = (await json("GET", `/runs/${runId}`)).id;
  $("#run-view").hidden = false;
  $("#run-id").textContent = short(currentRun);
  await loadRunResult(currentRun);
  await refreshRun();
  follow(currentRun);
}

// What each run button may do in each run state (the service answers 409 otherwise).
const ACTIONS = {
  pause: (run) => run.state === "capturing",
  resume: (run) => ["paused", "interrupted", "failed"].includes(run.state),
  cancel: (run) => ["capturing", "paused", "interrupted"].includes(run.state),
  finish: (run) => run.mode === "external" && run.state === "capturing",
};

async function refreshRun() {
  const run = await json("GET", `/runs/${currentRun}`);
  $("#run-state").textContent = run.state;
  $("#run-state").className = run.state;
  for (const button of document.querySelectorAll("[data-action]")) {
    button.disabled = !ACTIONS[button.dataset.action](run);
  }
  $("[data-action=finish]").hidden = run.mode !== "external";
  $("#calibrate").disabled = calibrating || run.state === "capturing" ||
    run.stations_captured === 0;
  $("#run-error").hidden = !run.error;
  $("#run-error").textContent = run.error ? run.error.detail : "";
  const seen = run.stations_captured + run.stations_skipped;
  const planned = Math.max(run.stations_planned, seen, 1);
  $("#progress").max = planned;
  $("#progress").value = seen;
  $("#progress-text").textContent = run.mode === "external"
    ? `${run.stations_captured} stations captured, ${run.stations_skipped} skipped`
    : `${seen} of ${run.stations_planned} stations: ${run.stations_captured} captured, ` +
      `${run.stations_skipped} skipped`;
  drawSigma(run.cold_start);
  const stations = await json("GET", `/runs/${currentRun}/stations`);
  const body = $("#stations tbody");
  body.replaceChildren();
  for (const station of stations) {
    const row = body.insertRow();
    cell(row, station.index);
    cell(row, station.state, station.state);
    cell(row, station.error ? station.error.detail : "");
    row.dataset.index = station.index;
    if (station.image_url) {
      row.addEventListener("click", () => drawStation(station.index).catch((error) => {
        setStatus(error.message);
      }));
    }
  }
  const last = stations.filter((s) => s.image_url).pop();
  if (last) await drawStation(last.index);
}

// A tolerance run's 90 % bound on the hand-eye error after each station (coverage_factor x σ),
// in units of its tolerance (rotation and translation), against the line where the run stops;
// log scale, newest on the right.
function drawSigma(cold) {
  const rule = cold?.stop_rule;
  $("#sigma-view").hidden = !rule;
  if (!rule) return;
  const history = cold.sigma_history;
  const canvas = $("#sigma-plot");
  const g = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 30;
  g.clearRect(0, 0, w, h);
  const series = [
    { color: "#c0392b", label: "rotation", values: history.map((p) => (p.bound_rot_deg ?? p.rot_deg) / rule.tolerance_deg) },
    { color: "#2c7fb8", label: "translation", values: history.map((p) => (p.bound_trans_mm ?? p.trans_mm) / rule.tolerance_mm) },
  ];
  const all = series.flatMap((s) => s.values).concat([1]);
  const top = Math.log10(Math.max(...all) * 1.2), bottom = Math.log10(Math.min(...all) / 1.2);
  const n = Math.max(rule.max_stations, ...history.map((p) => p.stations));
  const x = (stations) => pad + (w - 2 * pad) * stations / n;
  const y = (v) => pad + (h - 2 * pad) * (top - Math.log10(v)) / Math.max(top - bottom, 1e-9);
  g.strokeStyle = "#888";
  g.setLineDash([4, 4]);
  g.beginPath(); g.moveTo(pad, y(1)); g.lineTo(w - pad, y(1)); g.stroke();
  g.setLineDash([]);
  g.fillStyle = "#555";
  g.font = "11px sans-serif";
  g.fillText("tolerance", w - pad - 50, y(1) - 4);
  g.fillText(`stations (of at most ${rule.max_stations})`, pad, h - 8);
  series.forEach((s, k) => {
    g.fillStyle = s.color;
    g.fillText(`${s.label}: 90 % bound / tolerance`, pad + 200 * k, 14);
  });
  for (const s of series) {
    g.strokeStyle = g.fillStyle = s.color;
    g.beginPath();
    history.forEach((p, i) => (i ? g.lineTo : g.moveTo).call(g, x(p.stations), y(s.values[i])));
    g.stroke();
    history.forEach((p, i) => g.fillRect(x(p.stations) - 2, y(s.values[i]) - 2, 4, 4));
  }
  const last = history[history.length - 1];
  $("#sigma-caption").textContent = (last
    ? `σ ${last.rot_deg.toFixed(3)}° / ${last.trans_mm.toFixed(2)} mm (${last.kind}), 90 % ` +
      `bound ${(last.bound_rot_deg ?? NaN).toFixed(3)}° / ${(last.bound_trans_mm ?? NaN).toFixed(2)} mm ` +
      `after ${last.stations} stations; tolerance ${rule.tolerance_deg}° / ${rule.tolerance_mm} mm`
    : `tolerance ${rule.tolerance_deg}° / ${rule.tolerance_mm} mm; no σ yet`) +
    (cold.stop_reason ? `; stopped: ${cold.stop_reason}` : "");
}

async function drawStation(index) {
  const station = await json("GET", `/runs/${currentRun}/stations/${index}`);
  const blob = await (await api("GET", station.image_url)).blob();
  const image = await createImageBitmap(blob);
  const canvas = $("#latest");
  canvas.width = image.width;
  canvas.height = image.height;
  const g = canvas.getContext("2d");
  g.drawImage(image, 0, 0);
  const corners = station.detection?.corners ?? [];
  g.strokeStyle = "#0f0";
  g.lineWidth = Math.max(1, image.width / 640);
  for (const [x, y] of corners) {
    g.beginPath();
    g.arc(x, y, 3 * g.lineWidth, 0, 2 * Math.PI);
    g.stroke();
  }
  const shown = drawReprojected(g, index, 4 * g.lineWidth);
  for (const row of document.querySelectorAll("#stations tbody tr")) {
    row.classList.toggle("shown", row.dataset.index === String(index));
  }
  $("#latest-caption").textContent = `Station ${index}: ${station.state}` +
    (corners.length ? `, ${corners.length} corners detected (green)` : "") +
    (shown ? `, ${shown} reprojected by the calibration (red)` : "") +
    (station.error ? ` (${station.error.detail})` : "");
}

// Server-sent events read with fetch, so the API key goes in the header; resumes with
// Last-Event-ID after a dropped connection.
async function follow(runId) {
  if (stream) stream.abort();
  const controller = new AbortController();
  stream = controller;
  let lastId = null;
  while (!controller.signal.aborted) {
    try {
      const headers = lastId === null ? {} : { "Last-Event-ID": lastId };
      await readEvents(`/runs/${runId}/events`, async (block) => {
        const id = /^id: (.*)$/m.exec(block);
        if (id) lastId = id[1];
        if (/^event: /m.test(block)) {
          await refreshRun();
          await loadRuns();
        }
      }, { headers, signal: controller.signal });
      return;
    } catch (error) {
      if (controller.signal.aborted) return;
      setStatus(`event stream: ${error.message}; reconnecting`);
      await new Promise((resolve) => setTimeout(resolve, 1000));
    }
  }
}

// Read a server-sent event stream with fetch (so the API key goes in the header) until it
// ends, handing each event's block of lines to onBlock.
async function readEvents(path, onBlock, { headers = {}, signal } = {}) {
  const response = await fetch(path, {
    headers: { Authorization: `Bearer ${key}`, ...headers }, signal });
  if (!response.ok) return;  // no such stream (any more): nothing to follow
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      await onBlock(block);
    }
  }
}

async function loadCalibrations() {
  const page = await json("GET", "/calibrations?limit=20");
  const body = $("#calibrations tbody");
  body.replaceChildren();
  for (const cal of page.items) {
    const row = body.insertRow();
    cell(row, short(cal.id));
    cell(row, short(cal.run_id));
    cell(row, cal.setup);
    cell(row, cal.state, cal.state);
    cell(row, cal.verdict, cal.verdict);
    cell(row, cal.rms_px === null ? null : cal.rms_px.toFixed(3));
    cell(row, cal.active ? "active" : "");
    const exports = cell(row, "");
    if (cal.state === "done") {
      const report = document.createElement("a");
      report.href = "#";
      report.textContent = "report";
      report.className = "report";
      report.addEventListener("click", (event) => {
        event.preventDefault();
        event.stopPropagation();
        openReport(cal.id);
      });
      exports.append(report, " · ");
      for (const format of FORMATS) {
        const link = document.createElement("a");
        link.href = "#";
        link.textContent = format;
        link.dataset.format = format;
        link.addEventListener("click", (event) => {
          event.preventDefault();
          event.stopPropagation();
          run(() => download(cal.id, format));
        });
        exports.append(link, " ");
      }
      const activate = document.createElement("button");
      activate.textContent = "Activate";
      activate.title = "make this the calibration the cell controller gets from " +
        "GET /calibrations/active";
      activate.addEventListener("click", (event) => {
        event.stopPropagation();
        run(() => confirmActivate(cal));
      });
      cell(row, "").append(activate);
    } else {
      cell(row, cal.error ?? "");
    }
    row.addEventListener("click", () => showCalibration(cal.id));
  }
}

async function showCalibration(calId) {
  const cal = await json("GET", `/calibrations/${calId}`);
  $("#calibration-view").hidden = false;
  $("#cal-id").textContent = short(cal.id);
  const r = cal.result ?? {};
  const mm = (values) => values?.map((v) => (1e3 * v).toFixed(2)).join(" / ");
  const deg = (values) => values?.map((v) => (180 / Math.PI * v).toFixed(3)).join(" / ");
  const pose = r.hand_eye?.pose;
  const K = r.camera?.K;
  const board = r.target_pose?.pose;
  const boardFrame = r.setup === "eye_to_hand" ? "tool → board" : "base → board";
  const figures = {
    state: cal.state,
    verdict: r.quality?.verdict,
    findings: r.quality?.findings?.map((f) => `${f.severity}: ${f.message}`).join("\n"),
    "reprojection RMS (px)": r.camera?.rms_px?.toFixed(3),
    "predicted from robot poses, RMS (px)": r.cross_validation?.rms_px?.toFixed(3),
    "board scale κ / aspect ratio ν": r.target && `${r.target.kappa?.toFixed(5)} / ${r.target.nu?.toFixed(5)}`,
    [`hand-eye (${r.setup === "eye_to_hand" ? "base → camera" : "tool → camera"}) x / y / z (mm)`]:
      mm(pose?.slice(0, 3)),
    "hand-eye rotation vector rx / ry / rz (deg)": deg(pose?.slice(3)),
    "hand-eye 1σ x / y / z (mm)": mm(r.uncertainty?.hand_eye_trans_m),
    "hand-eye 1σ rotation (deg)": deg(r.uncertainty?.hand_eye_rot_rad),
    "image size (px)": r.camera?.image_size?.join(" × "),
    "focal length fx / fy (px)": K && `${K[0][0].toFixed(2)} / ${K[1][1].toFixed(2)}`,
    "principal point cx / cy (px)": K && `${K[0][2].toFixed(2)} / ${K[1][2].toFixed(2)}`,
    "distortion k1 k2 p1 p2 k3": r.camera?.dist?.map((v) => v.toFixed(5)).join(" "),
    [`board pose (${boardFrame}) x / y / z (mm)`]: mm(board?.slice(0, 3)),
    "board pose rotation vector rx / ry / rz (deg)": deg(board?.slice(3)),
    error: cal.error,
  };
  const list = $("#figures");
  list.replaceChildren();
  for (const [name, value] of Object.entries(figures)) {
    if (value === undefined || value === null) continue;
    const dt = document.createElement("dt");
    dt.textContent = name;
    const dd = document.createElement("dd");
    dd.textContent = value;
    if (name === "verdict") dd.className = value;
    if (name === "findings") dd.className = "findings";
    list.append(dt, dd);
  }
}

// The report needs the API key, so it is fetched here and shown in a new tab. The tab is
// opened at the click itself (a tab opened after a slow answer would count as a pop-up).
function openReport(calId) {
  const tab = window.open("", "_blank");
  run(async () => {
    try {
      const html = await (await reportPage(calId)).text();
      tab.location = URL.createObjectURL(new Blob([html], { type: "text/html" }));
    } catch (error) {
      tab.close();
      throw error;
    }
  });
}

// A report still being rendered is answered 503 report_rendering: ask again after its
// Retry-After, as long as the service says it is rendering.
async function reportPage(calId) {
  const path = `/calibrations/${calId}/report`;
  for (;;) {
    const response = await fetch(path, { headers: { Authorization: `Bearer ${key}` } });
    const error = response.status === 503
      ? await response.clone().json().catch(() => null) : null;
    if (error?.code !== "report_rendering") {
      if (!response.ok) throw await failure(response);
      return response;
    }
    setStatus(`report of ${short(calId)} being rendered…`);
    const seconds = Number(response.headers.get("Retry-After")) || 5;
    await new Promise((resolve) => setTimeout(resolve, 1000 * seconds));
  }
}

async function download(calId, format) {
  const response = await api("GET", `/calibrations/${calId}/export?format=${format}`);
  const name = /filename="([^"]+)"/.exec(response.headers.get("Content-Disposition") ?? "");
  const link = document.createElement("a");
  link.href = URL.createObjectURL(await response.blob());
  link.download = name ? name[1] : `calibration-${format}`;
  link.click();
  URL.revokeObjectURL(link.href);
}

async function run(action) {
  try {
    setStatus("");
    await action();
  } catch (error) {
    setStatus(error.message);
  }
}

async function loadAll() {
  await Promise.all([loadDevices(), loadRuns(), loadCalibrations()]);
  watchDevices();
  setStatus("connected");
}

$("#key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  key = $("#key").value;
  sessionStorage.setItem("cellcal-key", key);
  run(loadAll);
});

// The body of POST /runs for the kind of run chosen: planned (a station count or a
// tolerance), external (a cell controller posts the stations) or a list of TCP poses.
function runBody() {
  const kind = $("#run-kind").value;
  if (kind === "external") return { mode: "external" };
  if (kind === "poses") {
    let poses;
    try {
      poses = JSON.parse($("#poses").value);
    } catch (error) {
      throw new Error(`poses: not JSON (${error.message})`);
    }
    return { poses };
  }
  return $("#use-tolerance").checked
    ? { tolerance_mm: Number($("#tolerance-mm").value),
        tolerance_deg: Number($("#tolerance-deg").value),
        max_stations: Number($("#max-stations").value) }
    : { stations: Number($("#stations").value) };
}

$("#run-kind").addEventListener("change", () => {
  const kind = $("#run-kind").value;
  $("#planned-options").hidden = kind !== "planned";
  $("#poses-options").hidden = kind !== "poses";
});

$("#run-form").addEventListener("submit", (event) => {
  event.preventDefault();
  run(async () => {
    const created = await json("POST", "/runs", runBody(), { "Idempotency-Key": idempotencyKey() });
    await loadRuns();
    await openRun(created.id);
  });
});

for (const button of document.querySelectorAll("[data-action]")) {
  button.addEventListener("click", () => run(async () => {
    await json("POST", `/runs/${currentRun}/${button.dataset.action}`);
    await refreshRun();
    await loadRuns();
  }));
}

// Calibrate disables itself until its calibration ends, and sends an Idempotency-Key, so a
// double click starts one solve.
$("#calibrate").addEventListener("click", () => {
  const button = $("#calibrate");
  calibrating = true;
  button.disabled = true;
  const options = { method: $("#method").value, kappa: $("#kappa").value };
  run(async () => {
    const created = await json("POST", `/runs/${currentRun}/calibrations`, { options },
                               { "Idempotency-Key": idempotencyKey() });
    setStatus(`calibrating (${short(created.id)})`);
    showProgress(`/calibrations/${created.id}/events`, "#solve-progress");
    for (;;) {
      const cal = await json("GET", `/calibrations/${created.id}`);
      if (cal.state !== "running") break;
      await new Promise((resolve) => setTimeout(resolve, 1000));
    }
    await loadCalibrations();
    await showCalibration(created.id);
    await loadRunResult(currentRun);
    setStatus("calibration finished");
  }).finally(() => {
    calibrating = false;
    return refreshRun().catch(() => { button.disabled = false; });
  });
});

// The address fragment (never sent to the server) may carry the key, taken once and removed,
// and a run and a calibration to open: #key=...&run=ID&calibration=ID.
const fragment = new URLSearchParams(location.hash.slice(1));
if (fragment.get("key")) {
  key = fragment.get("key");
  sessionStorage.setItem("cellcal-key", key);
  history.replaceState(null, "", location.pathname);
}
if (key) {
  run(async () => {
    await loadAll();
    if (fragment.get("run")) await openRun(fragment.get("run"));
    if (fragment.get("calibration")) await showCalibration(fragment.get("calibration"));
  });
}
