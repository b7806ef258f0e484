// cellcal web page, the rest of a whole calibration (loaded after app.js, whose helpers it
// uses): solve progress, station images with detected and reprojected corners, the station
// set download, activation that asks first, and the re-check and dot-hit validation of the
// active calibration.
"use strict";

// The latest finished calibration of the open run: its per-station corners and residuals
// draw the reprojected corners over each station's image.
let runResult = null;

// A solve's or a validation's progress: the message of each event, into `selector`.
function showProgress(path, selector) {
  $(selector).textContent = "started";
  return readEvents(path, (block) => {
    const name = /^event: (.*)$/m.exec(block);
    const data = /^data: (.*)$/m.exec(block);
    if (!name || !data) return;
    const event = JSON.parse(data[1]);
    const text = event.message ?? event.stage ?? event.state ?? name[1];
    if (text) $(selector).textContent = `${name[1]}: ${text}`;
  }).catch(() => {});
}

async function loadRunResult(runId) {
  const page = await json("GET", `/calibrations?run_id=${runId}&state=done&limit=1`);
  runResult = null;
  if (page.items.length) runResult = (await json("GET", `/calibrations/${page.items[0].id}`)).result;
}

// The reprojected corners of station `index` (N, 2 pixels) from the run's latest result.
function reprojected(index) {
  const fit = runResult?.stations?.find((s) => Number(s.id) === index);
  if (!fit?.corners_px || !fit.residuals_px) return [];
  return fit.corners_px.map(([x, y], i) => [x + fit.residuals_px[i][0], y + fit.residuals_px[i][1]]);
}

function drawReprojected(g, index, size) {
  const points = reprojected(index);
  g.strokeStyle = "#f33";
  for (const [x, y] of points) {
    g.beginPath();
    g.moveTo(x - size, y); g.lineTo(x + size, y);
    g.moveTo(x, y - size); g.lineTo(x, y + size);
    g.stroke();
  }
  return points.length;
}

// Activation changes what the cell controller gets, so the page asks first and shows what
// would be replaced: the calibration active now for the same cell and setup.
async function currentlyActive(setup) {
  const response = await fetch(`/calibrations/active?setup=${setup}`,
                               { headers: { Authorization: `Bearer ${key}` } });
  if (response.status === 404) return null;
  if (!response.ok) throw new Error(`${response.status}: cannot read the active calibration`);
  return response.json();
}

function summary(cal) {
  const r = cal.result ?? {};
  const pose = r.hand_eye?.pose;
  const parts = [`${short(cal.id)} (run ${short(cal.run_id)})`,
                 `verdict ${r.quality?.verdict ?? "–"}`,
                 `RMS ${r.camera?.rms_px?.toFixed(3) ?? "–"} px`];
  if (pose) {
    parts.push(`hand-eye ${pose.slice(0, 3).map((v) => (1e3 * v).toFixed(1)).join(" / ")} mm`);
  }
  return parts.join(", ");
}

async function confirmActivate(cal) {
  const [full, now] = await Promise.all([json("GET", `/calibrations/${cal.id}`),
                                         currentlyActive(cal.setup)]);
  $("#activate-new").textContent = summary(full);
  $("#activate-old").textContent = now === null
    ? `nothing: no calibration is active for ${cal.setup} yet`
    : `${summary(now.calibration)}, active since ${new Date(now.activated_at).toLocaleString()}` +
      (now.calibration.id === cal.id ? " (the same calibration: nothing changes)" : "");
  const dialog = $("#activate-dialog");
  dialog.showModal();
  const answer = await new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue), { once: true });
  });
  if (answer !== "activate") {
    setStatus("activation cancelled");
    return;
  }
  await json("POST", `/calibrations/${cal.id}/activate`);
  await loadCalibrations();
  setStatus(`activated ${short(cal.id)}`);
}

async function downloadStationSet() {
  const response = await api("GET", `/runs/${currentRun}/stationset`);
  const link = document.createElement("a");
  link.href = URL.createObjectURL(await response.blob());
  link.download = `stationset-${short(currentRun)}.zip`;
  link.click();
  URL.revokeObjectURL(link.href);
}

// Re-check (has the cell changed?) or dot-hit validation of the active calibration.
async function validateActive(kind) {
  const active = await currentlyActive($("#validate-setup").value);
  if (active === null) throw new Error("no calibration is active: activate one first");
  const path = kind === "check" ? "checks" : "validations";
  const created = await json("POST", `/calibrations/${active.calibration.id}/${path}`, {},
                             { "Idempotency-Key": idempotencyKey() });
  $("#validation-id").textContent = `${kind === "check" ? "re-check" : "dot-hit"} ` +
    `${short(created.id)} of ${short(active.calibration.id)}`;
  await showProgress(`/validations/${created.id}/events`, "#validation-progress");
  let validation;
  for (;;) {
    validation = await json("GET", `/validations/${created.id}`);
    if (validation.state !== "running") break;
    await new Promise((resolve) => setTimeout(resolve, 500));
  }
  $("#validation-state").textContent = validation.state;
  $("#validation-state").className = validation.state;
  $("#validation-result").textContent = validation.error ?? validationSummary(validation);
}

function validationSummary(validation) {
  const r = validation.result ?? {};
  if (validation.kind === "check") {
    const stations = r.stations ?? [];
    return `cell ${r.state}: ${stations.filter((s) => s.state === "ok").length} of ` +
      `${stations.length} stations ok`;
  }
  const touched = `${(r.points ?? []).length} points touched`;
  if (!r.error_m) return `${touched}; compare the probe's marks with the board's points`;
  return `${touched}; error mean ${(1e3 * r.error_m.mean).toFixed(2)} mm, ` +
    `max ${(1e3 * r.error_m.max).toFixed(2)} mm`;
}

for (const button of document.querySelectorAll("[data-validate]")) {
  button.addEventListener("click", () => {
    button.disabled = true;
    run(() => validateActive(button.dataset.validate)).finally(() => { button.disabled = false; });
  });
}
$("#stationset").addEventListener("click", () => run(downloadStationSet));
