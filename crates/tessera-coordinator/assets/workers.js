// The workers table: GET /api/v1/workers.

import { api } from "./api.js";
import { h, setText, num, int, ago, clock } from "./util.js";

const COLUMNS = [
  ["Name", (w) => w.name],
  ["ID", (w) => w.id, true],
  ["State", null],
  ["Threads", (w) => w.threads, true],
  ["Last heartbeat", null],
  ["Units done", (w) => int(w.units_done), true],
  ["Paths / s", (w) => num(w.paths_per_second), true],
  ["Faults", (w) => int(w.faults), true],
  ["Version", (w) => w.version || "—"],
];

/** The workers page. */
export function workersView() {
  const tbody = h("tbody");
  const table = h("table", { id: "workers-table", class: "grid" },
    h("caption", { class: "visually-hidden" }, "Workers registered with the coordinator"),
    h("thead", {}, h("tr", {}, COLUMNS.map(([label, , n]) => h("th", { scope: "col", class: n ? "num" : null }, label)))),
    tbody);
  const summary = h("p", { class: "summary" });
  const empty = h("p", { class: "empty", hidden: true }, "No worker has registered. Start one with `tessera worker --coordinator URL`.");
  const el = h("section", { "aria-labelledby": "workers-title" },
    h("h1", { id: "workers-title" }, "Workers"), summary, h("div", { class: "table-wrap" }, table), empty);

  const rows = new Map();

  function render(workers) {
    const now = Date.now();
    const seen = new Set();
    const order = [];
    for (const w of workers) {
      seen.add(w.id);
      let row = rows.get(w.id);
      if (!row) {
        const tds = COLUMNS.map(([, , n]) => h("td", { class: n ? "num" : null }));
        row = { tr: h("tr", { "data-worker": w.id }, tds), tds };
        rows.set(w.id, row);
      }
      COLUMNS.forEach(([, f], i) => {
        const td = row.tds[i];
        if (f) setText(td, f(w));
      });
      let badge = row.tds[2].firstChild;
      if (!badge) {
        badge = h("span");
        row.tds[2].append(badge);
      }
      // A quarantined worker (a spot check found it faulty) shows that instead of its
      // state, with the reason on hover: it gets no work whatever its state.
      const shown = w.quarantined ? "quarantined" : w.state;
      badge.className = `badge worker-${shown}`;
      badge.title = w.quarantined ? (w.quarantine_reason || "quarantined") : "";
      setText(badge, shown);
      setText(row.tds[4], ago(w.last_heartbeat_unix_ms, now));
      row.tds[4].title = clock(w.last_heartbeat_unix_ms);
      row.tr.className = `worker-row-${shown}`;
      order.push(row.tr);
    }
    for (const [id, row] of rows) if (!seen.has(id)) rows.delete(id);
    const have = Array.from(tbody.children);
    if (order.length !== have.length || order.some((tr, i) => tr !== have[i])) tbody.replaceChildren(...order);
    empty.hidden = workers.length > 0;
    const live = workers.filter((w) => w.state !== "lost");
    const busy = workers.filter((w) => w.state === "busy").length;
    const quarantined = workers.filter((w) => w.quarantined).length;
    const threads = live.reduce((a, w) => a + w.threads, 0);
    const pps = live.reduce((a, w) => a + (w.paths_per_second || 0), 0);
    setText(summary, `${workers.length} worker${workers.length === 1 ? "" : "s"}: ${busy} busy, ${live.length - busy} idle or draining, ${workers.length - live.length} lost${quarantined ? `, ${quarantined} quarantined` : ""}; ${int(threads)} threads, ${num(pps)} paths per second in all.`);
  }

  return {
    el,
    title: "Workers",
    async refresh(signal) {
      const list = await api.workers(signal);
      render(list.workers || []);
    },
  };
}
