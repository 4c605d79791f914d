// Calls to the service's /v1 API, as any client makes them: JSON bodies, the X-API-Key header
// when the user entered a key, and RFC 9457 problem details turned into readable errors.

const KEY_STORE = "gpnarx.apiKey";
export const API_KEY_HEADER = "X-API-Key";

export const root = (document.querySelector('meta[name="gpnarx-root"]')?.content || "").replace(/\/$/, "");

export function apiKey() {
  return sessionStorage.getItem(KEY_STORE) || "";
}

export function setApiKey(key) {
  if (key) sessionStorage.setItem(KEY_STORE, key);
  else sessionStorage.removeItem(KEY_STORE);
}

export class ApiError extends Error {
  constructor(status, problem, url) {
    const p = problem || {};
    const field = p.field ? ` (field ${p.field})` : "";
    super(`${status} ${p.title || "Error"}: ${p.detail || "no detail"}${field}`);
    this.status = status;
    this.problem = p;
    this.url = url;
  }
}

async function request(path, init = {}) {
  const headers = new Headers(init.headers || {});
  const key = apiKey();
  if (key && path.startsWith("/v1")) headers.set(API_KEY_HEADER, key);
  const url = root + path;
  const resp = await fetch(url, { ...init, headers });
  if (!resp.ok) {
    let problem = null;
    try { problem = await resp.json(); } catch (_) { /* not JSON */ }
    throw new ApiError(resp.status, problem, url);
  }
  return resp;
}

export async function getJSON(path) {
  return (await request(path)).json();
}

export async function postJSON(path, body) {
  const resp = await request(path, {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  });
  return resp.json();
}

export async function getText(path) {
  return (await request(path)).text();
}

/** POST /v1/records/parse with one record file or an LMS export's two files. */
export async function parseRecord(files, fs) {
  const form = new FormData();
  for (const f of files) form.append("files", f, f.webkitRelativePath || f.name);
  if (fs) form.append("fs", String(fs));
  return (await request("/v1/records/parse", { method: "POST", body: form })).json();
}

/** A static file of the service (no API key: /static is open). */
export async function staticBlob(path) {
  const resp = await fetch(root + path);
  if (!resp.ok) throw new Error(`${resp.status} loading ${path}`);
  return resp.blob();
}

export const enc = encodeURIComponent;
