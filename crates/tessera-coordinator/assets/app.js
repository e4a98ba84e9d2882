// The Tessera dashboard: hash routing between the pages and one polling loop.
//
// Routes: #/jobs (the jobs table), #/jobs/ID (a job), #/submit, #/workers.
// Only the page being shown is refreshed, about once a second, and not at all while the
// tab is hidden. Everything goes through the public HTTP API v1 (api.js).

import { onTokenNeeded, changeToken } from "./api.js";
import { jobsView } from "./jobs.js";
import { jobView } from "./job.js";
import { submitView } from "./submit.js";
import { workersView } from "./workers.js";

const POLL_MS = 1000;

const main = document.getElementById("main");
const live = document.getElementById("live");
const banner = document.getElementById("banner");

let current = null;
let timer = null;
let busy = false;
let controller = null;
let failures = 0;

function parseRoute(hash) {
  const m = /^#\/([a-z]+)(?:\/([^/?#]+))?/.exec(hash || "");
  if (!m) return { page: "jobs" };
  if (m[1] === "jobs" && m[2]) return { page: "job", id: decodeURIComponent(m[2]) };
  if (["jobs", "submit", "workers"].includes(m[1])) return { page: m[1] };
  return { page: "jobs" };
}

function poke() {
  schedule(0);
}

function route() {
  const r = parseRoute(location.hash);
  if (controller) controller.abort();
  if (current && current.destroy) current.destroy();
  switch (r.page) {
    case "job":
      current = jobView(r.id, poke);
      break;
    case "submit":
      current = submitView(poke);
      break;
    case "workers":
      current = workersView(poke);
      break;
    default:
      current = jobsView(poke);
  }
  main.replaceChildren(current.el);
  document.title = `${current.title} · Tessera`;
  document.body.dataset.page = r.page;
  for (const a of document.querySelectorAll("[data-nav]")) {
    const on = a.dataset.nav === r.page || (r.page === "job" && a.dataset.nav === "jobs");
    if (on) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  hideBanner();
  failures = 0;
  if (current.polls === false) setLive("");
  schedule(0);
}

function setLive(text) {
  if (live.textContent !== text) live.textContent = text;
}

function showBanner(err) {
  const msg = err.status === 0 ? `${err.message}; retrying…` : err.message;
  banner.textContent = msg;
  banner.hidden = false;
}

function hideBanner() {
  banner.hidden = true;
  banner.textContent = "";
}

function schedule(ms) {
  clearTimeout(timer);
  timer = setTimeout(tick, ms);
}

async function tick() {
  timer = null;
  if (busy || document.hidden || !current) return;
  const view = current;
  const c = new AbortController();
  controller = c;
  busy = true;
  let ok = false;
  try {
    await view.refresh(c.signal);
    ok = true;
    if (view === current) {
      failures = 0;
      hideBanner();
      if (view.polls !== false) setLive(`live · updated ${new Date().toLocaleTimeString()}`);
    }
  } catch (e) {
    if (e.name !== "AbortError" && view === current) {
      failures++;
      showBanner(e);
      setLive("not updating: see the message above");
    }
  } finally {
    busy = false;
    if (!document.hidden) {
      if (view !== current) schedule(0);
      else if (view.polls !== false) {
        // Back off gently while the coordinator is unreachable or refusing.
        schedule(ok ? POLL_MS : Math.min(10_000, POLL_MS * 2 ** Math.min(failures, 4)));
      }
    }
  }
}

document.addEventListener("visibilitychange", () => {
  if (document.hidden) {
    clearTimeout(timer);
    setLive("paused while the tab is hidden");
  } else {
    schedule(0);
  }
});

window.addEventListener("hashchange", route);

// The token prompt, shown when the API answers 401.
const dialog = document.getElementById("token-dialog");
const tokenInput = document.getElementById("token-input");
const tokenReason = document.getElementById("token-reason");
onTokenNeeded(
  (reason) =>
    new Promise((resolve) => {
      tokenReason.textContent = reason;
      tokenInput.value = "";
      dialog.returnValue = "";
      dialog.addEventListener(
        "close",
        () => resolve(dialog.returnValue === "ok" ? tokenInput.value.trim() || null : null),
        { once: true },
      );
      dialog.showModal();
      tokenInput.focus();
    }),
);

document.getElementById("token-button").addEventListener("click", async () => {
  if (await changeToken()) poke();
});

route();
