// The jobs table: one page of GET /api/v1/jobs (newest first, paginated by next_cursor),
// sortable by any column within the page.

import { api } from "./api.js";
import { h, setText, duration, num, int, percent, jobLabel, sceneLabel, progress, terminal } from "./util.js";

// Kept across visits of the page, so going to a job and back keeps the place.
const state = {
  cursors: [null],
  page: 0,
  limit: 50,
  filter: "",
  sort: { key: null, dir: 1 },
  next: null,
};

const STATES = ["queued", "running", "done", "failed", "canceled"];

function stateBadge(td, job) {
  let b = td.firstChild;
  if (!b) {
    b = h("span", { class: "badge" });
    td.append(b);
  }
  b.className = `badge state-${job.state}`;
  setText(b, job.state);
  td.title = job.state === "failed" && job.error ? job.error : "";
}

function link(td, job) {
  let a = td.firstChild;
  if (!a) {
    a = h("a", { href: `#/jobs/${job.id}` });
    td.append(a, h("span", { class: "sub" }));
  }
  setText(a, jobLabel(job));
  setText(td.lastChild, job.name ? sceneLabel(job.scene) : "");
}

function progressCell(td, job) {
  let bar = td.querySelector("progress");
  if (!bar) {
    bar = h("progress", { max: 1 });
    td.append(h("span", { class: "bar-line" }, bar, h("span", { class: "sub" })));
  }
  const p = progress(job);
  bar.value = p;
  const words = `${int(job.passes_done)} of ${int(job.passes_planned)} passes`;
  bar.setAttribute("aria-label", `${Math.round(p * 100)} %, ${words}`);
  const early = job.state === "done" && job.passes_done < job.passes_planned ? " (stopped early)" : "";
  setText(td.querySelector(".sub"), `${int(job.passes_done)} / ${int(job.passes_planned)}${early}`);
}

function errorCell(td, job) {
  const target = job.target_error ? ` / ${percent(job.target_error)}` : "";
  setText(td, `${percent(job.error_estimate)}${target}`);
  const met = job.target_reached ?? (job.target_error > 0 && job.error_estimate > 0 && job.error_estimate <= job.target_error);
  td.classList.toggle("met", met);
  td.classList.toggle("missed", job.target_reached === false);
  td.title = job.stop_reason ?? "";
}

function text(f) {
  return (td, job) => setText(td, f(job));
}

const eta = (job) => (terminal(job.state) ? null : job.eta_seconds);

/** The remaining time; a job whose ETA is not predictable says so, the reason on hover. */
function etaCell(td, job) {
  const unpredictable = !terminal(job.state) && job.eta_tail_class === "unpredictable";
  setText(td, unpredictable ? "not predictable" : duration(eta(job)));
  td.title = terminal(job.state) ? "" : job.eta_note ?? "";
}

const COLUMNS = [
  { key: "id", label: "ID", num: true, value: (j) => j.id, cell: text((j) => j.id) },
  { key: "name", label: "Job", value: (j) => jobLabel(j).toLowerCase(), cell: link },
  { key: "state", label: "State", value: (j) => STATES.indexOf(j.state), cell: stateBadge },
  { key: "priority", label: "Priority", num: true, value: (j) => j.priority, cell: text((j) => j.priority) },
  {
    key: "frames", label: "Frames", num: true, value: (j) => j.frames_total,
    cell: text((j) => `${int(j.frames_done)} / ${int(j.frames_total)}`),
  },
  { key: "progress", label: "Progress", value: progress, cell: progressCell },
  { key: "spp", label: "spp", num: true, value: (j) => j.spp_so_far, cell: text((j) => num(j.spp_so_far)) },
  { key: "error", label: "Error / target", num: true, value: (j) => j.error_estimate, cell: errorCell },
  {
    key: "elapsed", label: "Elapsed", num: true, value: (j) => j.elapsed_seconds,
    cell: text((j) => duration(j.elapsed_seconds)),
  },
  { key: "eta", label: "Remaining", num: true, value: eta, cell: etaCell },
];

function compare(a, b) {
  const na = a === null || a === undefined || Number.isNaN(a);
  const nb = b === null || b === undefined || Number.isNaN(b);
  if (na || nb) return na === nb ? 0 : na ? 1 : -1; // missing values last
  return a < b ? -1 : a > b ? 1 : 0;
}

/** The jobs page. `poke()` asks for an immediate refresh. */
export function jobsView(poke) {
  const rows = new Map();
  const tbody = h("tbody");
  const headRow = h("tr");
  const heads = new Map();
  for (const c of COLUMNS) {
    const btn = h("button", { type: "button", class: "sort", onclick: () => sortBy(c.key) }, c.label);
    const th = h("th", { scope: "col", class: c.num ? "num" : null }, btn);
    heads.set(c.key, th);
    headRow.append(th);
  }
  const table = h("table", { id: "jobs-table", class: "grid" },
    h("caption", { class: "visually-hidden" }, "Jobs, newest first; select a column header to sort this page"),
    h("thead", {}, headRow), tbody);
  const empty = h("p", { class: "empty", hidden: true });
  const summary = h("p", { class: "summary" });

  const filter = h("select", { id: "jobs-filter", onchange: () => {
    state.filter = filter.value;
    reset();
  } }, h("option", { value: "" }, "all states"), STATES.map((s) => h("option", { value: s }, s)));
  filter.value = state.filter;
  const limit = h("select", { id: "jobs-limit", onchange: () => {
    state.limit = Number(limit.value);
    reset();
  } }, [25, 50, 100, 200].map((n) => h("option", { value: n }, String(n))));
  limit.value = String(state.limit);

  const first = h("button", { type: "button", onclick: () => go(0) }, "Newest");
  const prev = h("button", { type: "button", onclick: () => go(state.page - 1) }, "← Newer");
  const next = h("button", { type: "button", id: "jobs-older", onclick: () => {
    if (!state.next) return;
    state.cursors[state.page + 1] = state.next;
    go(state.page + 1);
  } }, "Older →");
  const pageLabel = h("span", { class: "page" });

  const el = h("section", { "aria-labelledby": "jobs-title" },
    h("div", { class: "section-head" },
      h("h1", { id: "jobs-title" }, "Jobs"),
      h("a", { class: "button primary", href: "#/submit" }, "Submit a job")),
    h("div", { class: "toolbar" },
      h("label", {}, "Show ", filter),
      h("label", {}, "Per page ", limit),
      h("nav", { class: "pager", "aria-label": "Pages of jobs" }, first, prev, pageLabel, next)),
    h("div", { class: "table-wrap" }, table),
    empty, summary);

  function reset() {
    state.cursors = [null];
    state.page = 0;
    state.next = null;
    poke();
  }

  function go(page) {
    state.page = Math.max(0, page);
    state.cursors.length = state.page + 1;
    poke();
  }

  function sortBy(key) {
    if (state.sort.key === key) {
      if (state.sort.dir === 1) state.sort.dir = -1;
      else state.sort = { key: null, dir: 1 };
    } else state.sort = { key, dir: 1 };
    render(lastJobs);
  }

  let lastJobs = [];

  function render(jobs) {
    lastJobs = jobs;
    const seen = new Set();
    for (const job of jobs) {
      seen.add(job.id);
      let row = rows.get(job.id);
      if (!row) {
        row = { tr: h("tr", { "data-job": job.id }), tds: COLUMNS.map((c) => h("td", { class: c.num ? "num" : null })) };
        row.tr.append(...row.tds);
        rows.set(job.id, row);
      }
      COLUMNS.forEach((c, i) => c.cell(row.tds[i], job));
      row.tr.className = `state-row-${job.state}`;
    }
    for (const [id, row] of rows) {
      if (!seen.has(id)) {
        row.tr.remove();
        rows.delete(id);
      }
    }
    let order = jobs;
    const col = COLUMNS.find((c) => c.key === state.sort.key);
    if (col) order = [...jobs].sort((a, b) => state.sort.dir * compare(col.value(a), col.value(b)) || b.id - a.id);
    // Move rows only when the order changed (moving a row drops keyboard focus in it).
    const want = order.map((j) => rows.get(j.id).tr);
    const have = Array.from(tbody.children);
    if (want.length !== have.length || want.some((tr, i) => tr !== have[i])) tbody.replaceChildren(...want);

    for (const c of COLUMNS) {
      const th = heads.get(c.key);
      th.setAttribute("aria-sort", c === col ? (state.sort.dir === 1 ? "ascending" : "descending") : "none");
    }
    empty.hidden = jobs.length > 0;
    setText(empty, state.page === 0 && !state.filter
      ? "No jobs yet. Submit one to start rendering."
      : "No jobs on this page.");
    prev.disabled = state.page === 0;
    first.disabled = state.page === 0;
    next.disabled = !state.next;
    setText(pageLabel, `page ${state.page + 1}`);
    const sorted = col ? `, sorted by ${col.label.toLowerCase()} ${state.sort.dir === 1 ? "ascending" : "descending"} within the page` : "";
    const running = jobs.filter((j) => j.state === "running").length;
    setText(summary, `${jobs.length} job${jobs.length === 1 ? "" : "s"} on this page, ${running} running${sorted}.`);
  }

  return {
    el,
    title: "Jobs",
    async refresh(signal) {
      const page = await api.jobs({ limit: state.limit, cursor: state.cursors[state.page], state: state.filter }, signal);
      state.next = page.next_cursor || null;
      render(page.jobs || []);
    },
  };
}
