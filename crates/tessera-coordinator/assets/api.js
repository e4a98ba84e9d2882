// The coordinator's HTTP API v1, as the dashboard uses it.
//
// Every request goes to the page's own origin. When the coordinator answers 401 the user
// is asked for the API token (once, however many requests were waiting); the token is
// kept in sessionStorage and sent as `Authorization: Bearer TOKEN` on every request,
// images included (they are fetched as blobs, never by URL).

const TOKEN_KEY = "tessera.api-token";

/** An error from the API, or from reaching it, in words a person can act on. */
export class ApiError extends Error {
  constructor(status, code, message, field) {
    super(message);
    this.name = "ApiError";
    /** HTTP status; 0 when the coordinator could not be reached. */
    this.status = status;
    /** The API's error code, e.g. "invalid_field". */
    this.code = code;
    /** The request field the error is about, if any. */
    this.field = field ?? null;
  }
}

/** The stored token, or null. */
export function token() {
  try {
    return sessionStorage.getItem(TOKEN_KEY);
  } catch {
    return null;
  }
}

function setToken(value) {
  try {
    if (value) sessionStorage.setItem(TOKEN_KEY, value);
    else sessionStorage.removeItem(TOKEN_KEY);
  } catch {
    // Storage disabled: the token lasts until the page is reloaded.
  }
  memoryToken = value || null;
}

let memoryToken = null;
let askHandler = null;
let pendingAsk = null;
let declined = false;

/**
 * Sets the function that asks the user for a token: `async (reason) => token | null`.
 */
export function onTokenNeeded(handler) {
  askHandler = handler;
}

/** Whether the token prompt is open (polling waits for it). */
export function askingForToken() {
  return pendingAsk !== null;
}

async function askToken(reason) {
  if (!askHandler || declined) return null;
  if (!pendingAsk) {
    pendingAsk = askHandler(reason).then((t) => {
      // Asked once and refused: do not ask again on every poll, wait for the user.
      declined = !t;
      return t;
    }).finally(() => {
      pendingAsk = null;
    });
  }
  return pendingAsk;
}

/** Asks for a (new) token now, e.g. from a button; resolves to whether one was given. */
export async function changeToken() {
  declined = false;
  const t = await askToken(token() ? "Replace the API token of this tab." : "Enter the coordinator's API token.");
  if (t) setToken(t);
  return Boolean(t);
}

function describeNetworkError(e) {
  if (e && e.name === "AbortError") return e;
  return new ApiError(0, "unreachable", `cannot reach the coordinator (${e.message || e})`);
}

async function errorFrom(res) {
  let code = `http_${res.status}`;
  let message = `${res.status} ${res.statusText || "error"}`;
  let field = null;
  try {
    const body = await res.json();
    if (body && body.error) {
      code = body.error.code || code;
      message = body.error.message || message;
      field = body.error.field || null;
    }
  } catch {
    // Not JSON (a proxy's error page): keep the status line.
  }
  return new ApiError(res.status, code, message, field);
}

/**
 * Sends a request to `path` (e.g. "/api/v1/jobs") and returns the parsed JSON, a Blob
 * (`as: "blob"`) or the text (`as: "text"`). Throws ApiError.
 *
 * Options: method, json (a body to send as JSON), body (raw body), headers, signal, as.
 */
export async function request(path, options = {}) {
  const { method = "GET", json, body, headers = {}, signal, as = "json" } = options;
  for (let attempt = 0; ; attempt++) {
    const h = new Headers(headers);
    const t = memoryToken || token();
    if (t) h.set("Authorization", `Bearer ${t}`);
    let payload = body;
    if (json !== undefined) {
      h.set("Content-Type", "application/json");
      payload = JSON.stringify(json);
    }
    let res;
    try {
      res = await fetch(path, { method, headers: h, body: payload, signal, cache: "no-store" });
    } catch (e) {
      throw describeNetworkError(e);
    }
    if (res.status === 401 && attempt < 5) {
      const err = await errorFrom(res);
      const reason = t ? `The token was refused: ${err.message}` : "This coordinator asks for an API token.";
      const given = await askToken(reason);
      if (!given) {
        throw new ApiError(401, err.code, `${err.message}: this coordinator needs an API token (use "API token" at the top right)`, null);
      }
      setToken(given);
      continue;
    }
    if (!res.ok) throw await errorFrom(res);
    if (as === "blob") return res.blob();
    if (as === "text") return res.text();
    if (res.status === 204) return null;
    return res.json();
  }
}

/** A random idempotency key (works outside secure contexts too). */
export function idempotencyKey() {
  const bytes = new Uint8Array(16);
  crypto.getRandomValues(bytes);
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

/** Query string from an object, skipping null/undefined/"" values. */
export function query(params) {
  const q = new URLSearchParams();
  for (const [k, v] of Object.entries(params)) {
    if (v !== null && v !== undefined && v !== "") q.set(k, String(v));
  }
  const s = q.toString();
  return s ? `?${s}` : "";
}

const enc = encodeURIComponent;

/** The endpoints. */
export const api = {
  jobs: (params, signal) => request(`/api/v1/jobs${query(params)}`, { signal }),
  job: (id, signal) => request(`/api/v1/jobs/${enc(id)}`, { signal }),
  history: (id, signal) => request(`/api/v1/jobs/${enc(id)}/history`, { signal }),
  tiles: (id, frame, signal) => request(`/api/v1/jobs/${enc(id)}/tiles${query({ frame })}`, { signal }),
  image: (id, format, frame, signal) =>
    request(`/api/v1/jobs/${enc(id)}/image${query({ format, frame })}`, { signal, as: "blob" }),
  cancel: (id) => request(`/api/v1/jobs/${enc(id)}`, { method: "DELETE" }),
  submit: (settings, key) =>
    request("/api/v1/jobs", { method: "POST", json: settings, headers: { "idempotency-key": key } }),
  // A dry run: the job's quote from a short pilot; nothing is queued.
  quote: (settings) => request("/api/v1/jobs?dry_run=true", { method: "POST", json: settings }),
  uploadScene: (bytes, contentType) =>
    request("/api/v1/scenes", {
      method: "POST",
      body: bytes,
      headers: { "Content-Type": contentType || "application/octet-stream" },
    }),
  builtins: () => request("/api/v1/builtins"),
  workers: (signal) => request("/api/v1/workers", { signal }),
};
