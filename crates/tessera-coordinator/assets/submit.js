// The submit form: a built-in scene (GET /api/v1/builtins) or an uploaded .gltf/.glb
// (POST /api/v1/scenes, then the job names the returned hash), and the job settings
// (POST /api/v1/jobs with an idempotency key, so a double click submits once).

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
  const submit = h("button", { type: "submit", id: "f-submit", class: "primary" }, "Submit job");
  const status = h("div", { id: "submit-status", class: "form-status", role: "alert", "aria-live": "assertive" });

  const builtinRow = row("Built-in scene", builtin);
  const uploadRow = row("glTF file", file, "A .glb, or a .gltf with its buffers and images embedded.");
  uploadRow.hidden = true;

  const fields = {
    scene: builtin, width, height, spp, target_error: target, adaptive, priority,
    time_limit_seconds: timeLimit, name, frames: frameEnd, fps, animation, shutter: shutterOpen,
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
    h("fieldset", {}, h("legend", {}, "Scheduling"),
      row("Priority", priority, "Higher runs first."),
      row("Name", name)),
    h("div", { class: "actions" }, submit),
    status);

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
    for (const input of [...Object.values(fields), file, frameStart, shutterClose]) input.removeAttribute("aria-invalid");
    status.replaceChildren();
    status.className = "form-status";
  }

  function showError(message, fieldName) {
    status.className = "form-status error";
    status.replaceChildren(h("p", {}, message));
    const input = fieldName === "scene" && srcUpload.checked ? file : fields[fieldName?.split(".")[0]];
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

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    clearErrors();
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
    } catch (e) {
      showError(e.message, e.field);
      return;
    }
    for (const k of Object.keys(settings)) if (settings[k] === null) delete settings[k];

    submit.disabled = true;
    try {
      if (srcUpload.checked) {
        const f = file.files && file.files[0];
        if (!f) {
          showError("Choose a .gltf or .glb file to upload.", "scene");
          return;
        }
        status.className = "form-status";
        status.replaceChildren(h("p", {}, `Uploading ${f.name} (${int(f.size)} bytes)…`));
        const type = f.name.toLowerCase().endsWith(".glb") ? "model/gltf-binary" : "model/gltf+json";
        let up;
        try {
          up = await api.uploadScene(await f.arrayBuffer(), type);
        } catch (e) {
          showError(`The scene was not accepted: ${e.message}`, "scene");
          return;
        }
        status.replaceChildren(h("p", {},
          `Uploaded: ${int(up.triangles)} triangles, ${up.meshes} meshes, ${up.materials} materials, ${up.lights} lights.`));
        settings.scene = up.hash;
      } else if (!settings.scene) {
        showError("Choose a built-in scene.", "scene");
        return;
      }
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
