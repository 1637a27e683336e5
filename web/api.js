// The API helper: fetch with the API key (asked for once on a 401, kept
// for this browser tab), JSON in and out, errors as ApiError, and a job's
// Server-Sent Events. Every other module talks to the server through it.

const KEY = 'radiance-api-key';

export class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

let keyPrompt = null;
/** Asks for the API key once (one dialog however many requests wait). */
export function askKey() {
  if (!keyPrompt) {
    keyPrompt = new Promise((resolve) => {
      const dialog = document.getElementById('key-dialog');
      const input = document.getElementById('key-input');
      document.getElementById('key-form').onsubmit = () => {
        sessionStorage.setItem(KEY, input.value.trim());
        keyPrompt = null;
        resolve();
      };
      dialog.showModal();
      input.focus();
    });
  }
  return keyPrompt;
}

/** `headers` with the API key's Authorization header when there is a key. */
export function authHeaders(headers = {}) {
  const h = new Headers(headers);
  const key = sessionStorage.getItem(KEY);
  if (key) h.set('Authorization', 'Bearer ' + key);
  return h;
}

async function errorOf(res) {
  try {
    const body = await res.json();
    return new ApiError(res.status, body.error.message);
  } catch {
    return new ApiError(res.status, `${res.status} ${res.statusText}`);
  }
}

/** fetch with the key; asks for it on 401; throws ApiError on errors. */
export async function api(path, opts = {}) {
  for (;;) {
    const res = await fetch(path, { ...opts, headers: authHeaders(opts.headers) });
    if (res.status === 401) { await askKey(); continue; }
    if (!res.ok) throw await errorOf(res);
    return res;
  }
}

export const getJson = async (path) => (await api(path)).json();
export const postJson = async (path, body) =>
  (await api(path, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) })).json();

/** Follows a job's event stream, calling onJob with each record. */
export async function followJob(id, onJob, signal) {
  const res = await api(`/v1/jobs/${id}/events`, { signal });
  const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let end;
    while ((end = buffer.indexOf('\n\n')) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      const data = block.split('\n').filter((l) => l.startsWith('data:')).map((l) => l.slice(5).trimStart()).join('\n');
      if (data) onJob(JSON.parse(data));
    }
  }
}
