"use strict";
// The operator's dashboard: polls the station's JSON API and sends the scan buttons. No build step.

const $ = (id) => document.getElementById(id);
const ACTIVE = ["connecting", "scanning", "pausing", "paused", "waiting for operator", "cancelling"];
let pollSeconds = 1;
let formFilled = false;
let scan = null; // the newest scan state from /api/state
let previewFrame = null;
let lastPhase = null;
let lastContact = null;
let contactLost = false;

// A token given in the address (#token=...) becomes a same-site cookie, then leaves the address bar.
function keepToken() {
  const match = location.hash.match(/token=([^&]+)/);
  if (match) {
    document.cookie = `station_token=${match[1]}; path=/; SameSite=Strict`;
    history.replaceState(null, "", location.pathname + location.search);
  }
}
keepToken();
window.addEventListener("hashchange", keepToken);

async function api(path, body) {
  const options = body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  };
  const response = await fetch(path, options);
  const answer = await response.json().catch(() => ({}));
  if (!response.ok) {
    const why = answer.error || answer.detail || response.statusText;
    throw Object.assign(new Error(typeof why === "string" ? why : JSON.stringify(why)), { refused: true });
  }
  return answer;
}

function alertOperator(text) {
  $("alert").textContent = text;
  $("alert").hidden = !text;
}

function clock() {
  return new Date().toLocaleTimeString();
}

function degrees(value) {
  return value === null ? "–" : `${value.toFixed(1)}°`;
}

function showRig(rig) {
  $("rig-label").textContent = rig.label;
  $("turntable-state").textContent = rig.turntable.state;
  const { elevation_deg: elevation, azimuth_deg: azimuth } = rig.turntable;
  const pose = `elevation ${degrees(elevation)}, azimuth ${degrees(azimuth)}`;
  $("turntable-pose").textContent = elevation === null ? "–" : (rig.connected ? pose : `last: ${pose}`);
  $("camera-state").textContent = rig.camera;
}

function showScan(state) {
  scan = state.scan;
  const phase = scan ? scan.phase : "idle";
  const active = ACTIVE.includes(phase);
  $("phase").textContent = scan ? phase : "no scan yet";
  $("phase").className = `phase ${phase.split(" ")[0]}`;
  $("scan-name").textContent = scan ? scan.name : "";
  const done = scan ? scan.done : 0;
  const total = scan ? scan.total : 0;
  $("progress-bar").style.width = total ? `${(100 * done) / total}%` : "0";
  $("progress-text").textContent = scan ? (total ? `${done} of ${total} frames` : "starting the rig…") : "\u00a0";
  $("scan-message").textContent = scan ? scan.message : "";

  $("pause").disabled = !(phase === "connecting" || phase === "scanning");
  $("resume").disabled = !(phase === "pausing" || phase === "paused" || (scan && scan.resumable));
  $("cancel").disabled = !active || phase === "cancelling";
  $("start").disabled = active;

  $("operator").hidden = !state.operator_prompt;
  $("operator-prompt").textContent = state.operator_prompt || "";

  if (scan && scan.latest && `${scan.name}/${scan.latest}` !== previewFrame) {
    previewFrame = `${scan.name}/${scan.latest}`;
    $("preview").src = `/api/scan/preview.jpg?frame=${encodeURIComponent(previewFrame)}`;
    $("preview").hidden = false;
    $("preview-caption").textContent = `Newest frame: ${scan.latest} of ${scan.name}`;
  }
  if (phase !== lastPhase) {
    lastPhase = phase;
    refreshQueue();
  }
}

function fillForm(state) {
  if (formFilled) return;
  formFilled = true;
  $("elevations").value = state.defaults.elevations;
  $("azimuths").value = state.defaults.azimuths;
  const now = new Date();
  const pad = (n) => String(n).padStart(2, "0");
  $("name").value = `stone-${now.getFullYear()}${pad(now.getMonth() + 1)}${pad(now.getDate())}-${pad(now.getHours())}${pad(now.getMinutes())}`;
}

async function pollState() {
  try {
    const state = await api("/api/state");
    pollSeconds = state.poll_seconds;
    fillForm(state);
    showRig(state.rig);
    showScan(state);
    lastContact = clock();
    $("contact").textContent = `updated ${lastContact}`;
    if (contactLost) alertOperator("");
    contactLost = false;
  } catch (error) {
    contactLost = true;
    alertOperator(error.refused ? `The station refused: ${error.message}`
      : `No answer from the station${lastContact ? ` since ${lastContact}` : ""}: ${error.message}`);
  }
  setTimeout(pollState, pollSeconds * 1000);
}

function cell(row, text, className) {
  const td = row.insertCell();
  td.textContent = text;
  if (className) td.className = className;
  return td;
}

function showScans(answer) {
  const body = $("scans");
  body.replaceChildren();
  if (!answer.scans.length) {
    const row = body.insertRow();
    const queue = !answer.queue ? "No queue was given (--queue)"
      : answer.queue_exists ? `The queue ${answer.queue} is empty` : `No queue at ${answer.queue} yet (station batch add makes it)`;
    cell(row, `${queue}, and no scan was started here.`, "muted").colSpan = 5;
  }
  for (const item of answer.scans) {
    const row = body.insertRow();
    row.dataset.key = item.key;
    const name = cell(row, item.name, "scan-name");
    name.title = item.folder;
    const job = item.job;
    cell(row, job ? [job.state, job.stage, job.attempts ? `attempt ${job.attempts}` : "", job.reason || ""].filter(Boolean).join(" · ") : "scanned here");
    const stages = cell(row, "", "stages");
    for (const [stage, done] of Object.entries(item.stages)) {
      const chip = document.createElement("span");
      chip.className = done ? "stage done" : "stage";
      chip.textContent = done ? `${stage} ✓` : stage;
      stages.append(chip);
    }
    const gate = item.gate;
    const verdict = cell(row, !gate ? "–" : gate.pass === true ? "PASS" : gate.pass === false ? "QUARANTINED" : "unreadable",
      !gate ? "muted" : gate.pass === true ? "verdict pass" : "verdict fail");
    const reasons = gate ? (gate.error ? [gate.error] : gate.failed) : [];
    if (reasons.length) {
      const list = document.createElement("ul");
      for (const reason of reasons) list.append(Object.assign(document.createElement("li"), { textContent: reason }));
      verdict.append(list);
    }
    const report = cell(row, "", "report");
    if (item.report_url) {
      report.append(Object.assign(document.createElement("a"), { href: item.report_url, target: "_blank", rel: "noopener", textContent: "open report" }));
    } else {
      report.textContent = "–";
      report.classList.add("muted");
    }
  }
}

async function refreshQueue() {
  try {
    showScans(await api("/api/queue"));
  } catch (error) {
    alertOperator(`Could not read the scans: ${error.message}`);
  }
}

async function pollQueue() {
  await refreshQueue();
  setTimeout(pollQueue, Math.max(5, 5 * pollSeconds) * 1000);
}

async function press(path, body) {
  try {
    alertOperator("");
    const state = await api(path, body ?? {});
    showRig(state.rig);
    showScan(state);
  } catch (error) {
    alertOperator(error.message);
  }
}

$("start-form").addEventListener("submit", (event) => {
  event.preventDefault();
  press("/api/scan/start", {
    name: $("name").value.trim(),
    elevations: Number($("elevations").value),
    azimuths: Number($("azimuths").value),
    stone: $("stone").value.trim() || null,
  });
});
$("pause").addEventListener("click", () => press("/api/scan/pause"));
$("resume").addEventListener("click", () =>
  scan && scan.resumable ? press("/api/scan/start", scan.request) : press("/api/scan/resume"));
$("cancel").addEventListener("click", () => {
  if (confirm("Cancel this scan? The frames shot so far are kept, and Resume continues it.")) press("/api/scan/cancel");
});
$("operator-done").addEventListener("click", () => press("/api/operator/done"));

pollState();
pollQueue();
