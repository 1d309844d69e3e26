// The technicians' page: start a run, follow it live (server-sent events), read the results.
// Plain JavaScript, no build step.  Units: the API is SI; the form takes the radius in mm.
"use strict";

const G = 9.80665;
const FINAL = ["completed", "aborted", "failed", "interrupted"];
let station = null;
let source = null;      // EventSource of the run on screen
let methodsSeq = 0;     // the latest request for the methods table (an older answer never overwrites it)
let shownRun = null;
let me = null;          // the logged-in user ({name, role, permissions}) or null
let register = null;    // GET /register

const $ = (sel) => document.querySelector(sel);
const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c]));

function banner(text, kind) {
  const b = $("#banner");
  b.textContent = text || "";
  b.className = kind || "";
  b.hidden = !text;
}

async function api(method, path, body) {
  const headers = {"Accept": "application/json", "X-Station-Client": "page"};  // the session cookie goes along
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, {method, headers, body: body === undefined ? undefined : JSON.stringify(body)});
  let data = null;
  const ct = r.headers.get("content-type") || "";
  if (ct.includes("json")) data = await r.json();
  if (r.status === 401 && me && path !== "/login") { me = null; showMe(); dropSession(); }  // the session ended
  return {status: r.status, ok: r.ok, data};
}

// what a refusal says, with what to do: the API's reason (401: log in; 403: the role)
// (the API answers RFC 9457 problem details: `type` says the kind of refusal, `detail` what happened)
const problemKind = (data) => String((data && data.type) || "").replace("urn:sinecal:problem:", "");
function refusal(res, action) {
  if (res.status === 401 && problemKind(res.data) === "not-logged-in")
    return `You are not logged in: log in at the top of the page to ${action}.`;
  if (res.status === 401) return `${action}: ${detailText(res.data)}`;
  return `${action} refused (${res.status}): ${detailText(res.data)}`;
}

const may = (perm) => !!(me && me.permissions.includes(perm));

function detailText(data) {
  if (!data) return "";
  if (Array.isArray(data.errors)) return data.errors.map((e) => locText(e.loc) + ": " + e.msg).join("; ");
  if (typeof data.detail === "string") return data.detail;
  return JSON.stringify(data);
}

// a field's place in the request, for people: steps count from 1 ("step 2.crank_radius_m")
function locText(loc) {
  const l = (loc || []).slice(1);
  const i = l.indexOf("steps");
  if (i >= 0 && typeof l[i + 1] === "number") return `step ${l[i + 1] + 1}` + (l[i + 2] ? " " + l.slice(i + 2).join(".") : "");
  return l.join(".");
}

// ------------------------------------------------------------------------------------------ login
function showMe() {
  $("#login-form").hidden = !!me;
  $("#me").hidden = !me;
  $("#login-hint").hidden = !!me || !(station && station.simulated);
  if (me) $("#me-name").textContent = `${me.name} (${me.role})`;
  $("#nav-users").hidden = !may("admin");
  if (!may("admin")) hideUsers();
  const ap = $("#approve");
  if (ap) ap.disabled = !may("approve");
  applyRoles();
}

// actions only for the roles that may use them, and only while they apply
let shownStatus = null;   // the status of the run on screen
let shownIssued = [];     // its issued certificates (not replaced)
function applyRoles() {
  const st = shownStatus;
  const own = !!(st && me && st.operator === me.name);  // nobody approves their own run
  $("#abort").hidden = !(st && may("run") && (st.state === "queued" || st.state === "running"));
  $("#approve-controls").hidden = !may("approve") || own;
  $("#cert-issue").hidden = !may("approve") || own || shownIssued.length > 0;
  $("#cert-state").textContent = shownIssued.length ? `issued: ${shownIssued.map((c) => c.number).join(", ")}` : "draft";
}

// an ended or expired session's cookie (HttpOnly: only the server can drop it) would have every
// later request refused, reading too: log out to drop it
async function dropSession() { await api("POST", "/logout"); }

async function loadMe() {
  const r = await api("GET", "/me");
  me = r.ok && r.data.user ? r.data.user : null;
  if (r.status === 401) { banner(`${detailText(r.data)}`, ""); await dropSession(); }
  showMe();
}

$("#login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const r = await api("POST", "/login", {name: $("#login-name").value.trim(), password: $("#login-password").value});
  $("#login-password").value = "";
  if (r.ok) { me = r.data.user; banner("", ""); showMe(); route(); }
  else banner(refusal(r, "log in"), "");
});

$("#logout").addEventListener("click", async () => {
  await api("POST", "/logout");
  me = null;
  showMe();
  route();
});

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
  if (latched) $("#latch-text").textContent = `since ${localTime(e.since)} (${e.source}: ${e.detail}). No run starts until it is acknowledged.`;
}

$("#ack").addEventListener("click", async () => {
  const r = await api("POST", "/stop/acknowledge", {note: $("#ack-note").value.trim()});
  if (r.ok) banner(`emergency stop acknowledged by ${r.data.by}: ${r.data.detail}`, "info");
  else banner(refusal(r, "acknowledge"), "");
  refreshHealth();
});

// the stop goes to the daemon's stop port first (a listener of its own, not crowded by other
// clients), then, if that cannot be reached or is not the station's, to this page's own port
async function stopPortStop() {
  if (!station || !station.stop_port) return null;
  try {
    const r = await fetch(`${location.protocol}//${location.hostname}:${station.stop_port}/stop?client=page`,
                          {method: "POST", credentials: "include"});
    const data = await r.json();
    return r.ok && typeof data.stop_commanded === "boolean" ? {status: r.status, ok: r.ok, data} : null;
  } catch (e) {
    return null;
  }
}

$("#estop").addEventListener("click", async () => {
  try {
    const r = (await stopPortStop()) || (await api("POST", "/stop"));
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
const numbers = (text) => text.split(/[,;\s]+/).filter((s) => s.length).map(Number);
function frequencies() { return numbers($("#frequencies").value); }
// the radius of each step in m: one value per step, or one for all
function radii() {
  const r = numbers($("#radius_mm").value).map((x) => x / 1000);
  const n = frequencies().length;
  return r.length === 1 ? Array(n).fill(r[0]) : Array.from({length: n}, (_, i) => (i < r.length ? r[i] : NaN));
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
  const rs = radii();
  const L = station.limits;
  frequencies().forEach((f, i) => {
    const r = rs[i];
    const rmax = maxRadiusM(f, m);
    const M = m + L.moving_mass_without_top_kg;
    const peak = M * (G + r * (2 * Math.PI * f) ** 2);
    const inRange = f >= L.crank_frequency_hz.min && f <= L.crank_frequency_hz.max;
    const ok = inRange && r >= L.crank_radius_m.min && r <= rmax;
    const tr = document.createElement("tr");
    if (!ok) tr.className = "bad";
    const why = !inRange ? `frequency outside the rig's range ${L.crank_frequency_hz.min}–${L.crank_frequency_hz.max} Hz`
      : !Number.isFinite(r) ? "no radius for this step" : r < L.crank_radius_m.min ? "radius below the rig's minimum" : "radius too large";
    tr.innerHTML = `<td>${i + 1}</td><td>${esc(f)}</td><td>${Number.isFinite(r) ? (r * 1000).toPrecision(3) : "—"}</td>` +
      `<td>${rmax > 0 ? (rmax * 1000).toPrecision(3) : "none"}</td>` +
      `<td>${Number.isFinite(peak) ? peak.toFixed(0) : "—"}</td><td>${ok ? "ok" : why}</td>`;
    tb.appendChild(tr);
  });
}

function showLimits() {
  const L = station.limits;
  $("#top_mass_kg").value = station.default_top_mass_kg;
  $("#hint-mass").textContent = `moving mass = top mass + ${L.moving_mass_without_top_kg.toFixed(3)} kg (adaption and end mass)`;
  $("#frequencies").value = station.default_steps.map((s) => s.crank_frequency_hz).join(", ");
  $("#hint-frequency").textContent = `rig range ${L.crank_frequency_hz.min}–${L.crank_frequency_hz.max} Hz, 1–200 steps`;
  // the configuration's plan: a radius per step (large at low frequencies, where the force allows it)
  $("#radius_mm").value = station.default_steps.map((s) => +(s.crank_radius_m * 1000).toPrecision(4)).join(", ");
  $("#hint-radius").textContent = `rig range ${L.crank_radius_m.min * 1000}–${L.crank_radius_m.max * 1000} mm; ` +
    "each step's maximum is in the table below";
  $("#hint-force").textContent = `Peak force M·(g + r·ω²) must stay below ${L.peak_force_limit_N.toFixed(0)} N; ` +
    `each step records ${station.default_record_s} s after ${station.default_settle_s} s settling.`;
  showEnvironmentInputs(station.environment);
  $("#station-name").textContent = station.name;
  $("#sim-badge").hidden = !station.simulated;
  $("#login-hint").hidden = !!me || !station.simulated;
  checkPlan();
}

// the room conditions: the API's accepted ranges as the inputs' min/max; empty = the configuration's
const ENV_INPUTS = [["temperature_c", "#hint-temperature", "°C"], ["relative_humidity_pct", "#hint-humidity", "%"]];
function showEnvironmentInputs(env) {
  if (!env) return;
  for (const [name, hint, unit] of ENV_INPUTS) {
    const input = $(`#${name}`);
    input.min = env[name].min;
    input.max = env[name].max;
    const dflt = env[`default_${name}`];
    $(hint).textContent = `${env[name].min} to ${env[name].max} ${unit}; empty: ` + (dflt !== null
      ? `the configuration's ${dflt} ${unit}` : env.otherwise === "not recorded" ? "not recorded (none configured)"
      : `the ${env.otherwise} (none configured)`);
  }
}

// the request's environment: the entered values, or null when both are empty (the configuration's)
function environmentBody() {
  const env = {};
  for (const [name] of ENV_INPUTS) {
    const input = $(`#${name}`);
    if (input.validity.badInput) throw Object.assign(new Error("not a number"), {field: name});
    if (input.value.trim() !== "") env[name] = Number(input.value);
  }
  return Object.keys(env).length ? env : null;
}

function environmentText(env) {
  if (!env) return "room conditions: not recorded";
  const q = (v, u, unit) => (v === null || v === undefined ? "not given" : `${fmtU(v, u)} ${unit}`);
  return `room conditions: air ${q(env.temperature_c, env.temperature_std_c, "°C")}, ` +
    `relative humidity ${q(env.relative_humidity_pct, env.relative_humidity_std_pct, "%")} (${env.source})`;
}

// the register: the transducer select (the mounted one chosen) and the standards in use
async function loadRegister() {
  const r = await api("GET", "/register");
  if (!r.ok) return;
  register = r.data;
  const sel = $("#transducer_id");
  const keep = sel.value;
  sel.innerHTML = register.transducers.map((t) => `<option value="${esc(t.id)}">${esc(t.id)}${t.id === register.mounted ? " (mounted)" : ""}` +
    ` — ${esc(t.type || "")} ${t.capacity_N} N${t.owner ? ", " + esc(t.owner) : ""}</option>`).join("");
  sel.value = keep && register.transducers.some((t) => t.id === keep) ? keep : (register.mounted || "");
  transducerHint();
  $("#standards").innerHTML = register.standards.map((s) => `<label class="std${s.overdue ? " bad" : ""}">` +
    `<input type="checkbox" value="${esc(s.id)}"${s.in_use ? " checked" : ""}> ${esc(s.id)} (${esc(s.kind)}, ${esc(s.certificate_id)}, ` +
    `due ${esc(s.due_date)}${s.overdue ? " — OVERDUE" : ""})</label>`).join("") || '<span class="hint">none registered</span>';
}

function transducerHint() {
  const t = register && register.transducers.find((x) => x.id === $("#transducer_id").value);
  $("#hint-transducer").innerHTML = t ? `capacity ${t.capacity_N} N, ${t.sensitivity_V_per_N} V/N` +
    (t.end_mass_kg ? `, end mass ${t.end_mass_kg} kg` : "") + ` · <a href="#/transducers/${encodeURIComponent(t.id)}">history</a>` : "";
}
$("#transducer_id").addEventListener("change", transducerHint);

$("#mount").addEventListener("click", async () => {
  const r = await api("POST", "/register/mount", {transducer_id: $("#transducer_id").value});
  if (r.ok) { banner(`${r.data.id} is recorded as mounted`, "info"); loadRegister(); }
  else banner(refusal(r, "mount"), "");
});

["#frequencies", "#radius_mm", "#top_mass_kg"].forEach((s) => $(s).addEventListener("input", checkPlan));

$("#run-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  document.querySelectorAll("#run-form .err").forEach((e) => { e.textContent = ""; });
  const rs = radii();
  const body = {
    transducer_id: $("#transducer_id").value,
    top_mass_kg: Number($("#top_mass_kg").value),
    steps: frequencies().map((f, i) => ({crank_frequency_hz: f, crank_radius_m: rs[i]})),
    standards: [...document.querySelectorAll("#standards input:checked")].map((c) => c.value),
  };
  if (rs.some((r) => !Number.isFinite(r))) {
    document.querySelector('#run-form .err[data-for="crank_radius_m"]').textContent = "give one radius per step, or one for all";
    return;
  }
  try {
    const env = environmentBody();
    if (env) body.environment = env;
  } catch (e) {
    document.querySelector(`#run-form .err[data-for="${e.field}"]`).textContent = "not a number";
    return;
  }
  $("#start").disabled = true;
  try {
    const res = await api("POST", "/runs", body);
    if (res.status === 202) {
      location.hash = `#/runs/${res.data.id}`;
      return;
    }
    if (res.status === 422 && Array.isArray(res.data.errors)) {
      for (const e of res.data.errors) {
        const field = [...(e.loc || [])].reverse().find((x) => typeof x === "string") || "";
        const slot = document.querySelector(`#run-form .err[data-for="${field}"]`);
        (slot || $("#form-msg")).textContent = `${locText(e.loc)}: ${e.msg}`;
      }
      return;
    }
    $("#form-msg").textContent = refusal(res, "start a run");
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
      `<td><a href="#/transducers/${encodeURIComponent(r.transducer_id)}">${esc(r.transducer_id)}</a></td>` +
      `<td>${r.steps.map((s) => s.crank_frequency_hz).join(", ")} Hz</td><td>${esc(localTime(r.created))}</td><td>${r.lost_samples}</td>`;
    tb.appendChild(tr);
  }
}

// ------------------------------------------------------------------------------------------ run view
function showStatus(st) {
  $("#run-state").textContent = st.state;
  $("#run-state").className = "state " + st.state;
  const stopping = st.state === "running" && st.step_state === "stopping";
  $("#run-step").textContent = st.current_step === null ? "" : stopping ? "all steps recorded; the crank ramps down to standstill" :
    `step ${st.current_step + 1} of ${st.n_steps} (${withUnit(st.steps[st.current_step].crank_frequency_hz, "Hz")}) ${st.step_state}`;
  $("#run-eta").textContent = timeLeftText(st);
  $("#run-history").href = `#/transducers/${encodeURIComponent(st.transducer_id)}`;
  $("#run-progress").value = st.progress;
  $("#run-samples").textContent = st.samples;
  $("#run-lost").textContent = st.lost_samples;
  $("#run-message").textContent = st.reason || st.message;
  shownStatus = st;
  applyRoles();
  if (FINAL.includes(st.state)) {
    if (st.state === "completed") loadResults(st.id);
    else if (st.recording) { $("#ended").hidden = false; $("#ended-recording").href = st.links.recording; }
  }
}

// the time left of a recording run, extrapolated from its progress so far (the rig's ramps, settling
// and recording all count; a run queued or identifying has none)
function timeLeftText(st) {
  if (st.state !== "running" || !st.started || !(st.progress > 0.02) || st.progress >= 1) return "";
  const elapsed = (Date.now() - new Date(st.started).getTime()) / 1000;
  if (!(elapsed > 0)) return "";
  return `about ${durationText(elapsed * (1 - st.progress) / st.progress)} left`;
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
    const seq = ++methodsSeq;
    const res = await api("GET", `/runs/${encodeURIComponent(id)}/results`);
    if (res.ok && id === shownRun && seq === methodsSeq) showMethods(res.data.methods);
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
    names.map((n) => `<th>${esc(n)}</th>`).join("") + "<th>time</th><th>seed</th></tr>";
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
        let c = !p ? "—" : p.identifiable ? esc(withUnit(fmtU(p.value, p.std), p.unit)) : (/^withheld\b/.test(p.reason) ? esc(p.reason) : `withheld: ${esc(p.reason)}`);
        if (a && a.z !== null) c += ` <span class="z">(z = ${a.z.toFixed(2)})</span>`;
        else if (a && a.reason && p && p.identifiable) c += ` <span class="z">(no z: ${esc(a.reason)})</span>`;
        cells += `<td data-param="${esc(n)}">${c}</td>`;
      }
    }
    cells += `<td>${m.compute_s === null ? "—" : withUnit(m.compute_s.toFixed(2), "s")}</td><td>${m.seed}</td>`;
    tr.innerHTML = cells;
    tb.appendChild(tr);
  }
  table.hidden = !methods.length;
  $("#methods-summary").textContent = methodsSummary(methods);
}

// the result in a sentence: what was determined, from how many steps, and whether anything needs a look
function resultSummary(d) {
  const got = d.parameters.filter((p) => p.identifiable).map((p) => QUANTITY_WORDS[p.name] || p.name);
  const missing = d.parameters.filter((p) => !p.identifiable).map((p) => QUANTITY_WORDS[p.name] || p.name);
  const look = (d.checks || []).filter((c) => c.severity !== "info").length;
  const conditional = d.parameters.filter((p) => p.identifiable && p.reason).length;
  return (got.length ? `The run determined the ${listText(got)}, each with its uncertainty (below).` : "The run determined nothing.") +
    (missing.length ? ` It could not determine the ${listText(missing)}.` : "") +
    (conditional ? " Some values rest on a condition (see their remarks)." : "") +
    (look ? ` ${look === 1 ? "One finding needs" : `${look} findings need`} checking before the results are used.` : " Nothing needs checking.");
}

const listText = (xs) => (xs.length < 2 ? xs.join("") : `${xs.slice(0, -1).join(", ")} and ${xs[xs.length - 1]}`);

// a parameter's remark: plain first, the identification's reason behind "why"
function parameterRemark(p) {
  const why = p.reason ? ` <details><summary>why</summary>${esc(p.reason)}</details>` : "";
  if (!p.identifiable) return `not determined by this run${why}`;
  if (p.flag) return `${esc(p.flag)}${why}`;
  return p.reason ? `determined, under a condition${why}` : "determined";
}

// the other methods in a sentence: do they agree with the primary within their uncertainties?
function methodsSummary(methods) {
  const others = methods.filter((m) => !m.primary);
  if (!others.length) return "Only one method was run for this result.";
  const open = others.filter((m) => m.status !== "done" && m.status !== "failed" && m.status !== "refused").length;
  const zs = others.filter((m) => m.status === "done").flatMap((m) => Object.values(m.agreement || {}).map((a) => a && a.z))
    .filter((z) => typeof z === "number");
  const agree = zs.length && zs.every((z) => Math.abs(z) <= 2);
  return `${others.length} other ${others.length === 1 ? "method checks" : "methods check"} the result` +
    (open ? `; ${open} still computing` : "") +
    (zs.length ? (agree ? ": they agree within their uncertainties." : ": some differ by more than their uncertainties (see the table).")
      : others.some((m) => m.status === "done") ? ": none of their values can be compared with it (the table says why)." : ".");
}

async function loadResults(id) {
  if ($("#results").dataset.run === id) return;
  const seq = ++methodsSeq;
  const res = await api("GET", `/runs/${encodeURIComponent(id)}/results`);
  if (!res.ok) { $("#run-message").textContent = detailText(res.data); return; }
  const d = res.data;
  $("#results").dataset.run = id;
  $("#res-summary").textContent = resultSummary(d);
  $("#res-model").textContent = `method ${d.method}, model ${d.model}` + (d.notes.length ? ` — ${d.notes.join("; ")}` : "");
  const nSteps = (shownStatus && shownStatus.n_steps) || d.frequency_response.length;
  $("#res-checks").innerHTML = (d.checks || []).map((c) => `<li data-check="${esc(c.name)}" data-severity="${esc(c.severity)}">` +
    `<span class="plain">${esc(findingText(c))}</span>` + (c.step === null || c.step === undefined ? "" : ` (step ${c.step + 1} of ${nSteps})`) +
    `<details><summary>details</summary>${esc(c.name)}: ${esc(c.message)}</details></li>`).join("");
  const em = (d.assumptions || {}).end_mass_kg;
  $("#res-assumptions").textContent = em ? `end mass m_e = ${em.value} kg (${em.source}` +
    (em.std === null ? ": assumed, no uncertainty; S, k_f, b_f are conditional on it)" : `, u = ${em.std} kg)`) : "";
  $("#res-environment").textContent = environmentText(d.environment);
  $("#res-structure").textContent = structureText(d.assumptions || {}, d.determined || {});
  const tb = $("#params tbody");
  tb.innerHTML = "";
  for (const p of d.parameters) {
    const tr = document.createElement("tr");
    tr.dataset.param = p.name;
    tr.innerHTML = `<td>${esc(QUANTITY_WORDS[p.name] || p.name)}, ${esc(p.name)}</td><td class="value">${p.identifiable ? fmtU(p.value, p.std) : "not determined"}</td>` +
      `<td>${esc(unitText(p.unit))}</td><td>${parameterRemark(p)}</td>`;
    tb.appendChild(tr);
  }
  const kept = d.frequency_response.length;
  $("#frf-summary").textContent = `${kept} of ${nSteps} steps were evaluated` + (kept < nSteps ? " (the findings above say why the others were left out)" : "") +
    `, from ${withUnit(Math.min(...d.frequency_response.map((s) => s.frequency_hz)).toPrecision(3), "Hz")} to ` +
    `${withUnit(Math.max(...d.frequency_response.map((s) => s.frequency_hz)).toPrecision(3), "Hz")}.`;
  if (d.fit) {
    $("#res-fit").textContent = `fit: χ²/dof ${d.fit.chi2_per_dof === null ? "—" : d.fit.chi2_per_dof.toFixed(2)}, ` +
      `mean square residual ${d.fit.mse === null ? "—" : d.fit.mse.toExponential(2)} V², ${d.fit.n_points} points` +
      (d.identifiability ? `, condition number ${d.identifiability.condition_number === null ? "—" : d.identifiability.condition_number.toPrecision(3)}` : "");
  }
  const fb = $("#frf tbody");
  fb.innerHTML = "";
  for (const s of d.frequency_response) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td>${s.index + 1} of ${nSteps}</td><td>${s.frequency_hz.toFixed(4)}</td><td>${fmtU(s.H_magnitude, s.H_magnitude_std)}</td>` +
      `<td>${fmtU(s.H_phase_deg, s.H_phase_std_deg)}</td><td>${s.n_samples}</td>`;
    fb.appendChild(tr);
  }
  const plots = $("#plots");
  plots.innerHTML = "";
  const names = Object.keys(d.plots);
  if (!names.length) plots.textContent = "plots are not available on this station (the plots module is not installed)";
  for (const n of names) {
    const fig = document.createElement("figure");
    fig.innerHTML = `<img alt="${esc(plotText(n))}" data-plot="${esc(n)}" src="${esc(d.plots[n])}"><figcaption class="small">${esc(plotText(n))}</figcaption>`;
    // a plot refused for the moment (the render worker busy, a further method being stored) is asked again
    const img = fig.querySelector("img"), src = d.plots[n];
    img.onerror = () => {
      const tries = Number(img.dataset.tries || 0);
      if (tries < 5) { img.dataset.tries = String(tries + 1); setTimeout(() => { img.src = `${src}?try=${tries + 1}`; }, 2000 * (tries + 1)); }
    };
    plots.appendChild(fig);
  }
  const rl = $("#report-link");
  if (d.report) { rl.href = d.report; rl.textContent = "calibration report"; } else { rl.removeAttribute("href"); rl.textContent = "report not available"; }
  $("#recording-link").href = `/runs/${encodeURIComponent(id)}/recording`;
  $("#archive-link").href = `/runs/${encodeURIComponent(id)}/archive.zip`;
  $("#report-pdf-link").href = `/runs/${encodeURIComponent(id)}/report.pdf`;
  for (const [sel, name] of [["#export-xlsx", "results.xlsx"], ["#export-params", "parameters.csv"], ["#export-sdyn", "sdyn.csv"]])
    $(sel).href = `/runs/${encodeURIComponent(id)}/export/${name}`;
  showCertificate(id);
  if (seq === methodsSeq) showMethods(d.methods || []);  // a later 'result' event's answer is newer
  $("#results").hidden = false;
  loadApprovals(id);
  showCompensation(id);
  loadDiscrepancy(d.discrepancy);
}

// ------------------------------------------------------------------------------------------ compensation
// a correction filter for the user's set-up from the run's identification (POST /runs/{id}/compensation),
// its Bode plot, the filter as a file, and the filter tried on an uploaded signal (POST /compensation/apply)
const COMP_MAX_SAMPLES = 200000;   // the API's bound; the command line takes more
let compFilter = null;              // the filter document on screen
let compUrls = [];                  // object URLs of the downloads and the plot, revoked when replaced

function compUrl(blob) {
  const u = URL.createObjectURL(blob);
  compUrls.push(u);
  return u;
}

function showCompensation(id) {
  for (const u of compUrls) URL.revokeObjectURL(u);
  compUrls = [];
  compFilter = null;
  $("#comp-result").hidden = true;
  $("#comp-applied").hidden = true;
  $("#comp-msg").textContent = "";
  $("#comp-form").onsubmit = (ev) => { ev.preventDefault(); designFilter(id); };
  $("#comp-apply-form").onsubmit = (ev) => { ev.preventDefault(); applyFilter(); };
}

function compBody() {
  const v = (sel) => $(sel).value.trim();
  for (const [sel, what] of [["#comp-fs", "your sample rate"], ["#comp-mass", "the mass on the transducer"], ["#comp-band", "up to which frequency to correct"]])
    if (v(sel) === "" || !Number.isFinite(Number(v(sel)))) throw new Error(`state ${what}`);
  return {sample_rate_hz: Number(v("#comp-fs")), mounted_mass_kg: Number(v("#comp-mass")),
          mounted_mass_std_kg: Number(v("#comp-mass-u") || 0), band_hz: [0, Number(v("#comp-band"))],
          allow_extrapolation: $("#comp-extrap").checked};
}

async function designFilter(id) {
  const msg = $("#comp-msg");
  let body;
  try { body = compBody(); } catch (e) { msg.textContent = e.message; return; }
  msg.textContent = "designing…";
  $("#comp-design").disabled = true;
  try {
    const path = `/runs/${encodeURIComponent(id)}/compensation`;
    const res = await api("POST", path, body);
    if (shownRun !== id) return;
    if (!res.ok) {
      const why = refusal(res, "design the filter");
      msg.textContent = why + (/calibrated range/.test(why) && !body.allow_extrapolation
        ? " To accept it, tick “correct beyond the calibrated frequencies”." : "");
      $("#comp-result").hidden = true;
      return;
    }
    msg.textContent = "";
    for (const u of compUrls) URL.revokeObjectURL(u);
    compUrls = [];
    compFilter = res.data;
    showFilter(compFilter);
    $("#comp-applied").hidden = true;
    $("#comp-result").hidden = false;
    const img = $("#comp-bode");
    img.removeAttribute("src");
    $("#comp-bode-cap").textContent = "drawing the frequency response…";
    const r = await fetch(path + "/plot", {method: "POST", body: JSON.stringify(body),
      headers: {"Content-Type": "application/json", "Accept": "image/png", "X-Station-Client": "page"}});
    if (shownRun !== id || compFilter !== res.data) return;
    if (r.ok) {
      img.src = compUrl(await r.blob());
      $("#comp-bode-cap").textContent = "how the transducer (blue), the filter (orange) and the corrected system (green) " +
        "answer each frequency, with their uncertainty (k = 2); grey: the band you asked for; dashed: the cut-off";
    } else $("#comp-bode-cap").textContent = `the plot is not available (${r.status})`;
  } finally { $("#comp-design").disabled = false; }
}

const pct = (v) => (100 * v).toPrecision(2) + " %";
function showFilter(d) {
  const S = d.transducer.theta[0];  // the static sensitivity (S or S0), unit_in per unit_out
  const [lo, hi] = d.band_hz;
  $("#comp-summary").innerHTML =
    `The filter corrects the force from ${esc(lo)} Hz to ${esc(hi)} Hz to within ${pct(d.dynamic_error_bound)} ` +
    `(besides the uncertainty it states at every sample). Above ${esc(Number(d.cutoff_hz).toPrecision(4))} Hz it smooths ` +
    `on purpose: correcting higher frequencies would amplify the noise too much. It delays the signal by ` +
    `${esc((1000 * d.delay_s).toPrecision(3))} ms (taken out of the time axis when it is applied). Noise in your signal ` +
    `comes out ${esc((d.noise_gain * S).toPrecision(3))} times larger than in a reading divided by the static sensitivity.`;
  $("#comp-findings").innerHTML = (d.findings || []).map((c) => `<li data-finding="${esc(c.name)}">${esc(c.severity)}: ${esc(c.message)}</li>`).join("");
  const t = d.transducer;
  const rows = [["taps (coefficients)", d.taps], ["sample rate", `${d.sample_rate_hz} Hz`],
    ["delay", `${d.delay_samples} samples (${(1000 * d.delay_s).toPrecision(4)} ms)${d.delay_given ? ", as given" : ", the one of least error"}`],
    ["regularising low-pass", `cut-off ${Number(d.cutoff_hz).toPrecision(5)} Hz, order ${d.lowpass_order}`],
    ["fit RMS over the band", Number(d.fit_rms_band).toExponential(2)],
    ["dynamic error bound in the band", Number(d.dynamic_error_bound).toExponential(2)],
    ["noise gain ‖b‖₂", `${Number(d.noise_gain).toPrecision(4)} ${esc(d.unit_out)}/${esc(d.unit_in)}`],
    ["transducer model", `${esc(t.kind)}: ${esc((t.assumptions || {}).model || "")}`],
    ["calibrated range", t.calibrated_range_hz.map((v) => (v === null ? "—" : v + " Hz")).join(" to ")]];
  t.names.forEach((n, i) => rows.push([`${n} (${t.units[i]})`, fmtU(t.theta[i], Math.sqrt(t.cov[i][i]))]));
  $("#comp-table tbody").innerHTML = rows.map(([k, v]) => `<tr><th>${esc(k)}</th><td>${v}</td></tr>`).join("");
  $("#comp-assumptions").textContent = Object.entries(t.assumptions || {}).filter(([, v]) => typeof v === "string")
    .map(([k, v]) => `${k}: ${v}`).join("; ");
  for (const el of document.querySelectorAll(".comp-unit-in")) el.textContent = d.unit_in;
  $("#comp-download").href = compUrl(new Blob([JSON.stringify(d, null, 1)], {type: "application/json"}));
}

// the uploaded CSV: a header, a time_s (or time) column and one value column, or one value column
function parseSignal(text) {
  const lines = text.split(/\r?\n/).filter((l) => l.trim() && !l.trim().startsWith("#"));
  if (lines.length < 2) throw new Error("the file has a header and no samples");
  const head = lines[0].split(",").map((h) => h.trim().toLowerCase());
  const ti = head.findIndex((h) => h === "time_s" || h === "time");
  const vi = head.map((_, i) => i).filter((i) => i !== ti);
  if (vi.length !== 1) throw new Error(`the header names ${vi.length} value columns (${head.join(", ")}): give one, with a time_s column or without`);
  if (lines.length - 1 > COMP_MAX_SAMPLES) throw new Error(`${lines.length - 1} samples: the page takes at most ${COMP_MAX_SAMPLES} (use station compensate apply)`);
  const x = new Float64Array(lines.length - 1), t = ti >= 0 ? new Float64Array(lines.length - 1) : null;
  for (let k = 1; k < lines.length; k++) {
    const f = lines[k].split(",");
    if (f.length !== head.length) throw new Error(`line ${k + 1}: ${f.length} fields, the header names ${head.length}`);
    x[k - 1] = Number(f[vi[0]]);
    if (f[vi[0]].trim() === "" || !Number.isFinite(x[k - 1])) throw new Error(`line ${k + 1}: "${f[vi[0]].trim()}" is not a finite number: nothing was corrected`);
    if (t) {
      t[k - 1] = Number(f[ti]);
      if (!Number.isFinite(t[k - 1])) throw new Error(`line ${k + 1}: the time "${f[ti].trim()}" is not a number`);
    }
  }
  let fs = null, t0 = 0;
  if (t) {
    if (t.length < 2) throw new Error("fewer than 2 samples");
    const step = (t[t.length - 1] - t[0]) / (t.length - 1);
    for (let k = 1; k < t.length; k++)
      if (!(step > 0) || Math.abs(t[k] - t[k - 1] - step) > 1e-3 * step) throw new Error(`the time column is not uniformly sampled (at line ${k + 2}): resample it first`);
    fs = 1 / step;
    t0 = t[0];
  }
  return {x, fs, t0, column: head[vi[0]]};
}

async function applyFilter() {
  const msg = $("#comp-apply-msg"), d = compFilter;
  const file = $("#comp-file").files[0];
  if (!d) { msg.textContent = "design a filter first"; return; }
  if (!file) { msg.textContent = "choose a signal file"; return; }
  let sig;
  try { sig = parseSignal(await file.text()); } catch (e) { msg.textContent = `${file.name}: ${e.message}`; return; }
  const noise = Number($("#comp-noise").value || 0);
  if (!(noise >= 0)) { msg.textContent = "the noise's standard deviation must be a number ≥ 0"; return; }
  // a time column within 1e-3 of the filter's rate is the filter's rate (a CSV rounds its times)
  const fs = sig.fs === null || Math.abs(sig.fs / d.sample_rate_hz - 1) <= 1e-3 ? d.sample_rate_hz : sig.fs;
  msg.textContent = "correcting…";
  $("#comp-apply").disabled = true;
  try {
    const res = await api("POST", "/compensation/apply", {filter: d, signal: Array.from(sig.x), sample_rate_hz: fs, noise_std: noise});
    if (compFilter !== d) return;
    if (!res.ok) { msg.textContent = refusal(res, "correct the signal"); return; }
    msg.textContent = "";
    showApplied(d, sig, fs, res.data);
  } finally { $("#comp-apply").disabled = false; }
}

function showApplied(d, sig, fs, r) {
  const S = d.transducer.theta[0];
  const y = r.estimate, u = r.u, t = r.time_s.map((v) => v + sig.t0);
  let ip = 0, im = 0;
  for (let k = 1; k < y.length; k++) if (Math.abs(y[k]) > Math.abs(y[ip])) ip = k;
  for (let k = 1; k < sig.x.length; k++) if (Math.abs(sig.x[k]) > Math.abs(sig.x[im])) im = k;
  $("#comp-applied-summary").textContent = `${y.length} samples corrected. Largest corrected force ${fmtU(y[ip], u[ip])} ${r.unit} ` +
    `(± one standard uncertainty) at ${(t[ip] * 1000).toPrecision(5)} ms; the uncorrected reading (signal ÷ static sensitivity) ` +
    `peaks at ${(sig.x[im] / S).toPrecision(4)} ${r.unit}. The delay of ${(1000 * r.delay_s).toPrecision(3)} ms is taken out of the time axis.`;
  $("#comp-signal").innerHTML = signalPlot(sig, S, fs, t, y, u, r.unit);
  const rows = ["time_s,estimate_" + r.unit + ",u_" + r.unit];
  for (let k = 0; k < y.length; k++) rows.push(`${t[k]},${y[k]},${u[k]}`);
  $("#comp-applied-download").href = compUrl(new Blob([rows.join("\n") + "\n"], {type: "text/csv"}));
  $("#comp-applied").hidden = false;
}

// measured ÷ static sensitivity and the corrected force with its band (k = 2), at most ~1200 points drawn
function signalPlot(sig, S, fs, t, y, u, unit) {
  const W = 700, H = 260, pad = 50, n = y.length, step = Math.max(1, Math.ceil(n / 1200));
  const idx = [];
  for (let k = 0; k < n; k += step) idx.push(k);
  const tm = (k) => sig.t0 + k / fs;  // the measured sample's time (the estimate's is earlier by the delay)
  const vals = idx.flatMap((k) => [y[k] - 2 * u[k], y[k] + 2 * u[k], sig.x[k] / S]);
  const lo = Math.min(...vals), hi = Math.max(...vals);
  const ta = Math.min(t[0], tm(0)), tb = Math.max(t[n - 1], tm(n - 1));
  const X = (v) => pad + (tb > ta ? (v - ta) / (tb - ta) : 0.5) * (W - 2 * pad);
  const Y = (v) => H - pad / 2 - (hi > lo ? (v - lo) / (hi - lo) : 0.5) * (H - pad);
  const line = (f) => idx.map((k, i) => `${i ? "L" : "M"}${X(f(k)[0]).toFixed(1)},${Y(f(k)[1]).toFixed(1)}`).join(" ");
  const band = idx.map((k, i) => `${i ? "L" : "M"}${X(t[k]).toFixed(1)},${Y(y[k] + 2 * u[k]).toFixed(1)}`).join(" ") + " " +
    idx.slice().reverse().map((k) => `L${X(t[k]).toFixed(1)},${Y(y[k] - 2 * u[k]).toFixed(1)}`).join(" ") + " Z";
  return `<svg viewBox="0 0 ${W} ${H}" width="100%" role="img" aria-label="measured and corrected signal" class="hist-svg">` +
    `<text x="4" y="14" font-size="12">${esc(unit)}: grey measured ÷ static sensitivity; blue corrected, band ± 2u</text>` +
    `<path d="${band}" fill="#06c" fill-opacity="0.25" stroke="none"/>` +
    `<path d="${line((k) => [tm(k), sig.x[k] / S])}" stroke="#888" fill="none"/>` +
    `<path d="${line((k) => [t[k], y[k]])}" stroke="#06c" fill="none"/>` +
    `<text x="4" y="${Y(hi) + 4}" font-size="10">${hi.toPrecision(4)}</text><text x="4" y="${Y(lo)}" font-size="10">${lo.toPrecision(4)}</text>` +
    `<text x="${pad}" y="${H - 4}" font-size="10">${(ta * 1000).toPrecision(4)} ms</text><text x="${W - pad - 60}" y="${H - 4}" font-size="10">${(tb * 1000).toPrecision(4)} ms</text></svg>`;
}

// the run's certificate: the draft until a second person with the approver role issues it
async function showCertificate(id) {
  const base = `/runs/${encodeURIComponent(id)}/certificate`;
  for (const ext of ["html", "pdf", "xml"]) $(`#cert-${ext}`).href = `${base}.${ext}`;
  $("#cert-form").onsubmit = async (ev) => {
    ev.preventDefault();
    const prepared = $("#cert-prepared").value.trim();
    const res = await api("POST", base, prepared ? {prepared_by: prepared} : {});
    $("#cert-msg").textContent = res.ok ? `issued ${res.data.number}` : (detailText(res.data) || `refused (${res.status})`);
    if (res.ok) { shownIssued = [res.data]; applyRoles(); }
  };
  shownIssued = [];
  const r = await api("GET", "/certificates");
  if (r.ok && shownRun === id) shownIssued = r.data.certificates.filter((c) => c.run_id === id && !c.replaced_by);
  applyRoles();
}

async function loadDiscrepancy(url) {
  const box = $("#discrepancy");
  box.textContent = "loading…";
  let res = await api("GET", url);
  if (res.status === 404 && may("run")) {  // not computed yet: computing and storing it needs a login
    box.textContent = "analysing…";
    res = await api("POST", url);
  }
  if (!res.ok) {
    box.textContent = res.status === 404 ? "not analysed yet: log in (top of the page) to analyse this run"
      : `not available: ${detailText(res.data)}`;
    return;
  }
  const d = res.data;
  const mV = (v) => (v === null ? "—" : (v * 1000).toPrecision(3) + " mV");
  const plainGap = d.effects.length
    ? `The measurement shows ${d.effects.length === 1 ? "an effect" : `${d.effects.length} effects`} the transducer model leaves out: ` +
      `${listText(d.effects.map((e) => String(e.name).replace(/_/g, " ")))}.`
    : "The transducer model explains the measurement: no known effect is missing.";
  let html = `<p class="plain">${esc(plainGap)}${d.unexplained.length ? " Part of the difference stays unexplained." : ""}</p>` +
    '<details class="tech"><summary>The numbers (for the expert)</summary>';
  html += `<p>force residual (RMS) of the model: ${mV(d.base_gap)} → ${mV(d.final_gap)} after the effects below</p>`;
  html += d.effects.length ? "<ul>" + d.effects.map((e) => `<li>${esc(e.name)} (gap after: ${mV(e.gap_after)})</li>`).join("") + "</ul>"
    : "<p>no catalogue effect needed: the model explains the measurement</p>";
  if (d.ties && d.ties.length) {
    html += '<div class="ties"><p><b>not decided by these data</b> (k_f and b_f carry the spread):</p><ul>'
      + d.ties.map((t) => `<li>${esc(t.kind)}: ${t.candidates.map((c) => esc(c.effects.join(" + ") || "base model")
        + ` (k_f ${c.k_f.value === null ? "—" : c.k_f.value.toPrecision(6)} N/m)`).join(" vs ")}</li>`).join("") + "</ul></div>";
  }
  if (d.unexplained.length) html += "<p>unexplained: " + d.unexplained.map(esc).join("; ") + "</p>";
  if (d.notes && d.notes.length) html += "<ul class=\"notes\">" + d.notes.map((n) => `<li>${esc(n)}</li>`).join("") + "</ul>";
  html += "</details>" + proposalHtml(d.proposal);
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
    msg.textContent = refusal(res, "start");
  } finally {
    const b = $("#run-proposal");
    if (b) b.disabled = false;
  }
}

$("#abort").addEventListener("click", async () => {
  const res = await api("POST", `/runs/${encodeURIComponent(shownRun)}/abort`);
  if (!res.ok) banner(refusal(res, "abort") + " (the EMERGENCY STOP needs no login)");
});

// ------------------------------------------------------------------------------------------ approval
async function loadApprovals(id) {
  const r = await api("GET", `/audit?target=${encodeURIComponent(id)}&action=certificate.approved`);
  const list = r.ok ? r.data.entries : [];
  $("#approvals").textContent = list.length ? list.map((e) => `approved by ${e.who} ${localTime(e.at)}` + (e.details.note ? ` (${e.details.note})` : "")).join("; ") + ". "
    : "not approved yet. ";
  $("#approve").disabled = !may("approve");
  $("#approve").title = may("approve") ? "approve as " + me.name : "an approver (not who ran it) approves";
}

$("#approve").addEventListener("click", async () => {
  const r = await api("POST", `/runs/${encodeURIComponent(shownRun)}/approve`, {note: $("#approve-note").value.trim()});
  $("#approve-msg").textContent = r.ok ? "" : refusal(r, "approve");
  if (r.ok) loadApprovals(shownRun);
});


// ------------------------------------------------------------------------------------------ register, history, audit
async function showRegister() {
  await loadRegister();
  if (!register) return;
  $("#reg-transducers tbody").innerHTML = register.transducers.map((t) => `<tr><td><a href="#/transducers/${encodeURIComponent(t.id)}">${esc(t.id)}</a></td>` +
    `<td>${esc(t.type)}</td><td>${esc(t.serial)}</td><td>${t.capacity_N}</td><td>${t.sensitivity_V_per_N}</td>` +
    `<td>${t.end_mass_kg === null ? "—" : fmtU(t.end_mass_kg, t.end_mass_std_kg)}</td><td>${esc(t.owner)}</td>` +
    `<td>${t.id === register.mounted ? "mounted" : ""}</td></tr>`).join("");
  $("#reg-standards tbody").innerHTML = register.standards.map((s) => `<tr${s.overdue ? ' class="bad"' : ""}><td>${esc(s.id)}</td><td>${esc(s.kind)}</td>` +
    `<td>${esc(s.certificate_id)}</td><td>${esc(s.issuer)}</td><td>${esc(s.due_date)}${s.overdue ? " OVERDUE" : ""}</td>` +
    `<td>${s.uncertainty} ${esc(s.uncertainty_unit)}</td><td>${s.in_use ? "yes" : "no"}</td></tr>`).join("");
  $("#reg-admin").hidden = !may("admin");
  $("#reg-policy").textContent = `A run with a standard past its due date is ${register.overdue_policy === "refuse" ? "refused" : "started with a warning"}. ` +
    "Administrators change the register below (or PUT /register/..., `station register`).";
}

// the administrators' forms: PUT the entry, then show the register again
function formBody(form, numbers) {
  const d = Object.fromEntries(new FormData(form).entries());
  const id = d.id;
  delete d.id;
  for (const k of numbers) d[k] = d[k] === "" || d[k] === undefined ? null : Number(d[k]);
  for (const k of Object.keys(d)) if (d[k] === null && !["end_mass_kg", "end_mass_std_kg"].includes(k)) delete d[k];
  return [id, d];
}

$("#std-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const [id, d] = formBody(ev.target, ["uncertainty"]);
  d.in_use = ev.target.in_use.checked;
  const r = await api("PUT", `/register/standards/${encodeURIComponent(id)}`, d);
  $("#reg-msg").textContent = r.ok ? `standard ${id} saved` : refusal(r, "save");
  if (r.ok) showRegister();
});

$("#tx-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const [id, d] = formBody(ev.target, ["capacity_N", "sensitivity_V_per_N", "end_mass_kg", "end_mass_std_kg"]);
  const r = await api("PUT", `/register/transducers/${encodeURIComponent(id)}`, d);
  $("#reg-msg").textContent = r.ok ? `transducer ${id} saved` : refusal(r, "save");
  if (r.ok) showRegister();
});

// k_f (or S) over time with its standard uncertainty, as an SVG: one point per completed run
function historyPlot(runs, name, apiUnit) {
  const unit = unitText(apiUnit);
  const pts = runs.map((r) => [r.created, (r.parameters[name] || {}).value, (r.parameters[name] || {}).std, (r.drift[name] || {}).flagged])
    .filter((p) => p[1] !== null && p[1] !== undefined);
  if (!pts.length) return `<p class="small">no identified ${esc(name)} yet</p>`;
  const W = 600, H = 220, pad = 50;
  const t0 = Math.min(...pts.map((p) => p[0])), t1 = Math.max(...pts.map((p) => p[0]));
  const lo = Math.min(...pts.map((p) => p[1] - (p[2] || 0))), hi = Math.max(...pts.map((p) => p[1] + (p[2] || 0)));
  const x = (t) => pad + (t1 > t0 ? (t - t0) / (t1 - t0) : 0.5) * (W - 2 * pad);
  const y = (v) => H - pad / 2 - (hi > lo ? (v - lo) / (hi - lo) : 0.5) * (H - pad);
  const marks = pts.map((p) => `<line x1="${x(p[0])}" x2="${x(p[0])}" y1="${y(p[1] - (p[2] || 0))}" y2="${y(p[1] + (p[2] || 0))}" stroke="#555"/>` +
    `<circle cx="${x(p[0])}" cy="${y(p[1])}" r="4" fill="${p[3] ? "#c00" : "#06c"}"><title>${localTime(p[0])}: ${fmtU(p[1], p[2])} ${unit}</title></circle>`).join("");
  return `<svg viewBox="0 0 ${W} ${H}" width="100%" role="img" aria-label="${esc(name)} over time" class="hist-svg">` +
    `<text x="4" y="14" font-size="12">${esc(name)} (${esc(unit)}) ± u; red: drift flagged</text>` +
    `<text x="4" y="${H - 4}" font-size="11">${localTime(t0).slice(0, 10)}</text><text x="${W - 80}" y="${H - 4}" font-size="11">${localTime(t1).slice(0, 10)}</text>` +
    `<text x="4" y="${y(hi) + 4}" font-size="10">${hi.toPrecision(4)}</text><text x="4" y="${y(lo)}" font-size="10">${lo.toPrecision(4)}</text>` +
    marks + "</svg>";
}

// a control chart (EWMA statistic or the values of a Shewhart chart) with its limits: red points are out of control
function chartPlot(name, unit, chart, points) {
  const W = 600, H = 200, pad = 50;
  const pts = chart.points;
  const ys = pts.flatMap((p) => [p.statistic, p.lower, p.upper]).concat(points.flatMap((p) => [p.value - p.u, p.value + p.u]));
  const lo = Math.min(...ys), hi = Math.max(...ys);
  const x = (i) => pad + (pts.length > 1 ? i / (pts.length - 1) : 0.5) * (W - 2 * pad);
  const y = (v) => H - pad / 2 - (hi > lo ? (v - lo) / (hi - lo) : 0.5) * (H - pad);
  const path = (key) => pts.map((p, i) => `${i ? "L" : "M"}${x(i)},${y(p[key])}`).join(" ");
  const bars = chart.kind === "shewhart" ? points.map((p, i) => `<line x1="${x(i)}" x2="${x(i)}" y1="${y(p.value - p.u)}" y2="${y(p.value + p.u)}" stroke="#555"/>`).join("") : "";
  const dots = pts.map((p, i) => `<circle cx="${x(i)}" cy="${y(p.statistic)}" r="4" fill="${p.out_of_control ? "#c00" : "#06c"}">` +
    `<title>${esc(points[i].run_id)}: ${p.statistic.toPrecision(6)} ${esc(unit)}${p.out_of_control ? " (out of control)" : ""}</title></circle>`).join("");
  const what = chart.kind === "ewma" ? `EWMA (λ ${chart.parameters.lambda}, limits ±${chart.parameters.L} s)` : `values ± u, limits ±${chart.parameters.k.toFixed(2)} s (t, ${chart.parameters.dof} degrees of freedom)`;
  return `<svg viewBox="0 0 ${W} ${H}" width="100%" role="img" aria-label="${esc(name)} control chart" class="hist-svg">` +
    `<text x="4" y="14" font-size="12">${esc(name)} (${esc(unit)}): ${esc(what)}; false alarms ${(100 * chart.false_alarm_rate).toFixed(2)} % per point</text>` +
    `<path d="${path("upper")}" stroke="#c60" fill="none" stroke-dasharray="4 3"/><path d="${path("lower")}" stroke="#c60" fill="none" stroke-dasharray="4 3"/>` +
    `<line x1="${pad}" x2="${W - pad}" y1="${y(chart.centre)}" y2="${y(chart.centre)}" stroke="#999"/>` +
    bars + (chart.kind === "ewma" ? `<path d="${path("statistic")}" stroke="#06c" fill="none"/>` : "") + dots +
    `<text x="4" y="${y(hi) + 4}" font-size="10">${hi.toPrecision(5)}</text><text x="4" y="${y(lo)}" font-size="10">${lo.toPrecision(5)}</text></svg>`;
}

// the trends: charts of each parameter, the latest as-found, drift risk and the intervals each method recommends
function trendSection(trends) {
  if (!trends) return "";
  const units = { S: "V/N", k_f: "N/m", b_f: "N·s/m", f_0: "Hz" };
  const names = { S: "sensitivity S", k_f: "stiffness k_f", b_f: "damping b_f", f_0: "natural frequency f_0 (with its end mass)" };
  let html = `<p class="small">${trends.policy.check_standard ? "<strong>check transducer</strong> · " : ""}assigned interval: ${trends.policy.interval_days ? trends.policy.interval_days + " d" : "none"} · ${esc(trends.note)}</p>`;
  for (const [name, p] of Object.entries(trends.parameters)) {
    const unit = units[name] || p.unit;
    html += `<h3>${esc(names[name] || name)}</h3>`;
    if (p.ewma) html += chartPlot(name, unit, p.ewma, p.points) + chartPlot(name, unit, p.shewhart, p.points);
    else html += `<p class="small">${esc(p.charts_note || "")}</p>`;
    const last = p.as_found[p.as_found.length - 1];
    if (last) html += `<p class="small">as found in ${esc(last.run_id)}: ${fmtU(last.difference, last.u)} ${esc(unit)} against the ${esc(last.as_left_source)} value of ${esc(last.previous_run_id)}` +
      (last.in_tolerance === undefined ? "" : last.in_tolerance ? " (in tolerance)" : " (<strong>out of tolerance</strong>)") + "</p>";
    const risk = p.drift_risk || {};
    if (risk.probability_out_of_tolerance !== undefined) html += `<p class="small">drift ${fmtU(risk.slope_per_day, risk.u_slope_per_day)} ${esc(unit)}/d; probability of being out of tolerance at the next due date: ${(100 * risk.probability_out_of_tolerance).toFixed(1)} %</p>`;
    const iv = Object.entries(p.intervals || {}).filter(([, r]) => r && typeof r.interval_days === "number");
    if (iv.length) html += `<p class="small">recommended intervals (for a person to decide): ` + iv.map(([m, r]) => `${esc(m)} ${Number(r.interval_days).toFixed(0)} d`).join(", ") + "</p>";
  }
  return html;
}

async function showHistory(id) {
  $("#hist-id").textContent = id;
  const r = await api("GET", `/transducers/${encodeURIComponent(id)}/history`);
  if (!r.ok) { $("#hist-transducer").textContent = detailText(r.data); return; }
  const d = r.data, t = d.transducer;
  $("#hist-transducer").textContent = [t.type, t.serial && `serial ${t.serial}`, `${t.capacity_N} N`, t.owner,
    `${d.runs.length} runs`].filter(Boolean).join(" · ");
  $("#hist-plot").innerHTML = historyPlot(d.runs, "k_f", d.units.k_f) + historyPlot(d.runs, "S", d.units.S);
  $("#hist-trends").innerHTML = (d.hold ? `<p class="hold"><strong>Held for review:</strong> ${esc(d.hold.reason)} (since ${esc(localTime(d.hold.since))})</p>` : "") +
    trendSection(d.trends);
  $("#hist-flagged").textContent = d.flagged.length ? "drift flagged: " + d.flagged.map((f) => `${f.run_id} ${f.parameter}`).join(", ")
    : "no drift flagged against earlier calibrations (the nightly batch's rule: |x − mean| > 3 u_c, after 3 runs)";
  const cell = (r, n) => { const p = r.parameters[n]; return p && p.value !== null ? fmtU(p.value, p.std) : "—"; };
  $("#hist-runs tbody").innerHTML = d.runs.slice().reverse().map((r) => `<tr><td><a href="#/runs/${esc(r.run_id)}">${esc(r.run_id)}</a></td>` +
    `<td class="state ${esc(r.state)}">${esc(r.state)}</td><td>${esc(r.operator)}</td><td>${cell(r, "S")}</td><td>${cell(r, "k_f")}</td><td>${cell(r, "b_f")}</td>` +
    `<td>${Object.entries(r.drift).filter(([, c]) => c.flagged).map(([n]) => n).join(", ") || "—"}</td>` +
    `<td>${r.approvals.map((a) => esc(a.by)).join(", ") || "—"}</td>` +
    `<td>${d.certificates.filter((c) => c.run_id === r.run_id).map((c) => `<a href="/certificates/${encodeURIComponent(c.number)}.html">${esc(c.number)}</a>` +
      (c.replaced_by ? ` (replaced by ${esc(c.replaced_by)})` : "")).join(", ") || "—"}</td></tr>`).join("");
}

async function showAudit() {
  const r = await api("GET", "/audit?limit=200");
  if (!r.ok) return;
  $("#audit tbody").innerHTML = r.data.entries.map((e) => `<tr><td>${e.id}</td><td>${localTime(e.at)}</td><td>${esc(e.who)}</td>` +
    `<td>${esc(e.action)}</td><td>${esc(e.target)}</td><td class="details">${esc(JSON.stringify(e.details))}</td></tr>`).join("");
}

// ------------------------------------------------------------------------------------------ users (administrators)
// The section exists for a user with the admin permission only (the API refuses everyone else).
// Nothing secret stays in the page: a password field is emptied once sent, an issued token is shown
// until "done" (or leaving the view, logging out) and never logged.
function clearToken() {
  $("#token-text").textContent = "";
  $("#token-copied").textContent = "";
  $("#token-shown").hidden = true;
}

function hideUsers() {
  $("#view-users").hidden = true;
  $("#users tbody").innerHTML = "";
  $("#user-password").value = "";
  clearToken();
}

// a refusal shown at its field: 422 at the field its loc names, other refusals by what they are about
function showRefusal(form, res, action, fields, about) {
  for (const e of form.querySelectorAll(".err")) e.textContent = "";
  if (res.ok) return;
  const put = (field, text) => {
    const el = form.querySelector(`.err[data-for="${fields[field] || form.id}"]`);
    el.textContent = (el.textContent ? el.textContent + "; " : "") + text;
  };
  if (res.status === 422 && Array.isArray(res.data && res.data.errors)) {
    for (const e of res.data.errors) put(String((e.loc || []).slice(-1)[0]), e.msg);
  } else {
    put(about(detailText(res.data)), refusal(res, action));
  }
}

async function showUsers() {
  clearToken();
  const [p, r] = await Promise.all([api("GET", "/users/policy"), api("GET", "/users")]);
  if (!p.ok || !r.ok) { $("#users-msg").textContent = refusal(p.ok ? r : p, "list the users"); return; }
  const policy = p.data;
  const picked = ($("#user-roles input:checked") || {}).value;
  $("#user-roles").innerHTML = "<legend>role</legend>" + policy.roles.map((ro) =>
    `<label title="${esc(ro.permissions.join(", "))}"><input type="radio" name="role" value="${esc(ro.name)}"` +
    `${ro.name === picked ? " checked" : ""}> ${esc(ro.name)}</label>`).join("");
  $("#users-roles").textContent = "One role per user: " + policy.roles.map((ro) => `${ro.name} may ${ro.permissions.join(", ")}`).join("; ") +
    `. Names: lower-case letters, digits, '_', '.', '-', starting with a letter, at most 32 characters.`;
  $("#user-password-rule").textContent = `at least ${policy.min_password} characters; empty: the password stays as it is`;
  $("#users tbody").innerHTML = r.data.map((u) => `<tr data-user="${esc(u.name)}"${u.disabled ? ' class="bad"' : ""}><td>${esc(u.name)}</td>` +
    `<td>${esc(u.role)}</td><td>${u.disabled ? "disabled" : "active"}</td>` +
    `<td>${u.changed ? `${localTime(u.changed)} by ${esc(u.changed_by)}` : "—"}</td>` +
    `<td><button type="button" class="user-edit" data-user="${esc(u.name)}">change</button></td></tr>`).join("");
  const keep = $("#token-user").value;
  $("#token-user").innerHTML = r.data.map((u) => `<option${u.disabled ? " disabled" : ""}>${esc(u.name)}</option>`).join("");
  if (r.data.some((u) => u.name === keep && !u.disabled)) $("#token-user").value = keep;
  for (const b of document.querySelectorAll(".user-edit")) b.addEventListener("click", () => {
    const u = r.data.find((x) => x.name === b.dataset.user);
    $("#user-name").value = u.name;
    for (const i of document.querySelectorAll("#user-roles input")) i.checked = i.value === u.role;
    $("#user-disabled").checked = u.disabled;
    $("#user-password").value = "";
    $("#user-password").focus();
  });
}

$("#user-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const form = ev.target;
  const name = $("#user-name").value.trim();
  const role = $("#user-roles input:checked");
  const body = {role: role ? role.value : null, disabled: $("#user-disabled").checked};
  if ($("#user-password").value) body.password = $("#user-password").value;
  $("#user-password").value = "";  // sent once, never kept
  const fields = {name: "name", role: "role", password: "password", disabled: "disabled"};
  if (!name) { showRefusal(form, {ok: false, status: 422, data: {errors: [{loc: ["path", "name"], msg: "a user name is needed"}]}}, "", fields, () => ""); return; }
  const r = await api("PUT", `/users/${encodeURIComponent(name)}`, body);
  showRefusal(form, r, "save the user", fields, (t) => t.startsWith("user name") ? "name" : t.includes("password") ? "password" : "");
  if (r.ok) {
    $("#users-msg").textContent = `user ${r.data.name} saved: ${r.data.role}, ${r.data.disabled ? "disabled" : "active"}`;
    showUsers();
  }
});

$("#token-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearToken();
  const user = $("#token-user").value;
  const fields = {name: "user", label: "label"};
  if (!user) { showRefusal(ev.target, {ok: false, status: 422, data: {errors: [{loc: ["path", "name"], msg: "choose a user"}]}}, "", fields, () => ""); return; }
  const r = await api("POST", `/users/${encodeURIComponent(user)}/tokens`, {label: $("#token-label").value});
  showRefusal(ev.target, r, "issue the token", fields, (t) => t.startsWith("no user") ? "name" : "");
  if (!r.ok) return;
  $("#token-text").textContent = r.data.token;
  $("#token-shown").hidden = false;
  $("#users-msg").textContent = `token issued for ${r.data.user}` + (r.data.label ? ` (${r.data.label})` : "");
  $("#token-label").value = "";
});

$("#token-copy").addEventListener("click", async () => {
  const text = $("#token-text").textContent;
  try {
    await navigator.clipboard.writeText(text);
    $("#token-copied").textContent = "copied";
  } catch {  // no clipboard permission: select it for Ctrl+C
    getSelection().selectAllChildren($("#token-text"));
    $("#token-copied").textContent = "selected: copy it with Ctrl+C";
  }
});

$("#token-done").addEventListener("click", clearToken);

// ------------------------------------------------------------------------------------------ routing
async function route() {
  const h = location.hash;
  const m = h.match(/^#\/runs\/([^/]+)$/);
  const th = h.match(/^#\/transducers\/([^/]+)$/);
  const users = h === "#/users" && may("admin");  // nobody else sees the section
  const view = m ? "run" : th ? "history" : h === "#/register" ? "register" : h === "#/audit" ? "audit" : users ? "users" : "home";
  for (const v of ["home", "run", "history", "register", "audit"]) $(`#view-${v}`).hidden = v !== view;
  if (view === "users") $("#view-users").hidden = false;
  else hideUsers();
  if (view !== "run") { shownRun = null; if (source) { source.close(); source = null; } }
  if (view === "history") return showHistory(decodeURIComponent(th[1]));
  if (view === "register") return showRegister();
  if (view === "audit") return showAudit();
  if (view === "users") return showUsers();
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
    $("#run-who").textContent = res.data.operator ? `started by ${res.data.operator}` : "";
    if (!FINAL.includes(res.data.state)) follow(id);
  } else {
    refreshRuns();
  }
}

async function init() {
  await loadMe();
  station = (await api("GET", "/station")).data;
  showLimits();
  await loadRegister();
  window.addEventListener("hashchange", route);
  await route();
  refreshHealth();
  setInterval(refreshHealth, 5000);
  setInterval(() => { if (!shownRun) refreshRuns(); }, 5000);
}

init();
