// The viewer's only way to the service: same-origin fetches that carry the API key the user typed
// (kept in sessionStorage: gone when the tab closes).

const KEY = "cortexloc.apiKey";

export function apiKey() { return sessionStorage.getItem(KEY) || ""; }
export function setApiKey(value) {
  if (value) sessionStorage.setItem(KEY, value); else sessionStorage.removeItem(KEY);
}

function headers() {
  const key = apiKey();
  return key ? { "X-API-Key": key } : {};
}

export class HttpError extends Error {
  constructor(status, problem) {
    super(problem && problem.detail ? problem.detail : `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
  }
}

/** GET a JSON resource of the API; an error reply becomes an HttpError with its problem body. */
export async function getJson(path) {
  const r = await fetch(path, { headers: headers(), cache: "no-store" });
  if (!r.ok) {
    let problem = null;
    try { problem = await r.json(); } catch { /* not JSON */ }
    throw new HttpError(r.status, problem);
  }
  return r.json();
}

/** A file of the API as a Blob (a download cannot send the key), or null if there is none. */
export async function getBlob(path) {
  const r = await fetch(path, { headers: headers(), cache: "no-store" });
  return r.ok ? r.blob() : null;
}

/** An image of the API as an object URL (an <img src> cannot send the key), or null if there is none. */
export async function getImageUrl(path) {
  const r = await fetch(path, { headers: headers() });
  if (!r.ok) return null;
  return URL.createObjectURL(await r.blob());
}
