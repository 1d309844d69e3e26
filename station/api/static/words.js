// The lab's words on the page: plain names of quantities, findings and plots; SI typography for
// numbers and units; times in the viewer's local time with its zone.  Loaded before app.js.
"use strict";

// the quantities by their plain names (the symbol follows in the table)
const QUANTITY_WORDS = {
  S: "sensitivity", k_f: "stiffness of the transducer", b_f: "damping of the transducer",
  k_c: "stiffness of the coupling", b_c: "damping of the coupling", m_e: "end mass",
  f_0: "natural frequency", zeta: "damping ratio",
};

// a unit as SI typography writes it: "N*s/m" -> "N·s/m", "m/s^2" -> "m/s²", "deg" -> "°", "us" -> "µs"
const SUPERSCRIPT = {"-": "⁻", "0": "⁰", "1": "¹", "2": "²", "3": "³", "4": "⁴", "5": "⁵", "6": "⁶", "7": "⁷", "8": "⁸", "9": "⁹"};
const sup = (digits) => String(digits).replace(/[-0-9]/g, (c) => SUPERSCRIPT[c]);
function unitText(unit) {
  const u = String(unit ?? "");
  if (u === "deg") return "°";
  if (u === "1") return "";
  return u.replace(/\*/g, "·").replace(/\^\((-?\d+)\)|\^(-?\d+)/g, (_, a, b) => sup(a ?? b)).replace(/\bus\b/g, "µs").replace(/\bdeg\b/g, "°");
}

// a number and its unit: a space between them (none before "°")
function withUnit(number, unit) {
  const u = unitText(unit);
  return !u ? String(number) : u === "°" ? `${number}°` : `${number} ${u}`;
}

// value ± std, both to the precision of 2 significant digits of the uncertainty; a very large or small
// value as (v ± u) × 10ⁿ
function fmtU(v, s) {
  if (v === null || v === undefined) return "—";
  if (s === null || s === undefined || !(s > 0)) return Number(v).toPrecision(6);
  const e = Math.floor(Math.log10(s)) - 1;
  const scale = Math.floor(Math.log10(Math.abs(v) || s));
  if (scale >= 5 || scale <= -4) {
    const m = Math.pow(10, scale);
    const digits = Math.max(0, scale - e);
    return `(${(v / m).toFixed(digits)} ± ${(s / m).toFixed(digits)}) × 10${sup(scale)}`;
  }
  const d = Math.max(0, -e);
  return `${v.toFixed(d)} ± ${s.toFixed(d)}`;
}

// a time (epoch seconds, an ISO text or a Date) in the viewer's local time with its zone:
// "2026-11-27 05:10:23 CET" (or "GMT+1" where the zone has no short name)
function localTime(t) {
  const d = t instanceof Date ? t : new Date(typeof t === "number" ? t * 1000 : t);
  if (Number.isNaN(d.getTime())) return String(t ?? "");
  const p2 = (n) => String(n).padStart(2, "0");
  const zone = (new Intl.DateTimeFormat("en", {timeZoneName: "short"}).formatToParts(d)
    .find((x) => x.type === "timeZoneName") || {value: ""}).value;
  return `${d.getFullYear()}-${p2(d.getMonth() + 1)}-${p2(d.getDate())} ${p2(d.getHours())}:${p2(d.getMinutes())}:${p2(d.getSeconds())} ${zone}`;
}

// a duration for people: "40 s", "3 min", "1 h 5 min"
function durationText(s) {
  if (!(s >= 0) || !Number.isFinite(s)) return "";
  if (s < 90) return `${Math.max(1, Math.round(s))} s`;
  if (s < 3600) return `${Math.round(s / 60)} min`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}

// what a finding of the identification means, in a sentence a technician reads first (the
// identification's own message, with its statistics, goes in the details)
const FINDING_WORDS = {
  model_misfit: "The transducer model does not describe the measurement within its noise; the uncertainties are enlarged to cover it.",
  coupling_suspected: "The mounting (coupling) is probably not stiff: the stiffness found is that of transducer and mounting together.",
  coupling_not_excluded: "This run cannot rule out some give in the mounting; the stiffness is stated under a stiff mounting.",
  displacement_resonance_suspected: "The displacement sensor seems to resonate within the frequencies run; its resonance should be stated in the configuration.",
  displacement_vs_radius: "The measured motion and the crank radius disagree: one of the two standards is off.",
  samples_lost: "Samples were lost during a step; that step was left out.",
  dead_channel: "A signal channel gave only zeros during a step (not connected?); that step was left out.",
  constant_channel: "A signal channel did not change during a step; that step was left out.",
  clipped_channel: "A signal was clipped (beyond the input range) during a step; that step was left out.",
  step_failed: "A step could not be evaluated and was left out.",
  no_usable_step: "No step could be evaluated: there is no result.",
  no_signal: "No signal was measured.",
  non_finite_channel: "A channel holds invalid numbers; the affected step was left out.",
  frequency_mismatch: "A step ran at a frequency other than the one planned; it was evaluated at the measured one.",
  clock_skew: "The two converters' clocks run at slightly different rates.",
  polarity: "The force signal's sign (polarity) is noted.",
  channels_swapped: "The force and displacement signals look swapped: check the wiring.",
  low_frequency_gain: "The force signal is far from what the top mass and sensitivity predict: check the top mass, the sensitivity and the units.",
  sensitivity_vs_nominal: "The sensitivity found differs markedly from the transducer's nominal one.",
  end_mass_not_given: "The transducer's end mass is not known; the results assume a value for it.",
  end_mass_conditional: "The results assume a value for the transducer's end mass.",
  end_mass_stated: "The end mass used is the one stated for the transducer.",
  extrapolation: "Part of the range asked for lies outside the frequencies calibrated.",
};

const SEVERITY_WORDS = {info: "Note", warning: "Check before using the results", refused: "Refused"};

function findingText(check) {
  const plain = FINDING_WORDS[check.name] || `${String(check.name).replace(/_/g, " ")}.`;
  return `${SEVERITY_WORDS[check.severity] || check.severity}: ${plain}`;
}

// the plots by what they show (the file stems of the API: bode, timefit, residuals, convergence, ...)
const PLOT_WORDS = {
  bode: "Dynamic sensitivity over frequency: the measured steps with their uncertainty and the identified model",
  timefit: "The force signal of each step as measured and as the identified model gives it",
  residuals: "What the model leaves unexplained in each step (residuals)",
  convergence: "How the particle swarm's search settled (the paper's method)",
};
const plotText = (name) => PLOT_WORDS[name] || String(name).replace(/_/g, " ");
