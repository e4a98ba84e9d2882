// The convergence plot: estimated image error against render time on log-log axes,
// drawn as plain SVG. Monte Carlo error falls like 1/sqrt(time) (ARCHITECTURE.md §3), a straight
// line of slope -1/2 here; the prediction continues that line from the latest point to
// the coordinator's finishing time estimate (eta_seconds).

import { s, duration, percent } from "./util.js";

const W = 640;
const H = 300;
const M = { left: 64, right: 16, top: 14, bottom: 42 };

const log10 = Math.log10;

/** Decade ticks (1, 2, 5 per decade when the range is short) in [lo, hi] (linear values). */
function ticks(lo, hi) {
  const span = log10(hi) - log10(lo);
  const steps = span <= 1.2 ? [1, 2, 5] : span <= 3 ? [1, 3] : [1];
  const out = [];
  for (let e = Math.floor(log10(lo)); e <= Math.ceil(log10(hi)); e++) {
    for (const m of steps) {
      const v = m * 10 ** e;
      if (v >= lo * 0.999 && v <= hi * 1.001) out.push(v);
    }
  }
  return out;
}

/** Widens [lo, hi] to at least `minDecades` decades around its geometric middle. */
function widen(lo, hi, minDecades) {
  const l = log10(lo);
  const u = log10(hi);
  if (u - l >= minDecades) return [lo, hi];
  const mid = (l + u) / 2;
  return [10 ** (mid - minDecades / 2), 10 ** (mid + minDecades / 2)];
}

function timeTick(v) {
  if (v < 1) return `${+v.toPrecision(2)} s`;
  return duration(v).replace(" 00 s", "").replace(" 00 min", "");
}

/**
 * Draws the plot into `svg` (replacing its content).
 *
 * `points`: [{elapsed_seconds, error_estimate}] oldest first (points without an estimate
 * or at time 0 are skipped); `job`: the JobStatus (target_error, eta_seconds, state,
 * error_estimate, elapsed_seconds). Returns the number of points drawn.
 */
export function drawConvergence(svg, points, job) {
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  const pts = points
    .filter((p) => p.error_estimate > 0 && p.elapsed_seconds > 0)
    .map((p) => [p.elapsed_seconds, p.error_estimate]);
  const target = job.target_error > 0 ? job.target_error : null;
  const running = job.state === "running" || job.state === "queued";
  const eta = running && Number.isFinite(job.eta_seconds) && job.eta_seconds >= 0 ? job.eta_seconds : null;

  const children = [];
  if (pts.length === 0) {
    children.push(
      s("text", { x: W / 2, y: H / 2, class: "plot-empty", "text-anchor": "middle" },
        "No error estimate yet: every pixel needs two passes."),
    );
    svg.replaceChildren(...children);
    svg.setAttribute("aria-label", "Convergence plot: no error estimate yet");
    svg.dataset.points = "0";
    return 0;
  }

  const last = pts[pts.length - 1];
  // Prediction: error ~ e1 * sqrt(t1 / t) from the last point to t1 + eta.
  let predicted = null;
  if (eta !== null && eta > 0) {
    const tEnd = last[0] + eta;
    predicted = [tEnd, last[1] * Math.sqrt(last[0] / tEnd)];
  }

  let tLo = Math.min(...pts.map((p) => p[0]));
  let tHi = Math.max(last[0], predicted ? predicted[0] : 0);
  let eLo = Math.min(...pts.map((p) => p[1]), target ?? Infinity, predicted ? predicted[1] : Infinity);
  let eHi = Math.max(...pts.map((p) => p[1]), target ?? 0);
  [tLo, tHi] = widen(tLo / 1.15, tHi * 1.15, 1);
  [eLo, eHi] = widen(eLo / 1.25, eHi * 1.25, 1);

  const x = (t) => M.left + ((log10(t) - log10(tLo)) / (log10(tHi) - log10(tLo))) * (W - M.left - M.right);
  const y = (e) => M.top + ((log10(eHi) - log10(e)) / (log10(eHi) - log10(eLo))) * (H - M.top - M.bottom);
  const x0 = M.left;
  const x1 = W - M.right;
  const y0 = H - M.bottom;
  const y1 = M.top;

  // Grid and axes.
  const grid = s("g", { class: "plot-grid" });
  for (const t of ticks(tLo, tHi)) {
    grid.append(s("line", { x1: x(t), x2: x(t), y1: y0, y2: y1 }));
    children.push(s("text", { x: x(t), y: y0 + 16, class: "tick", "text-anchor": "middle" }, timeTick(t)));
  }
  for (const e of ticks(eLo, eHi)) {
    grid.append(s("line", { x1: x0, x2: x1, y1: y(e), y2: y(e) }));
    children.push(s("text", { x: x0 - 6, y: y(e) + 4, class: "tick", "text-anchor": "end" }, percent(e)));
  }
  children.unshift(grid);
  children.push(
    s("path", { class: "plot-axis", d: `M${x0},${y1}V${y0}H${x1}` }),
    s("text", { x: (x0 + x1) / 2, y: H - 6, class: "axis-label", "text-anchor": "middle" }, "render time"),
    s("text", {
      x: 14, y: (y0 + y1) / 2, class: "axis-label", "text-anchor": "middle",
      transform: `rotate(-90 14 ${(y0 + y1) / 2})`,
    }, "estimated error (RMS relative)"),
  );

  // Target line.
  if (target !== null) {
    children.push(
      s("line", { class: "plot-target", x1: x0, x2: x1, y1: y(target), y2: y(target) }),
      s("text", { class: "plot-target-label", x: x1 - 4, y: y(target) - 5, "text-anchor": "end" },
        `target ${percent(target)}`),
    );
  }

  // Prediction to the finishing time.
  if (predicted) {
    children.push(
      s("line", {
        class: "plot-predicted", x1: x(last[0]), y1: y(last[1]), x2: x(predicted[0]), y2: y(predicted[1]),
      }),
      s("line", { class: "plot-eta", x1: x(predicted[0]), x2: x(predicted[0]), y1: y0, y2: y1 }),
      s("text", {
        class: "plot-eta-label", x: x(predicted[0]) - 4, y: y1 + 12, "text-anchor": "end",
      }, `done in ≈ ${duration(eta)}${target !== null && predicted[1] > target * 1.05 ? ` at ≈ ${percent(predicted[1])} (sample budget)` : ""}`),
    );
  }

  // The measured points.
  const line = pts.map((p, i) => `${i ? "L" : "M"}${x(p[0]).toFixed(1)},${y(p[1]).toFixed(1)}`).join("");
  children.push(s("path", { class: "plot-line", d: line }));
  const dots = s("g", { class: "plot-points" });
  const step = Math.max(1, Math.ceil(pts.length / 400));
  pts.forEach((p, i) => {
    if (i % step !== 0 && i !== pts.length - 1) return;
    dots.append(
      s("circle", { class: "pt", cx: x(p[0]).toFixed(1), cy: y(p[1]).toFixed(1), r: 2.5 },
        s("title", {}, `${duration(p[0])}: ${percent(p[1])}`)),
    );
  });
  children.push(dots);

  svg.replaceChildren(...children);
  const words = [`Convergence plot: ${pts.length} points, latest error ${percent(last[1])} at ${duration(last[0])}`];
  if (target !== null) words.push(`target ${percent(target)}`);
  if (predicted) words.push(`predicted done in ${duration(eta)}`);
  svg.setAttribute("aria-label", words.join("; "));
  svg.dataset.points = String(pts.length);
  return pts.length;
}
