// Small DOM and formatting helpers. Text always goes in as text (never as HTML).

/**
 * Creates an element: `h("td", {class: "num", title: "x"}, "text", child)`.
 * Attribute values of null/undefined/false are skipped; `true` sets an empty attribute.
 * Keys starting with "on" add event listeners.
 */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  setAttrs(el, attrs);
  append(el, children);
  return el;
}

const SVG_NS = "http://www.w3.org/2000/svg";

/** Creates an SVG element, like `h`. */
export function s(tag, attrs = {}, ...children) {
  const el = document.createElementNS(SVG_NS, tag);
  setAttrs(el, attrs);
  append(el, children);
  return el;
}

function setAttrs(el, attrs) {
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, v === true ? "" : String(v));
  }
}

function append(el, children) {
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
}

/** Sets `el.textContent` only when it changed (keeps selections and screen readers calm). */
export function setText(el, text) {
  const t = String(text);
  if (el.textContent !== t) el.textContent = t;
}

/** "1 h 02 min", "3 min 05 s", "12.3 s", "0.42 s"; "—" for null. */
export function duration(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "—";
  if (seconds < 0) seconds = 0;
  if (seconds < 10) return `${seconds.toFixed(seconds < 1 ? 2 : 1)} s`;
  if (seconds < 60) return `${Math.round(seconds)} s`;
  const total = Math.round(seconds);
  const d = Math.floor(total / 86400);
  const hr = Math.floor((total % 86400) / 3600);
  const min = Math.floor((total % 3600) / 60);
  const sec = total % 60;
  const two = (n) => String(n).padStart(2, "0");
  if (d > 0) return `${d} d ${two(hr)} h`;
  if (hr > 0) return `${hr} h ${two(min)} min`;
  return `${min} min ${two(sec)} s`;
}

/**
 * The ETA of a job for people: "≈ 3 min 05 s", with its 95% interval for a job that stops
 * at its target ("≈ 3 min 05 s (2 min 40 s to 4 min 10 s)"), "not predictable (at least
 * 12 s, at most 8 min 20 s)" when its passes so far cannot predict its error (the status's
 * `eta_note` says why), "not yet predictable" before any, "—" once the job has ended.
 */
export function etaText(j) {
  if (terminal(j.state)) return "—";
  const lo = j.eta_low_seconds;
  const hi = j.eta_high_seconds;
  const interval = Number.isFinite(lo) && Number.isFinite(hi);
  if (j.eta_seconds === null || j.eta_seconds === undefined) {
    if (j.eta_tail_class === "unpredictable" && interval) {
      return `not predictable (at least ${duration(lo)}, at most ${duration(hi)})`;
    }
    return "not yet predictable";
  }
  const point = `≈ ${duration(j.eta_seconds)}`;
  return interval ? `${point} (${duration(lo)} to ${duration(hi)})` : point;
}

/** A number with about three significant digits; "—" for null. */
export function num(x, digits = 3) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "—";
  if (x === 0) return "0";
  const a = Math.abs(x);
  if (a >= 1e6 || a < 1e-3) return x.toExponential(digits - 1);
  return Number(x.toPrecision(digits)).toLocaleString("en-US", { maximumFractionDigits: 6 });
}

/** An integer with thousands separators. */
export function int(x) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "—";
  return Math.round(x).toLocaleString("en-US");
}

/** A relative error as a percentage, "3.10 %". */
export function percent(x) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "—";
  const p = x * 100;
  return `${p >= 10 ? p.toFixed(1) : p >= 1 ? p.toFixed(2) : p.toPrecision(2)} %`;
}

/** "12 s ago" from Unix milliseconds. */
export function ago(unixMs, nowMs = Date.now()) {
  if (!unixMs) return "never";
  const s = (nowMs - unixMs) / 1000;
  if (s < 1.5) return "just now";
  return `${duration(s)} ago`;
}

/** Local date and time of Unix milliseconds. */
export function clock(unixMs) {
  if (!unixMs) return "—";
  return new Date(unixMs).toLocaleString();
}

/** The label of a job: its name, or its scene. */
export function jobLabel(job) {
  if (job.name) return job.name;
  return sceneLabel(job.scene);
}

/** A scene reference for people: "cornell-box" or "scene 1a2b3c4d…". */
export function sceneLabel(scene) {
  if (!scene) return "—";
  if (scene.startsWith("builtin:")) return scene.slice(8);
  return `uploaded ${scene.slice(0, 12)}…`;
}

/** Passes merged as a fraction of those planned, in [0, 1]. */
export function progress(job) {
  if (job.state === "done") return 1;
  if (!job.passes_planned) return 0;
  return Math.min(1, job.passes_done / job.passes_planned);
}

/** Whether a job state will not change any more. */
export function terminal(state) {
  return state === "done" || state === "failed" || state === "canceled";
}

/** Triggers a download of a Blob under `filename`. */
export function download(blob, filename) {
  const url = URL.createObjectURL(blob);
  const a = h("a", { href: url, download: filename });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}
