// The technicians' page: start a run, follow it live (server-sent events), read the results.
// Plain JavaScript, no build step.  Units: the API is SI; the form takes the radius in mm.
"use strict";

const G = 9.80665;
const FINAL = ["completed", "aborted", "failed", "interrupted"];
let station = null;
let source = null;      // EventSource of the run on screen
let shownRun = null;

const $ = (sel) => document.querySelector(sel);
const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c]));

function token() { return localStorage.getItem("sinecal-token") || ""; }

function banner(text, kind) {
  const b = $("#banner");
  b.textContent = text || "";
  b.className = kind || "";
  b.hidden = !text;
}

async function api(method, path, body) {
  const headers = {"Accept": "application/json", "X-Station-Client": "page"};
  if (token()) headers["Authorization"] = "Bearer " + token();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, {method, headers, body: body === undefined ? undefined : JSON.stringify(body)});
  let data = null;
  const ct = r.headers.get("content-type") || "";
  if (ct.includes("json")) data = await r.json();
  return {status: r.status, ok: r.ok, data};
}

function detailText(data) {
  if (!data) return "";
  if (typeof data.detail === "string") return data.detail;
  if (Array.isArray(data.detail)) return data.detail.map((e) => (e.loc || []).slice(1).join(".") + ": " + e.msg).join("; ");
  return JSON.stringify(data);
}

// value ± std, both to the precision of 2 significant digits of the uncertainty
function fmtU(v, s) {
  if (v === null || v === undefined) return "—";
  if (s === null || s === undefined || !(s > 0)) return Number(v).toPrecision(6);
  const e = Math.floor(Math.log10(s)) - 1;
  const scale = Math.floor(Math.log10(Math.abs(v) || s));
  if (scale >= 5 || scale <= -4) {
    const m = Math.pow(10, scale);
    const digits = Math.max(0, scale - e);
    return `(${(v / m).toFixed(digits)} ± ${(s / m).toFixed(digits)})e${scale}`;
  }
  const d = Math.max(0, -e);
  return `${v.toFixed(d)} ± ${s.toFixed(d)}`;
}

// ------------------------------------------------------------------------------------------ header
async function refreshHealth() {
  try {
    const h = (await api("GET", "/health")).data;
    const link = (ok, name) => `<span class="${ok ? "ok" : "bad"}">${name} ${ok ? "●" : "○"}</span>`;
    $("#health").innerHTML = [
      link(h.rig.motor.connected && !h.rig.motor.watchdog_error, "motor"),
      link(h.rig.connected && !h.rig.daq.link_error, "DAQ"),
      link(h.database.ok, "database"),
      `<span>jobs queued ${h.worker.jobs.queued}</span>`].join(" ")
      + (h.drive && h.drive.standstill === false
         ? ` <span class="bad" id="drive-fault">DRIVE DOES NOT STOP: ${h.drive.detail}; use the hardware emergency stop</span>`
         : "");
    showLatch(h.estop);
  } catch (e) {
    $("#health").innerHTML = '<span class="bad">daemon unreachable</span>';
  }
}

// the emergency-stop latch: shown until an operator acknowledges it (token needed)
let latchShown = false;
function showLatch(e) {
  const latched = !!(e && e.latched);
  $("#latch").hidden = !latched;
  if (latched !== latchShown) $("#start").disabled = latched;  // leave a submission in progress alone
  latchShown = latched;
  if (latched) $("#latch-text").textContent = `since ${e.since} (${e.source}: ${e.detail}). No run starts until it is acknowledged.`;
}

$("#ack").addEventListener("click", async () => {
  const operator = $("#ack-operator").value.trim();
  if (!operator) { banner("acknowledge: enter the operator's name or initials", ""); return; }
  const r = await api("POST", "/stop/acknowledge", {operator});
  if (r.ok) banner(`emergency stop acknowledged by ${r.data.by}: ${r.data.detail}`, "info");
  else banner(`not acknowledged (${r.status}): ${detailText(r.data)}`, "");
  refreshHealth();
});

$("#token-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  localStorage.setItem("sinecal-token", $("#token").value.trim());
  $("#token-state").textContent = token() ? "saved" : "";
});

$("#estop").addEventListener("click", async () => {
  try {
    const r = await api("POST", "/stop");
    const d = r.data || {};
    const turning = d.drive && d.drive.standstill === false ? " - THE CRANK STILL TURNS: use the hardware emergency stop" : "";
    banner(`EMERGENCY STOP: ${d.detail || r.status}` + (d.aborted_runs && d.aborted_runs.length ? ` (aborted ${d.aborted_runs.join(", ")})` : "") + turning,
           d.motor_stopped ? "info" : "");
    refreshHealth();
  } catch (e) {
    banner("EMERGENCY STOP could not reach the daemon: use the hardware emergency stop");
  }
});

// ------------------------------------------------------------------------------------------ form
function frequencies() {
  return $("#frequencies").value.split(/[,;\s]+/).filter((s) => s.length).map(Number);
}

function maxRadiusM(f, topMass) {
  const L = station.limits;
  const M = topMass + L.moving_mass_without_top_kg;
  const w = 2 * Math.PI * f;
  return Math.min(L.crank_radius_m.max, (L.peak_force_limit_N / M - G) / (w * w));
}

function checkPlan() {
  if (!station) return;
  const tb = $("#plan-check tbody");
  tb.innerHTML = "";
  const m = Number($("#top_mass_kg").value);
  const r = Number($("#radius_mm").value) / 1000;
  const L = station.limits;
  frequencies().forEach((f, i) => {
    const rmax = maxRadiusM(f, m);
    const M = m + L.moving_mass_without_top_kg;
    const peak = M * (G + r * (2 * Math.PI * f) ** 2);
    const inRange = f >= L.crank_frequency_hz.min && f <= L.crank_frequency_hz.max;
    const ok = inRange && r >= L.crank_radius_m.min && r <= rmax;
    const tr = document.createElement("tr");
    if (!ok) tr.className = "bad";
    tr.innerHTML = `<td>${i}</td><td>${esc(f)}</td><td>${rmax > 0 ? (rmax * 1000).toPrecision(3) : "none"}</td>` +
      `<td>${Number.isFinite(peak) ? peak.toFixed(0) : "—"}</td><td>${ok ? "ok" : (inRange ? "radius too large" : "frequency outside the rig's range")}</td>`;
    tb.appendChild(tr);
  });
}

function showLimits() {
  const L = station.limits;
  $("#transducer_id").value = station.transducer_id;
  $("#hint-transducer").textContent = `mounted: ${station.transducer_id} (capacity ${station.capacity_N} N)`;
  $("#top_mass_kg").value = station.default_top_mass_kg;
  $("#hint-mass").textContent = `moving mass = top mass + ${L.moving_mass_without_top_kg.toFixed(3)} kg (adaption and end mass)`;
  $("#frequencies").value = station.default_steps.map((s) => s.crank_frequency_hz).join(", ");
  $("#hint-frequency").textContent = `rig range ${L.crank_frequency_hz.min}–${L.crank_frequency_hz.max} Hz, 1–200 steps`;
  $("#radius_mm").value = Math.min(...station.default_steps.map((s) => s.crank_radius_m)) * 1000;
  $("#hint-radius").textContent = `rig range ${L.crank_radius_m.min * 1000}–${L.crank_radius_m.max * 1000} mm`;
  $("#hint-force").textContent = `Peak force M·(g + r·ω²) must stay below ${L.peak_force_limit_N.toFixed(0)} N; ` +
    `each step records ${station.default_record_s} s after ${station.default_settle_s} s settling.`;
  $("#station-name").textContent = `${station.name} · ${station.transducer_id}`;
  $("#sim-badge").hidden = !station.simulated;
  checkPlan();
}

["#frequencies", "#radius_mm", "#top_mass_kg"].forEach((s) => $(s).addEventListener("input", checkPlan));

$("#run-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  document.querySelectorAll("#run-form .err").forEach((e) => { e.textContent = ""; });
  const r = Number($("#radius_mm").value) / 1000;
  const body = {
    transducer_id: $("#transducer_id").value.trim(),
    top_mass_kg: Number($("#top_mass_kg").value),
    steps: frequencies().map((f) => ({crank_frequency_hz: f, crank_radius_m: r})),
  };
  $("#start").disabled = true;
  try {
    const res = await api("POST", "/runs", body);
    if (res.status === 202) {
      location.hash = `#/runs/${res.data.id}`;
      return;
    }
    if (res.status === 422 && Array.isArray(res.data.detail)) {
      for (const e of res.data.detail) {
        const field = [...(e.loc || [])].reverse().find((x) => typeof x === "string") || "";
        const slot = document.querySelector(`#run-form .err[data-for="${field}"]`);
        (slot || $("#form-msg")).textContent = `${(e.loc || []).slice(1).join(".")}: ${e.msg}`;
      }
      return;
    }
    $("#form-msg").textContent = res.status === 401 ? "enter the station token (top of the page) to start runs"
      : `${res.status}: ${detailText(res.data)}`;
  } finally {
    $("#start").disabled = false;
  }
});

async function refreshRuns() {
  const res = await api("GET", "/runs?limit=20");
  if (!res.ok) return;
  const tb = $("#runs tbody");
  tb.innerHTML = "";
  for (const r of res.data.runs) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td><a href="#/runs/${esc(r.id)}">${esc(r.id)}</a></td><td class="state ${esc(r.state)}">${esc(r.state)}</td>` +
      `<td>${r.steps.map((s) => s.crank_frequency_hz).join(", ")} Hz</td><td>${new Date(r.created).toLocaleString()}</td><td>${r.lost_samples}</td>`;
    tb.appendChild(tr);
  }
}

// ------------------------------------------------------------------------------------------ run view
function showStatus(st) {
  $("#run-state").textContent = st.state;
  $("#run-state").className = "state " + st.state;
  $("#run-step").textContent = st.current_step === null ? "" :
    `step ${st.current_step + 1}/${st.n_steps} (${st.steps[st.current_step].crank_frequency_hz} Hz) ${st.step_state}`;
  $("#run-progress").value = st.progress;
  $("#run-samples").textContent = st.samples;
  $("#run-lost").textContent = st.lost_samples;
  $("#run-message").textContent = st.reason || st.message;
  $("#abort").hidden = !(st.state === "queued" || st.state === "running");
  if (FINAL.includes(st.state)) {
    if (st.state === "completed") loadResults(st.id);
    else if (st.recording) { $("#ended").hidden = false; $("#ended-recording").href = st.links.recording; }
  }
}

function follow(id) {
  if (source) source.close();
  source = new EventSource(`/runs/${encodeURIComponent(id)}/events`);
  const onEvent = (ev) => {
    const st = JSON.parse(ev.data);
    if (st.id === shownRun) showStatus(st);
  };
  source.addEventListener("status", onEvent);
  source.addEventListener("result", async () => {  // a listed method has its outcome: refresh the comparison
    if ($("#results").dataset.run !== id) return;  // the primary's results load with the completed status
    const res = await api("GET", `/runs/${encodeURIComponent(id)}/results`);
    if (res.ok && id === shownRun) showMethods(res.data.methods);
  });
  source.addEventListener("end", (ev) => { onEvent(ev); source.close(); source = null; });
  source.onerror = () => { /* the browser reconnects by itself; a final state closes the stream */ };
}

function structureText(assumptions, determined) {
  // the model structure the result rests on, and what the data determine under it
  const st = assumptions.structure;
  if (!st) return "";
  let t = `structure: ${st.model}; displacement chain ${st.displacement_chain.response}` +
    (st.displacement_chain.response === "resonance" ? ` at ${st.displacement_chain.resonance_hz} Hz` : "");
  const ks = determined.series_stiffness;
  if (ks) t += `; series stiffness of transducer and coupling ${fmtU(ks.value, ks.combined)} N/m`;
  const alone = determined.transducer_stiffness_alone;
  if (alone) t += `; k_f alone ${alone.conditional_on}`;
  return t;
}

function showMethods(methods) {
  // every listed identification side by side: values, z against the primary, why a value is withheld
  const table = $("#methods");
  const names = [];
  for (const m of methods) for (const p of m.parameters) if (!names.includes(p.name)) names.push(p.name);
  table.querySelector("thead").innerHTML = "<tr><th>method</th><th>status</th>" +
    names.map((n) => `<th>${esc(n)}</th>`).join("") + "<th>time (s)</th><th>seed</th></tr>";
  const tb = table.querySelector("tbody");
  tb.innerHTML = "";
  for (const m of methods) {
    const tr = document.createElement("tr");
    tr.dataset.method = `${m.method}/${m.model}`;
    tr.dataset.status = m.status;
    const model = m.result_model && m.result_model !== m.model ? `${m.model} → ${m.result_model}` : m.model;
    let cells = `<td>${m.primary ? "★ " : ""}${esc(m.method)} (${esc(model)})</td><td class="state ${esc(m.status)}">${esc(m.status)}</td>`;
    if (m.status !== "done") {
      cells += `<td colspan="${names.length}" class="reason">${esc(m.reason || (m.status === "running" ? "computing…" : "waiting for a worker"))}</td>`;
    } else {
      const ps = Object.fromEntries(m.parameters.map((p) => [p.name, p]));
      for (const n of names) {
        const p = ps[n];
        const a = (m.agreement || {})[n];
        let c = !p ? "—" : p.identifiable ? `${fmtU(p.value, p.std)} ${esc(p.unit)}` : `withheld: ${esc(p.reason)}`;
        if (a && a.z !== null) c += ` <span class="z">(z = ${a.z.toFixed(2)})</span>`;
        else if (a && a.reason && p && p.identifiable) c += ` <span class="z">(no z: ${esc(a.reason)})</span>`;
        cells += `<td data-param="${esc(n)}">${c}</td>`;
      }
    }
    cells += `<td>${m.compute_s === null ? "—" : m.compute_s.toFixed(2)}</td><td>${m.seed}</td>`;
    tr.innerHTML = cells;
    tb.appendChild(tr);
  }
  table.hidden = !methods.length;
}

async function loadResults(id) {
  if ($("#results").dataset.run === id) return;
  const res = await api("GET", `/runs/${encodeURIComponent(id)}/results`);
  if (!res.ok) { $("#run-message").textContent = detailText(res.data); return; }
  const d = res.data;
  $("#results").dataset.run = id;
  $("#res-model").textContent = `method ${d.method}, model ${d.model}` + (d.notes.length ? ` — ${d.notes.join("; ")}` : "");
  const cl = $("#res-checks");
  cl.innerHTML = "";
  for (const c of d.checks || []) {
    const li = document.createElement("li");
    li.dataset.check = c.name;
    li.textContent = `${c.severity}: ${c.name}: ${c.message}`;
    cl.appendChild(li);
  }
  const em = (d.assumptions || {}).end_mass_kg;
  $("#res-assumptions").textContent = em ? `end mass m_e = ${em.value} kg (${em.source}` +
    (em.std === null ? ": assumed, no uncertainty; S, k_f, b_f are conditional on it)" : `, u = ${em.std} kg)`) : "";
  $("#res-structure").textContent = structureText(d.assumptions || {}, d.determined || {});
  const tb = $("#params tbody");
  tb.innerHTML = "";
  for (const p of d.parameters) {
    const tr = document.createElement("tr");
    tr.dataset.param = p.name;
    tr.innerHTML = `<td>${esc(p.name)}</td><td class="value">${p.identifiable ? fmtU(p.value, p.std) : "not identifiable"}</td>` +
      `<td>${esc(p.unit)}</td><td>${p.identifiable ? (p.flag ? esc(p.flag) + ": " + esc(p.reason) : "yes") : "no: " + esc(p.reason)}</td>`;
    tb.appendChild(tr);
  }
  if (d.fit) {
    $("#res-fit").textContent = `fit: χ²/dof ${d.fit.chi2_per_dof === null ? "—" : d.fit.chi2_per_dof.toFixed(2)}, ` +
      `mean square residual ${d.fit.mse === null ? "—" : d.fit.mse.toExponential(2)} V², ${d.fit.n_points} points` +
      (d.identifiability ? `, condition number ${d.identifiability.condition_number === null ? "—" : d.identifiability.condition_number.toPrecision(3)}` : "");
  }
  const fb = $("#frf tbody");
  fb.innerHTML = "";
  for (const s of d.frequency_response) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td>${s.index}</td><td>${s.frequency_hz.toFixed(4)}</td><td>${fmtU(s.H_magnitude, s.H_magnitude_std)}</td>` +
      `<td>${fmtU(s.H_phase_deg, s.H_phase_std_deg)}</td><td>${s.n_samples}</td>`;
    fb.appendChild(tr);
  }
  const plots = $("#plots");
  plots.innerHTML = "";
  const names = Object.keys(d.plots);
  if (!names.length) plots.textContent = "plots are not available on this station (the plots module is not installed)";
  for (const n of names) {
    const fig = document.createElement("figure");
    fig.innerHTML = `<img alt="${esc(n)} plot" data-plot="${esc(n)}" src="${esc(d.plots[n])}"><figcaption class="small">${esc(n)}</figcaption>`;
    plots.appendChild(fig);
  }
  const rl = $("#report-link");
  if (d.report) { rl.href = d.report; rl.textContent = "calibration report"; } else { rl.removeAttribute("href"); rl.textContent = "report not available"; }
  $("#recording-link").href = `/runs/${encodeURIComponent(id)}/recording`;
  showCertificate(id);
  showMethods(d.methods || []);
  $("#results").hidden = false;
  loadDiscrepancy(d.discrepancy);
}

// the run's certificate: the draft until a second person with the approver role issues it
function showCertificate(id) {
  const base = `/runs/${encodeURIComponent(id)}/certificate`;
  for (const ext of ["html", "pdf", "xml"]) $(`#cert-${ext}`).href = `${base}.${ext}`;
  $("#cert-form").onsubmit = async (ev) => {
    ev.preventDefault();
    const res = await api("POST", base, {prepared_by: $("#cert-prepared").value.trim(), approver: $("#cert-approver").value.trim()});
    $("#cert-msg").textContent = res.ok ? `issued ${res.data.number}` : (detailText(res.data) || `refused (${res.status})`);
  };
}

async function loadDiscrepancy(url) {
  const box = $("#discrepancy");
  box.textContent = "loading…";
  let res = await api("GET", url);
  if (res.status === 404 && token()) {  // not computed yet: computing and storing it needs the token
    box.textContent = "analysing…";
    res = await api("POST", url);
  }
  if (!res.ok) {
    box.textContent = res.status === 404 ? "not analysed yet: enter the station token (top of the page) to analyse this run"
      : `not available: ${detailText(res.data)}`;
    return;
  }
  const d = res.data;
  const mV = (v) => (v === null ? "—" : (v * 1000).toPrecision(3) + " mV");
  let html = `<p>force residual (RMS) of the model: ${mV(d.base_gap)} → ${mV(d.final_gap)} after the effects below</p>`;
  html += d.effects.length ? "<ul>" + d.effects.map((e) => `<li>${esc(e.name)} (gap after: ${mV(e.gap_after)})</li>`).join("") + "</ul>"
    : "<p>no catalogue effect needed: the model explains the measurement</p>";
  if (d.ties && d.ties.length) {
    html += '<div class="ties"><p><b>not decided by these data</b> (k_f and b_f carry the spread):</p><ul>'
      + d.ties.map((t) => `<li>${esc(t.kind)}: ${t.candidates.map((c) => esc(c.effects.join(" + ") || "base model")
        + ` (k_f ${c.k_f.value === null ? "—" : c.k_f.value.toPrecision(6)} N/m)`).join(" vs ")}</li>`).join("") + "</ul></div>";
  }
  if (d.unexplained.length) html += "<p>unexplained: " + d.unexplained.map(esc).join("; ") + "</p>";
  if (d.notes && d.notes.length) html += "<ul class=\"notes\">" + d.notes.map((n) => `<li>${esc(n)}</li>`).join("") + "</ul>";
  html += proposalHtml(d.proposal);
  box.innerHTML = html;
  const btn = $("#run-proposal");
  if (btn) btn.addEventListener("click", () => runProposal(shownRun));
  box.dataset.loaded = "1";
}

// the follow-up run that would settle a tie (or pin down k_f): its added steps and one button
function proposalHtml(p) {
  if (!p || !p.steps || !p.steps.length) return "";
  const gain = p.measure === "bits" ? `${Number(p.expected_information_gain).toPrecision(3)} bits`
    : `expected Δχ² between the explanations ${Number(p.current).toPrecision(3)} → ${Number(p.expected_information_gain).toPrecision(3)}`;
  const rows = p.steps.map((s) => `<tr><td>${Number(s.crank_frequency_hz)}</td><td>${(s.crank_radius_m * 1000).toPrecision(3)}</td></tr>`).join("");
  return `<div id="proposal"><h3>Next run that settles it</h3><p class="small">${esc(p.reason)}; ${esc(gain)}</p>` +
    `<table><thead><tr><th>added step f / Hz</th><th>radius / mm</th></tr></thead><tbody>${rows}</tbody></table>` +
    `<p class="small">the run repeats this run's ${p.run_steps.length - p.steps.length} steps and adds these ${p.steps.length}</p>` +
    `<button type="button" id="run-proposal">run the proposed steps</button> <span id="proposal-msg"></span></div>`;
}

async function runProposal(id) {
  const msg = $("#proposal-msg");
  $("#run-proposal").disabled = true;
  try {
    const p = await api("GET", `/runs/${encodeURIComponent(id)}/proposal`);
    if (!p.ok || !p.data.request) { msg.textContent = p.ok ? "nothing to run" : detailText(p.data); return; }
    const res = await api("POST", "/runs", p.data.request);
    if (res.status === 202) { location.hash = `#/runs/${res.data.id}`; return; }
    msg.textContent = res.status === 401 ? "enter the station token (top of the page) to start runs"
      : `${res.status}: ${detailText(res.data)}`;
  } finally {
    const b = $("#run-proposal");
    if (b) b.disabled = false;
  }
}

$("#abort").addEventListener("click", async () => {
  const res = await api("POST", `/runs/${encodeURIComponent(shownRun)}/abort`);
  if (!res.ok) banner(res.status === 401 ? "enter the station token to abort runs (or use EMERGENCY STOP)" : detailText(res.data));
});

// ------------------------------------------------------------------------------------------ routing
async function route() {
  const m = location.hash.match(/^#\/runs\/([^/]+)$/);
  $("#view-home").hidden = !!m;
  $("#view-run").hidden = !m;
  if (m) {
    const id = decodeURIComponent(m[1]);
    shownRun = id;
    $("#run-id").textContent = id;
    $("#results").hidden = true;
    $("#ended").hidden = true;
    delete $("#results").dataset.run;
    const res = await api("GET", `/runs/${encodeURIComponent(id)}`);
    if (!res.ok) { $("#run-message").textContent = detailText(res.data); return; }
    showStatus(res.data);
    if (!FINAL.includes(res.data.state)) follow(id);
  } else {
    shownRun = null;
    if (source) { source.close(); source = null; }
    refreshRuns();
  }
}

async function init() {
  $("#token").value = token();
  $("#token-state").textContent = token() ? "saved" : "";
  station = (await api("GET", "/station")).data;
  showLimits();
  window.addEventListener("hashchange", route);
  await route();
  refreshHealth();
  setInterval(refreshHealth, 5000);
  setInterval(() => { if (!shownRun) refreshRuns(); }, 5000);
}

init();
