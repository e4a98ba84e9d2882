// The job page: status, live preview with a per-tile heat map, the convergence plot, the
// render plan, and the cancel and download buttons.
//
// Each poll asks only for GET /api/v1/jobs/{id}; the image, tiles and history are fetched
// again only when the merged pass count (or the state, or the frame shown) changed.

import { api } from "./api.js";
import { drawConvergence } from "./plot.js";
import { drawHeatmap, tileAt, describeTile } from "./heatmap.js";
import {
  h, s, setText, duration, num, int, percent, jobLabel, sceneLabel, progress, terminal, clock, download,
  etaText,
} from "./util.js";

function field(dl, label) {
  const dd = h("dd");
  dl.append(h("div", { class: "field" }, h("dt", {}, label), dd));
  return dd;
}

/** The job page for job `id`. */
export function jobView(id, poke) {
  const title = h("h1", { id: "job-title" }, `Job ${id}`);
  const badge = h("span", { id: "job-state", class: "badge" }, "…");
  const cancelBtn = h("button", { type: "button", id: "job-cancel", class: "danger", onclick: cancel }, "Cancel job");
  const exrBtn = h("button", { type: "button", id: "job-exr", onclick: () => save("exr") }, "Download EXR");
  const pngBtn = h("button", { type: "button", id: "job-png", onclick: () => save("png") }, "Download PNG");
  const actionMsg = h("p", { class: "action-msg", role: "status", "aria-live": "polite" });

  // Status fields.
  const dl = h("dl", { class: "fields" });
  const f = {
    scene: field(dl, "Scene"),
    progress: field(dl, "Progress"),
    spp: field(dl, "Samples per pixel"),
    error: field(dl, "Error estimate / target"),
    elapsed: field(dl, "Elapsed"),
    eta: field(dl, "Remaining"),
    size: field(dl, "Resolution"),
    frames: field(dl, "Frames"),
    tiles: field(dl, "Tiles"),
    adaptive: field(dl, "Adaptive stopping"),
    priority: field(dl, "Priority"),
    faults: field(dl, "Worker faults"),
    created: field(dl, "Submitted"),
  };
  const bar = h("progress", { max: 1, value: 0, id: "job-progress" });
  const barText = h("span", { class: "sub" });
  f.progress.append(bar, barText);
  const failure = h("p", { class: "failure", role: "alert", hidden: true });

  // Preview and heat map.
  const img = h("img", { id: "preview-img", alt: "Preview of the merged image" });
  const overlay = h("canvas", { id: "heatmap", class: "heatmap", "aria-hidden": "true" });
  const waiting = h("p", { class: "preview-waiting" }, "Waiting for the first merged pass…");
  const stage = h("div", { class: "stage" }, waiting, img, overlay);
  img.hidden = true;
  overlay.hidden = true;
  const caption = h("figcaption", { id: "preview-caption" });
  const tileInfo = h("p", { class: "tile-info", "aria-live": "polite" });
  const legendLo = h("span");
  const legendHi = h("span");
  const legend = h("div", { class: "legend", hidden: true }, legendLo, h("span", { class: "ramp", "aria-hidden": "true" }), legendHi);
  let overlayMode = "none";
  const modes = h("fieldset", { class: "segmented" }, h("legend", {}, "Overlay"),
    [["none", "Image only"], ["error", "Tile error"], ["spp", "Tile spp"]].map(([value, label]) =>
      h("label", {},
        h("input", {
          type: "radio", name: `overlay-${id}`, value, checked: value === "none",
          onchange: () => {
            overlayMode = value;
            drawOverlay();
          },
        }), ` ${label}`)));
  const frameInput = h("input", { type: "number", id: "job-frame", step: 1, class: "short" });
  const frameLabel = h("label", { hidden: true }, "Frame ", frameInput);
  frameInput.addEventListener("change", () => {
    lastKey = null;
    poke();
  });

  // Plot.
  const svg = s("svg", { id: "plot", class: "plot", role: "img", "aria-label": "Convergence plot" });
  const plotNote = h("p", { class: "sub" });

  // Plan and settings.
  const planBox = h("div", { id: "plan" }, h("p", { class: "sub" }, "Not analysed yet."));
  const settingsBox = h("dl", { class: "fields settings" });

  const el = h("article", { "aria-labelledby": "job-title", class: "job" },
    h("p", { class: "crumbs" }, h("a", { href: "#/jobs" }, "← All jobs")),
    h("div", { class: "section-head" }, h("div", { class: "title-line" }, title, badge),
      h("div", { class: "actions" }, pngBtn, exrBtn, cancelBtn)),
    actionMsg, failure,
    h("div", { class: "job-grid" },
      h("section", { class: "panel preview", "aria-labelledby": "h-preview" },
        h("h2", { id: "h-preview" }, "Preview"),
        h("div", { class: "toolbar" }, modes, frameLabel),
        h("figure", {}, stage, caption), legend, tileInfo),
      h("section", { class: "panel", "aria-labelledby": "h-status" }, h("h2", { id: "h-status" }, "Status"), dl),
      h("section", { class: "panel", "aria-labelledby": "h-plot" },
        h("h2", { id: "h-plot" }, "Convergence"),
        svg, plotNote),
      h("section", { class: "panel", "aria-labelledby": "h-plan" },
        h("h2", { id: "h-plan" }, "Render plan"), planBox,
        h("details", {}, h("summary", {}, "Settings"), settingsBox))));

  let job = null;
  let lastKey = null;
  let imageUrl = null;
  let tiles = null;
  let history = [];
  let planJson = null;
  let settingsJson = null;

  function frame() {
    const v = frameInput.value === "" ? null : Number(frameInput.value);
    return Number.isInteger(v) ? v : null;
  }

  async function cancel() {
    if (!job) return;
    if (!confirm(`Cancel job ${job.id} (${jobLabel(job)})? The passes merged so far are kept; no more are rendered.`)) return;
    cancelBtn.disabled = true;
    setText(actionMsg, "Canceling…");
    try {
      await api.cancel(id);
      setText(actionMsg, "Job canceled.");
      poke();
    } catch (e) {
      setText(actionMsg, `Could not cancel: ${e.message}`);
      cancelBtn.disabled = false;
    }
  }

  async function save(format) {
    const btn = format === "exr" ? exrBtn : pngBtn;
    btn.disabled = true;
    setText(actionMsg, `Downloading the ${format.toUpperCase()}…`);
    try {
      const blob = await api.image(id, format, frame());
      const fr = frame() !== null ? `-f${frame()}` : "";
      const base = (job ? jobLabel(job) : "job").replace(/[^A-Za-z0-9._-]+/g, "_");
      download(blob, `${base}-${id}${fr}.${format}`);
      setText(actionMsg, `Downloaded the ${format.toUpperCase()} (${int(blob.size)} bytes).`);
    } catch (e) {
      setText(actionMsg, `Could not download the ${format.toUpperCase()}: ${e.message}`);
    } finally {
      btn.disabled = false;
    }
  }

  function renderStatus(j) {
    setText(title, jobLabel(j));
    document.title = `${jobLabel(j)} · ${j.state} · Tessera`;
    badge.className = `badge state-${j.state}`;
    setText(badge, j.state);
    el.dataset.state = j.state;
    cancelBtn.hidden = terminal(j.state);
    if (!terminal(j.state)) cancelBtn.disabled = false;
    setText(f.scene, j.scene.startsWith("builtin:") ? j.scene : `${sceneLabel(j.scene)} (uploaded)`);
    f.scene.title = j.scene;
    const p = progress(j);
    bar.value = p;
    bar.setAttribute("aria-label", `${Math.round(p * 100)} % of the planned passes`);
    const early = j.state === "done" && j.passes_done < j.passes_planned ? ", stopped early" : "";
    setText(barText, ` ${int(j.passes_done)} of ${int(j.passes_planned)} passes${early}`);
    setText(f.spp, `${num(j.spp_so_far)} of ${int(j.settings?.spp)} planned`);
    const target = j.target_error ? percent(j.target_error) : "none";
    // Once done, the server's verdict: a finished job need not have reached its target.
    const verdict = j.stop_reason ? ` (${j.stop_reason})` : "";
    // The estimate's caveat (path-traced caustics of a tiny light, adaptive stopping on a
    // scene of rare paths): flagged, in full on hover.
    const caveat = j.error_estimate_caveat ? " — may be optimistic" : "";
    setText(f.error, `${percent(j.error_estimate)} / ${target}${verdict}${caveat}`);
    f.error.title = j.error_estimate_caveat || "";
    setText(f.elapsed, duration(j.elapsed_seconds));
    setText(f.eta, etaText(j));
    // Why the ETA is widened or not predictable (a job that stops at its target): on hover.
    f.eta.title = terminal(j.state) ? "" : j.eta_note || "";
    const w = j.width ?? j.settings?.width;
    const hh = j.height ?? j.settings?.height;
    setText(f.size, w && hh ? `${w} × ${hh}` : "from the scene (not loaded yet)");
    setText(f.frames, `${int(j.frames_done)} of ${int(j.frames_total)} done`);
    setText(f.tiles, int(j.tiles_total));
    setText(f.adaptive, j.adaptive || j.settings?.adaptive || "off");
    setText(f.priority, j.priority);
    setText(f.faults, int(j.faults));
    setText(f.created, clock(j.created_unix_ms));
    failure.hidden = !j.error;
    setText(failure, j.error ? `The job failed: ${j.error}` : "");
    if (j.frames_total > 1) {
      frameLabel.hidden = false;
      const start = j.settings?.frames?.start ?? 0;
      frameInput.min = start;
      frameInput.max = j.settings?.frames?.end ?? start + j.frames_total - 1;
      if (frameInput.value === "") frameInput.value = start;
    }
    const sj = JSON.stringify(j.settings);
    if (sj !== settingsJson) {
      settingsJson = sj;
      settingsBox.replaceChildren(...Object.entries(j.settings || {}).map(([k, v]) =>
        h("div", { class: "field" }, h("dt", {}, k), h("dd", {}, v === null ? "—" : typeof v === "object" ? JSON.stringify(v) : String(v)))));
    }
  }

  function renderPlan(plan) {
    const pj = JSON.stringify(plan);
    if (pj === planJson) return;
    planJson = pj;
    if (!plan) {
      planBox.replaceChildren(h("p", { class: "sub" }, "Not analysed yet (the scene loads when the job starts)."));
      return;
    }
    const parts = [
      h("p", {}, "Integrator ", h("strong", { id: "plan-integrator" }, plan.integrator ?? "—"),
        `, max depth ${plan.max_depth ?? "—"}, Russian roulette from depth ${plan.rr_depth ?? "—"}, lens sampling ${plan.lens_sampling ? "on" : "off"}.`),
    ];
    if (plan.overridden) parts.push(h("p", { class: "note" }, `Overridden: ${plan.overridden}`));
    const effects = plan.effects || [];
    parts.push(h("h3", {}, "Effects simulated"));
    parts.push(effects.length
      ? h("ul", { class: "effects" }, effects.map((e) => h("li", {}, h("span", { class: "chip" }, e.kind), " ", h("span", { class: "sub" }, e.evidence))))
      : h("p", { class: "sub" }, "None: the scene has no light to trace."));
    const absent = plan.absent || [];
    if (absent.length) {
      parts.push(h("h3", {}, "Absent, not simulated"));
      parts.push(h("p", { class: "chips" }, absent.map((k) => h("span", { class: "chip muted" }, k))));
    }
    const reasons = plan.reasons || [];
    if (reasons.length) {
      parts.push(h("h3", {}, "Why"));
      parts.push(h("ul", {}, reasons.map((r) => h("li", {}, r))));
    }
    planBox.replaceChildren(...parts);
  }

  async function loadImage(j, signal) {
    if (!(j.passes_done > 0)) {
      img.hidden = true;
      waiting.hidden = false;
      setText(caption, j.state === "queued" ? "Queued: no pass merged yet." : "No pass merged yet.");
      return;
    }
    try {
      const blob = await api.image(id, "png", frame(), signal);
      const url = URL.createObjectURL(blob);
      await new Promise((resolve, reject) => {
        img.onload = resolve;
        img.onerror = () => reject(new Error("the PNG could not be decoded"));
        img.src = url;
      });
      if (imageUrl) URL.revokeObjectURL(imageUrl);
      imageUrl = url;
      img.hidden = false;
      waiting.hidden = true;
      img.classList.toggle("pixelated", img.naturalWidth < 256);
      setText(caption, `${img.naturalWidth} × ${img.naturalHeight}, after ${int(j.passes_done)} merged passes (${num(j.spp_so_far)} spp)${terminal(j.state) ? ", final" : ""}.`);
    } catch (e) {
      if (e.name === "AbortError") throw e;
      setText(caption, `Preview unavailable: ${e.message}`);
    }
  }

  async function loadTiles(signal) {
    try {
      tiles = await api.tiles(id, frame(), signal);
    } catch (e) {
      if (e.name === "AbortError") throw e;
      tiles = null;
      setText(tileInfo, `Tile map unavailable: ${e.message}`);
    }
    drawOverlay();
  }

  async function loadHistory(signal) {
    try {
      const hist = await api.history(id, signal);
      history = hist.points || [];
    } catch (e) {
      if (e.name === "AbortError") throw e;
      setText(plotNote, `History unavailable: ${e.message}`);
    }
  }

  function drawOverlay() {
    const show = overlayMode !== "none" && tiles && tiles.tiles?.length;
    overlay.hidden = !show || img.hidden;
    legend.hidden = !show;
    if (!show) return;
    const lg = drawHeatmap(overlay, tiles, overlayMode);
    if (lg) {
      setText(legendLo, lg.label(lg.min));
      setText(legendHi, `${lg.label(lg.max)} (${lg.scale} scale)`);
    } else {
      setText(legendLo, overlayMode === "error" ? "no tile has an error estimate yet" : "no samples yet");
      setText(legendHi, "");
    }
  }

  overlay.addEventListener("mousemove", (ev) => {
    if (!tiles) return;
    const r = overlay.getBoundingClientRect();
    const px = ((ev.clientX - r.left) / r.width) * tiles.width;
    const py = ((ev.clientY - r.top) / r.height) * tiles.height;
    const t = tileAt(tiles, px, py);
    setText(tileInfo, t ? describeTile(t, tiles.passes_planned) : "");
  });
  overlay.addEventListener("mouseleave", () => setText(tileInfo, ""));

  function renderPlot(j) {
    const n = drawConvergence(svg, history, j);
    const parts = [];
    if (n) parts.push(`${n} points.`);
    if (!terminal(j.state) && j.eta_seconds !== null && j.eta_seconds !== undefined) {
      parts.push(`Predicted to finish at ${new Date(Date.now() + j.eta_seconds * 1000).toLocaleTimeString()} (in ≈ ${duration(j.eta_seconds)}).`);
    } else if (j.state === "done") {
      parts.push(`Finished after ${duration(j.elapsed_seconds)} at ${percent(j.error_estimate)} error.`);
    }
    setText(plotNote, parts.join(" "));
  }

  return {
    el,
    title: `Job ${id}`,
    async refresh(signal) {
      const j = await api.job(id, signal);
      job = j;
      renderStatus(j);
      renderPlan(j.plan);
      const key = `${j.passes_done}|${j.state}|${frame()}`;
      if (key !== lastKey) {
        await Promise.all([loadImage(j, signal), loadTiles(signal), loadHistory(signal)]);
        lastKey = key;
        drawOverlay();
      }
      renderPlot(j);
    },
    destroy() {
      if (imageUrl) URL.revokeObjectURL(imageUrl);
    },
  };
}
