// The gateway's REST API (docs/api.md): fetch with the API key, errors as the problem+json's
// person-readable message, uploads with progress, and job progress as server-sent events.
export const API = '/api/v1';
const KEY_STORAGE = 'volumesh.apiKey';
const TERMINAL = new Set(['succeeded', 'failed', 'cancelled']);

export class ApiError extends Error {
  constructor(status, message, problem = null) {
    super(message);
    this.status = status;
    this.problem = problem;
  }
}

export function apiKey() {
  try {
    return localStorage.getItem(KEY_STORAGE) || '';
  } catch {
    return '';
  }
}

export function setApiKey(key) {
  try {
    if (key) localStorage.setItem(KEY_STORAGE, key);
    else localStorage.removeItem(KEY_STORAGE);
  } catch { /* private mode: the key lives for this page only */ }
}

function authHeaders(extra = {}) {
  const key = apiKey();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : extra;
}

// The message a person can act on: problem+json's detail, else its title, else the status.
function messageOf(status, text) {
  let problem = null;
  try {
    problem = JSON.parse(text);
  } catch { /* not JSON */ }
  const detail = problem && (problem.detail || problem.title);
  const message = typeof detail === 'string' && detail ? detail : `HTTP ${status}${text ? `: ${text.slice(0, 200)}` : ''}`;
  const hint = status === 401 || status === 403 ? ' (enter an API key under "API key")' : '';
  return new ApiError(status, message + hint, problem);
}

export async function errorFrom(response) {
  return messageOf(response.status, await response.text().catch(() => ''));
}

/** fetch() against the API; JSON in/out; throws ApiError with the problem's message. */
export async function apiFetch(path, { method = 'GET', json, signal, raw = false } = {}) {
  const headers = authHeaders(json === undefined ? {} : { 'Content-Type': 'application/json' });
  let response;
  try {
    response = await fetch(path.startsWith('/') ? path : `${API}/${path}`, {
      method, headers, signal, body: json === undefined ? undefined : JSON.stringify(json),
    });
  } catch (err) {
    throw new ApiError(0, `the gateway cannot be reached (${err.message})`);
  }
  if (!response.ok) throw await errorFrom(response);
  if (raw) return response;
  return response.status === 204 ? null : response.json();
}

/**
 * Bytes of a URL (same origin gets the API key), as an ArrayBuffer. `started` is a fetch()
 * promise for that URL begun earlier (index.html starts the asset's mesh before any module).
 */
export async function fetchBytes(url, started = null) {
  const sameOrigin = new URL(url, location.href).origin === location.origin;
  let response;
  try {
    response = await (started || fetch(url, { headers: sameOrigin ? authHeaders() : {} }));
  } catch (err) {
    throw new ApiError(0, `cannot fetch ${url} (${err.message})`);
  }
  if (!response.ok) throw await errorFrom(response);
  return response.arrayBuffer();
}

/** POSTs a file with upload progress (XMLHttpRequest: fetch has no upload progress). */
export function uploadFile(path, file, { onProgress = () => {}, contentType = 'application/zip' } = {}) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('POST', `${API}/${path}`);
    for (const [name, value] of Object.entries(authHeaders({ 'Content-Type': contentType }))) {
      xhr.setRequestHeader(name, value);
    }
    xhr.upload.onprogress = (event) => {
      if (event.lengthComputable) onProgress(event.loaded / event.total);
    };
    xhr.onload = () => {
      if (xhr.status >= 200 && xhr.status < 300) {
        try {
          resolve(JSON.parse(xhr.responseText));
        } catch {
          reject(new ApiError(xhr.status, 'the gateway answered the upload with something that is not JSON'));
        }
      } else {
        reject(messageOf(xhr.status, xhr.responseText));
      }
    };
    xhr.onerror = () => reject(new ApiError(0, 'the upload was interrupted: the gateway cannot be reached'));
    xhr.send(file);
  });
}

/**
 * Yields the job object each time it changes until a terminal state, from
 * GET /jobs/{id}/events (server-sent events). Read with fetch rather than EventSource, which
 * cannot send the Authorization header; falls back to polling GET /jobs/{id} if the stream
 * cannot be had.
 */
export async function* jobUpdates(jobId, { signal } = {}) {
  let last = null;
  try {
    for await (const job of sseJson(`${API}/jobs/${encodeURIComponent(jobId)}/events`, signal)) {
      last = job;
      yield job;
      if (TERMINAL.has(job.state)) return;
    }
  } catch (err) {
    if (err instanceof ApiError && err.status >= 400 && err.status < 500 && err.status !== 404) throw err;
  }
  while (!last || !TERMINAL.has(last.state)) { // the stream ended early or is not served
    await new Promise((resolve) => setTimeout(resolve, 1000));
    last = await apiFetch(`jobs/${encodeURIComponent(jobId)}`, { signal });
    yield last;
  }
}

async function* sseJson(url, signal) {
  const response = await fetch(url, { headers: authHeaders({ Accept: 'text/event-stream' }), signal });
  if (!response.ok) throw await errorFrom(response);
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value.replace(/\r\n?/g, '\n');
    let end;
    while ((end = buffer.indexOf('\n\n')) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      const data = block.split('\n').filter((l) => l.startsWith('data:')).map((l) => l.slice(5).trimStart());
      if (data.length === 0) continue; // comments and keep-alives
      try {
        yield JSON.parse(data.join('\n'));
      } catch { /* an event that is not a job object */ }
    }
  }
}

/** A job's error as a sentence (the field may be a string or a problem object). */
export function jobErrorMessage(job) {
  const error = job.error;
  if (!error) return `the job ${job.state}`;
  if (typeof error === 'string') return error;
  return error.detail || error.title || error.message || JSON.stringify(error);
}

/** The key's recent jobs, newest first. */
export async function recentJobs(limit = 10) {
  return (await apiFetch(`jobs?limit=${limit}`)).items;
}
