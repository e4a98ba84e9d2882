// The submit form: a built-in scene (GET /api/v1/builtins) or an uploaded .gltf/.glb
// (POST /api/v1/scenes, then the job names the returned hash), and the job settings
// (POST /api/v1/jobs with an idempotency key, so a double click submits once). "Quote"
// asks for a dry run first (POST /api/v1/jobs?dry_run=true): the predicted time and
// worker-seconds to reach 10%, 5%, 2% and 1% error (or the target), shown before you submit.
// The lighting: an environment image (.hdr/.exr, uploaded like a scene; the job names its
// hash) or a uniform colour, with a strength and a rotation; empty: the scene's lights only.

import { api, idempotencyKey } from "./api.js";
import { h, int } from "./util.js";

let builtinsCache = null;

function row(label, input, hint) {
  const hintEl = hint ? h("span", { class: "hint", id: `${input.id}-hint` }, hint) : null;
  if (hintEl) input.setAttribute("aria-describedby", hintEl.id);
  return h("div", { class: "form-row" }, h("label", { for: input.id }, label), input, hintEl);
}

/** The submit page. */
export function submitView() {
  const srcBuiltin = h("input", { type: "radio", name: "source", id: "f-source-builtin", value: "builtin", checked: true });
  const srcUpload = h("input", { type: "radio", name: "source", id: "f-source-upload", value: "upload" });
  const builtin = h("select", { id: "f-scene", name: "scene" }, h("option", { value: "" }, "loading…"));
  const file = h("input", { type: "file", id: "f-file", name: "file", accept: ".gltf,.glb,model/gltf-binary,model/gltf+json" });
  const num = (id, attrs) => h("input", { type: "number", id, name: id.slice(2), inputmode: "numeric", ...attrs });
  const width = num("f-width", { min: 1, max: 16384, step: 1, placeholder: "scene's" });
  const height = num("f-height", { min: 1, max: 16384, step: 1, placeholder: "scene's" });
  const spp = num("f-spp", { min: 1, max: 1048576, step: 1, value: 64, required: true });
  const target = h("input", { type: "number", id: "f-target", name: "target_error", min: 0, max: 1, step: "any", placeholder: "none", inputmode: "decimal" });
  const adaptive = h("select", { id: "f-adaptive", name: "adaptive" },
    h("option", { value: "off" }, "off: every planned pass"),
    h("option", { value: "sequential" }, "sequential: stop tiles early (fast, slightly biased)"),
    h("option", { value: "unbiased" }, "unbiased: pilot passes fix each pixel's budget"));
  const priority = num("f-priority", { step: 1, value: 0 });
  const timeLimit = h("input", { type: "number", id: "f-time", name: "time_limit_seconds", min: 0, step: "any", placeholder: "none", inputmode: "decimal" });
  const frameStart = num("f-frame-start", { min: 0, step: 1, placeholder: "0" });
  const frameEnd = num("f-frame-end", { min: 0, step: 1, placeholder: "first" });
  const fps = h("input", { type: "number", id: "f-fps", name: "fps", min: 0, step: "any", placeholder: "24", inputmode: "decimal" });
  const animation = h("input", { type: "text", id: "f-animation", name: "animation", maxlength: 200, autocomplete: "off", placeholder: "all" });
  const shutterOpen = h("input", { type: "number", id: "f-shutter-open", name: "shutter", min: -1, max: 1, step: "any", placeholder: "none", inputmode: "decimal" });
  const shutterClose = h("input", { type: "number", id: "f-shutter-close", name: "shutter-close", min: -1, max: 1, step: "any", placeholder: "none", inputmode: "decimal" });
  const name = h("input", { type: "text", id: "f-name", name: "name", maxlength: 200, autocomplete: "off", placeholder: "optional label" });
  const envFile = h("input", { type: "file", id: "f-env-file", name: "environment", accept: ".hdr,.exr,image/vnd.radiance,image/x-exr" });
  const envColour = h("input", { type: "text", id: "f-env-colour", name: "environment", autocomplete: "off", placeholder: "none, e.g. 1,1,1" });
  const envStrength = h("input", { type: "number", id: "f-env-strength", name: "environment.strength", min: 0, step: "any", placeholder: "1", inputmode: "decimal" });
  const envRotation = h("input", { type: "number", id: "f-env-rotation", name: "environment.rotation_degrees", min: -360, max: 360, step: "any", placeholder: "0", inputmode: "decimal" });
  const submit = h("button", { type: "submit", id: "f-submit", class: "primary" }, "Submit job");
  const quoteButton = h("button", { type: "button", id: "f-quote" }, "Quote");
  const status = h("div", { id: "submit-status", class: "form-status", role: "alert", "aria-live": "assertive" });
  const quoteEl = h("div", { id: "quote", class: "quote", "aria-live": "polite" });

  const builtinRow = row("Built-in scene", builtin);
  const uploadRow = row("glTF file", file, "A .glb, or a .gltf with its buffers and images embedded.");
  uploadRow.hidden = true;

  const fields = {
    scene: builtin, width, height, spp, target_error: target, adaptive, priority,
    time_limit_seconds: timeLimit, name, frames: frameEnd, fps, animation, shutter: shutterOpen,
    environment: envColour,
  };

  const form = h("form", { id: "submit-form", class: "submit-form", novalidate: true },
    h("fieldset", {}, h("legend", {}, "Scene"),
      h("div", { class: "radio-line" },
        h("label", {}, srcBuiltin, " Built-in"),
        h("label", {}, srcUpload, " Upload .gltf / .glb")),
      builtinRow, uploadRow),
    h("fieldset", {}, h("legend", {}, "Image and quality"),
      h("div", { class: "form-pair" }, row("Width (px)", width), row("Height (px)", height)),
      row("Maximum samples per pixel", spp, "Rounded up to whole passes."),
      row("Target error", target, "RMS relative error at which to stop, e.g. 0.02 for 2 %. Empty: render every sample."),
      row("Adaptive stopping", adaptive),
      row("Time limit (s)", timeLimit)),
    h("fieldset", {}, h("legend", {}, "Frames and animation"),
      h("div", { class: "form-pair" }, row("First frame", frameStart), row("Last frame", frameEnd)),
      row("Frames per second", fps, "Frame F shows the scene's glTF animations at F / fps seconds."),
      row("Animation", animation, "Name or index of one animation; empty: all of them play."),
      h("div", { class: "form-pair" }, row("Shutter opens (frames)", shutterOpen), row("Shutter closes (frames)", shutterClose)),
      h("p", { class: "hint" }, "Motion blur: when the shutter opens and closes relative to each frame, e.g. -0.25 and 0.25. Empty: no blur.")),
    h("fieldset", {}, h("legend", {}, "Lighting"),
      row("Environment image", envFile, "An equirectangular .hdr or .exr that lights the scene from every direction (uploaded like a scene)."),
      row("Or a uniform colour", envColour, "Radiance R,G,B, e.g. 1,1,1 for a white sky. Empty and no image: the scene's own lights only."),
      h("div", { class: "form-pair" }, row("Strength", envStrength), row("Rotation (degrees)", envRotation))),
    h("fieldset", {}, h("legend", {}, "Scheduling"),
      row("Priority", priority, "Higher runs first."),
      row("Name", name)),
    h("div", { class: "actions" }, quoteButton, submit),
    status, quoteEl);

  const el = h("section", { "aria-labelledby": "submit-title", class: "submit" },
    h("h1", { id: "submit-title" }, "Submit a job"), form);

  for (const r of [srcBuiltin, srcUpload]) {
    r.addEventListener("change", () => {
      const up = srcUpload.checked;
      uploadRow.hidden = !up;
      builtinRow.hidden = up;
    });
  }

  function clearErrors() {
    for (const input of [...Object.values(fields), file, frameStart, shutterClose, envFile, envStrength, envRotation]) input.removeAttribute("aria-invalid");
    status.replaceChildren();
    status.className = "form-status";
  }

  function showError(message, fieldName) {
    status.className = "form-status error";
    status.replaceChildren(h("p", {}, message));
    const input = fieldName === "scene" && srcUpload.checked ? file
      : fieldName === "environment.strength" ? envStrength
      : fieldName === "environment.rotation_degrees" ? envRotation
      : fieldName?.startsWith("environment") && envFile.files?.length ? envFile
      : fields[fieldName?.split(".")[0]];
    if (input) {
      input.setAttribute("aria-invalid", "true");
      input.setAttribute("aria-errormessage", status.id);
      input.focus();
    }
  }

  function intOrNull(input, label) {
    if (input.value.trim() === "") return null;
    const v = Number(input.value);
    if (!Number.isInteger(v)) throw Object.assign(new Error(`${label}: expected a whole number, got "${input.value}"`), { field: input.name });
    return v;
  }

  function floatOrNull(input, label) {
    if (input.value.trim() === "") return null;
    const v = Number(input.value);
    if (!Number.isFinite(v)) throw Object.assign(new Error(`${label}: expected a number, got "${input.value}"`), { field: input.name });
    return v;
  }

  let key = idempotencyKey();
  form.addEventListener("input", () => {
    key = idempotencyKey(); // a changed form is a new job
  });

  // The form's settings, or null after showing what is wrong.
  function readSettings() {
    let settings;
    try {
      settings = {
        scene: builtin.value,
        spp: intOrNull(spp, "spp"),
        width: intOrNull(width, "width"),
        height: intOrNull(height, "height"),
        target_error: floatOrNull(target, "target_error"),
        adaptive: adaptive.value,
        priority: intOrNull(priority, "priority") ?? 0,
        time_limit_seconds: floatOrNull(timeLimit, "time_limit_seconds"),
        name: name.value.trim() || null,
        fps: floatOrNull(fps, "fps"),
        animation: animation.value.trim() || null,
      };
      const first = intOrNull(frameStart, "frames.start");
      const last = intOrNull(frameEnd, "frames.end");
      if (first !== null || last !== null) settings.frames = { start: first ?? 0, end: last ?? first ?? 0 };
      const open = floatOrNull(shutterOpen, "shutter");
      const close = floatOrNull(shutterClose, "shutter");
      if ((open === null) !== (close === null)) throw Object.assign(new Error("shutter: give both when it opens and when it closes, or neither"), { field: "shutter" });
      if (open !== null) settings.shutter = [open, close];
      if (settings.spp === null) throw Object.assign(new Error("spp: required"), { field: "spp" });
      const strength = floatOrNull(envStrength, "environment.strength");
      const rotation = floatOrNull(envRotation, "environment.rotation_degrees");
      const colour = envColour.value.trim();
      const image = envFile.files && envFile.files[0];
      if (colour && image) throw Object.assign(new Error("environment: choose an image or a colour, not both"), { field: "environment" });
      if (colour || image) {
        // An image's source is its hash, set once it is uploaded (environmentReady).
        settings.environment = { source: colour, strength: strength ?? 1, rotation_degrees: rotation ?? 0 };
      } else if (strength !== null || rotation !== null) {
        throw Object.assign(new Error("environment: a strength or rotation needs an image or a colour"), { field: "environment" });
      }
    } catch (e) {
      showError(e.message, e.field);
      return null;
    }
    for (const k of Object.keys(settings)) if (settings[k] === null) delete settings[k];
    return settings;
  }

  // The uploaded file's hash, so that a quote and then a submission upload it once.
  let uploaded = null;

  // Sets settings.scene to the uploaded file's hash (uploading it if needed); false after
  // showing what went wrong.
  async function sceneReady(settings) {
    if (!srcUpload.checked) {
      if (settings.scene) return true;
      showError("Choose a built-in scene.", "scene");
      return false;
    }
    const f = file.files && file.files[0];
    if (!f) {
      showError("Choose a .gltf or .glb file to upload.", "scene");
      return false;
    }
    if (uploaded && uploaded.file === f) {
      settings.scene = uploaded.hash;
      return true;
    }
    status.className = "form-status";
    status.replaceChildren(h("p", {}, `Uploading ${f.name} (${int(f.size)} bytes)…`));
    const type = f.name.toLowerCase().endsWith(".glb") ? "model/gltf-binary" : "model/gltf+json";
    let up;
    try {
      up = await api.uploadScene(await f.arrayBuffer(), type);
    } catch (e) {
      showError(`The scene was not accepted: ${e.message}`, "scene");
      return false;
    }
    status.replaceChildren(h("p", {},
      `Uploaded: ${int(up.triangles)} triangles, ${up.meshes} meshes, ${up.materials} materials, ${up.lights} lights.`));
    uploaded = { file: f, hash: up.hash };
    settings.scene = up.hash;
    return true;
  }

  // The uploaded environment image's hash, for the same reason.
  let uploadedEnv = null;

  // Sets settings.environment.source to the chosen image's hash (uploading it if
  // needed); false after showing what went wrong.
  async function environmentReady(settings) {
    const f = envFile.files && envFile.files[0];
    if (!settings.environment || !f) return true;
    if (uploadedEnv && uploadedEnv.file === f) {
      settings.environment.source = uploadedEnv.hash;
      return true;
    }
    status.className = "form-status";
    status.replaceChildren(h("p", {}, `Uploading ${f.name} (${int(f.size)} bytes)…`));
    let up;
    try {
      up = await api.uploadScene(await f.arrayBuffer(), "application/octet-stream");
    } catch (e) {
      showError(`The environment image was not accepted: ${e.message}`, "environment");
      return false;
    }
    status.replaceChildren();
    uploadedEnv = { file: f, hash: up.hash };
    settings.environment.source = up.hash;
    return true;
  }

  function seconds(s) {
    if (s < 100) return `${s.toFixed(s < 10 ? 2 : 1)} s`;
    if (s < 7200) return `${(s / 60).toFixed(1)} min`;
    return `${(s / 3600).toFixed(1)} h`;
  }

  function showQuote(q) {
    if (q.black || !q.quote) {
      quoteEl.replaceChildren(h("p", {}, "The image is black (no light reaches the camera): nothing to render."));
      return;
    }
    const cell = (i) => `${seconds(i.estimate)} (${seconds(i.low)}–${seconds(i.high)})`;
    const tr = (label, c, note) => h("tr", {},
      h("th", { scope: "row" }, label),
      h("td", {}, `${int(c.spp.estimate)}`),
      h("td", {}, cell(c.seconds)),
      h("td", {}, cell(c.worker_seconds)),
      h("td", {}, note || ""));
    const rows = [tr(`as planned: error ${(q.quote.planned.error.estimate * 100).toFixed(2)} %`, q.quote.planned)];
    for (const t of q.quote.targets) {
      rows.push(tr(`${+(t.target * 100).toFixed(3)} % error`, t.cost, t.within_plan ? "" : "needs more than the planned spp"));
    }
    quoteEl.replaceChildren(
      h("h2", {}, "Quote"),
      h("p", { class: "hint" }, `${q.width}×${q.height}, ${q.frames} frame(s), ${int(q.spp)} spp planned, ${q.integrator}; for ${q.fleet}. Pilot: ${q.pilot_tiles} tiles, ${q.quote.pilot_passes} passes in ${q.pilot_seconds.toFixed(2)} s. Intervals are 95 %.`),
      h("div", { class: "table-wrap" }, h("table", { class: "grid quote-table" },
        h("thead", {}, h("tr", {},
          h("th", { scope: "col" }, "to reach"), h("th", { scope: "col" }, "spp"),
          h("th", { scope: "col" }, "wall time"), h("th", { scope: "col" }, "worker-seconds"),
          h("th", { scope: "col" }, ""))),
        h("tbody", {}, ...rows))),
      // The estimate's caveat (path-traced caustics of a tiny light, adaptive stopping on a
      // scene of rare paths): these errors may be low.
      ...(q.error_estimate_caveat ? [h("p", { class: "hint caveat" }, `The quoted errors ${q.error_estimate_caveat}.`)] : []),
      // The pilot's tails (tessera_farm::quote::Tails): rare paths make the figures a lower
      // bound ("unpredictable") or widen the intervals ("heavy"); the note says why.
      ...(q.quote.tail_note ? [h("p", { class: "hint caveat" }, q.quote.tail_note)] : []));
  }

  quoteButton.addEventListener("click", async () => {
    clearErrors();
    quoteEl.replaceChildren();
    const settings = readSettings();
    if (!settings) return;
    quoteButton.disabled = true;
    try {
      if (!(await sceneReady(settings)) || !(await environmentReady(settings))) return;
      quoteEl.replaceChildren(h("p", {}, "Rendering a short pilot…"));
      showQuote(await api.quote(settings));
    } catch (e) {
      quoteEl.replaceChildren();
      showError(e.status === 0 ? e.message : `No quote: ${e.message}`, e.field);
    } finally {
      quoteButton.disabled = false;
    }
  });

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    clearErrors();
    const settings = readSettings();
    if (!settings) return;
    submit.disabled = true;
    try {
      if (!(await sceneReady(settings)) || !(await environmentReady(settings))) return;
      const job = await api.submit(settings, key);
      key = idempotencyKey();
      location.hash = `#/jobs/${job.id}`;
    } catch (e) {
      showError(e.status === 0 ? e.message : `The job was not accepted: ${e.message}`, e.field);
    } finally {
      submit.disabled = false;
    }
  });

  async function loadBuiltins() {
    try {
      builtinsCache = builtinsCache || (await api.builtins()).builtins || [];
    } catch (e) {
      builtin.replaceChildren(h("option", { value: "" }, "(could not load the list)"));
      showError(`Could not load the built-in scenes: ${e.message}`);
      return;
    }
    const keep = builtin.value;
    builtin.replaceChildren(...builtinsCache.map((b) =>
      h("option", { value: `builtin:${b.name}`, title: b.description || null },
        b.description ? `${b.name} — ${b.description}` : b.name)));
    if (keep && builtinsCache.some((b) => `builtin:${b.name}` === keep)) builtin.value = keep;
    else if (builtinsCache.some((b) => b.name === "cornell-box")) builtin.value = "builtin:cornell-box";
  }
  loadBuiltins();

  return {
    el,
    title: "Submit a job",
    // Nothing here changes by itself: no polling.
    async refresh() {},
    polls: false,
  };
}
