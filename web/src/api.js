// The API as the page uses it: same origin, JSON in and out, every error an RFC 9457 problem
// (`detail`, `code`, and `field` for a bad parameter) carried by ApiError as the API words it.

export class ApiError extends Error {
  constructor(problem, status) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.problem = problem;
    this.status = status;
  }
}

export async function api(path, init = {}) {
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
    throw new ApiError(problem || { detail: `${res.status} ${res.statusText}`, code: 'http' }, res.status);
  }
  return res;
}

export const json = async (path, init) => (await api(path, init)).json();
export const bytes = async (path) => (await api(path)).arrayBuffer();
