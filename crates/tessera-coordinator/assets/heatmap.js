// The per-tile heat map drawn over the preview: relative error (log scale) or samples per
// pixel (linear), from GET /api/v1/jobs/{id}/tiles.

import { num, percent } from "./util.js";

// A perceptually ordered ramp (dark blue, teal, green, yellow), as in viridis.
const RAMP = [
  [68, 1, 84],
  [59, 82, 139],
  [33, 145, 140],
  [94, 201, 98],
  [253, 231, 37],
];

/** The ramp color at u in [0, 1], "rgb(r g b)". */
export function rampColor(u) {
  const t = Math.min(1, Math.max(0, u)) * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(t));
  const f = t - i;
  const c = RAMP[i].map((a, k) => Math.round(a + (RAMP[i + 1][k] - a) * f));
  return `rgb(${c[0]} ${c[1]} ${c[2]})`;
}

/** The value shown for a tile in `mode` ("error" or "spp"), or null. */
function value(tile, mode) {
  if (mode === "spp") return tile.spp;
  return tile.error > 0 ? tile.error : null;
}

/**
 * Draws `map` (a TileMap) into `canvas` at the image's resolution. Returns the legend:
 * {min, max, label(v), scale} or null when there is nothing to show.
 */
export function drawHeatmap(canvas, map, mode) {
  if (canvas.width !== map.width) canvas.width = map.width;
  if (canvas.height !== map.height) canvas.height = map.height;
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const values = map.tiles.map((t) => value(t, mode)).filter((v) => v !== null && Number.isFinite(v));
  if (values.length === 0) return null;
  let min = Math.min(...values);
  let max = Math.max(...values);
  const logScale = mode === "error";
  const f = logScale ? Math.log10 : (v) => v;
  if (!logScale) min = Math.min(min, 0);
  const lo = f(min);
  const hi = f(max);
  for (const t of map.tiles) {
    const v = value(t, mode);
    if (v === null) {
      ctx.fillStyle = "rgb(128 128 128 / 0.5)";
    } else {
      ctx.fillStyle = rampColor(hi > lo ? (f(v) - lo) / (hi - lo) : 0.5);
    }
    ctx.fillRect(t.x, t.y, t.width, t.height);
  }
  // Tile outlines: stopped tiles dashed-free, running ones outlined so progress is visible.
  ctx.lineWidth = Math.max(1, map.width / 512);
  for (const t of map.tiles) {
    if (t.done) continue;
    ctx.strokeStyle = "rgb(255 255 255 / 0.6)";
    ctx.strokeRect(t.x + 0.5, t.y + 0.5, t.width - 1, t.height - 1);
  }
  const label = mode === "spp" ? (v) => `${num(v)} spp` : (v) => percent(v);
  return { min, max, label, scale: logScale ? "log" : "linear" };
}

/** The tile under the canvas-relative point (px, py), in image pixels, or null. */
export function tileAt(map, px, py) {
  for (const t of map.tiles) {
    if (px >= t.x && px < t.x + t.width && py >= t.y && py < t.y + t.height) return t;
  }
  return null;
}

/** A sentence about one tile, for its tooltip. */
export function describeTile(t, passesPlanned) {
  const err = t.error > 0 ? `error ${percent(t.error)}` : "no error estimate yet";
  const state = t.done ? "stopped" : "rendering";
  return `Tile ${t.index} (${t.x}, ${t.y}): ${t.passes} of ${passesPlanned} passes, ${num(t.spp)} spp, ${err}, ${state}`;
}
