// The API as the page uses it: same origin, JSON in and out, every error an RFC 9457 problem
// (`detail`, `code`, and `field` for a bad parameter) carried by ApiError as the API words it.
//
// Credentials: the API key (or token) the user typed is kept in sessionStorage for this tab
// only (never localStorage, never a URL) and sent as `Authorization: Bearer` on every call.
// Without one the calls go exactly as before (a server with `--auth none` needs none).

const KEY_ITEM = 'willow.apiKey';

export function apiKey() {
  try { return sessionStorage.getItem(KEY_ITEM) || ''; } catch { return ''; }
}

/** Store the key for this tab ('' clears it). */
export function setApiKey(key) {
  try {
    if (key) sessionStorage.setItem(KEY_ITEM, key); else sessionStorage.removeItem(KEY_ITEM);
  } catch { /* storage disabled: the key lasts as long as nothing */ }
}

let unauthorized = () => {};
/** `fn(apiError)` is called on every 401, before the error is thrown to the caller. */
export function onUnauthorized(fn) { unauthorized = fn; }

export class ApiError extends Error {
  constructor(problem, status) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.problem = problem;
    this.status = status;
  }
}

/** A 401 in the page's words: it asks for a key (the server's own detail is for API clients). */
function unauthenticated(problem, hadKey) {
  const reason = problem?.reason ? ` (${problem.reason})` : '';
  const detail = hadKey
    ? `the API key was refused${reason}: enter a valid key in the “API key” field`
    : 'this server needs an API key: enter it in the “API key” field';
  return { ...(problem || {}), detail, code: 'unauthenticated', server_detail: problem?.detail };
}

export async function api(path, init = {}) {
  const key = apiKey();
  if (key) {
    const headers = new Headers(init.headers || {});
    headers.set('Authorization', `Bearer ${key}`);
    init = { ...init, headers };
  }
  let res;
  try {
    res = await fetch(path, init);
  } catch (e) {
    throw new ApiError({ detail: `the server cannot be reached (${e.message})`, code: 'network' }, 0);
  }
  if (!res.ok) {
    let problem;
    const type = res.headers.get('content-type') || '';
    if (type.includes('json')) {
      try { problem = await res.json(); } catch { problem = null; }
    }
    if (res.status === 401) {
      const err = new ApiError(unauthenticated(problem, !!key), 401);
      unauthorized(err);
      throw err;
    }
    throw new ApiError(problem || { detail: `${res.status} ${res.statusText}`, code: 'http' }, res.status);
  }
  return res;
}

export const json = async (path, init) => (await api(path, init)).json();
export const bytes = async (path) => (await api(path)).arrayBuffer();
