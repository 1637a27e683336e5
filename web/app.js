// radiance web app: plain JavaScript, no framework, no build step. It uses
// the service's REST API like any client: scenes, jobs (followed over their
// Server-Sent Events), renders and videos. Images and videos are fetched
// with the API key (when the server has one) and shown from object URLs.
'use strict';

const $ = (id) => document.getElementById(id);
const KEY = 'radiance-api-key';

// ---------------------------------------------------------------- API ----

class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

let keyPrompt = null;
/** Asks for the API key once (one dialog however many requests wait). */
function askKey() {
  if (!keyPrompt) {
    keyPrompt = new Promise((resolve) => {
      const dialog = $('key-dialog');
      $('key-form').onsubmit = () => {
        sessionStorage.setItem(KEY, $('key-input').value.trim());
        keyPrompt = null;
        resolve();
      };
      dialog.showModal();
      $('key-input').focus();
    });
  }
  return keyPrompt;
}

function authHeaders(headers = {}) {
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
async function api(path, opts = {}) {
  for (;;) {
    const res = await fetch(path, { ...opts, headers: authHeaders(opts.headers) });
    if (res.status === 401) { await askKey(); continue; }
    if (!res.ok) throw await errorOf(res);
    return res;
  }
}

const getJson = async (path) => (await api(path)).json();
const postJson = async (path, body) =>
  (await api(path, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) })).json();

/** Follows a job's event stream, calling onJob with each record. */
async function followJob(id, onJob, signal) {
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

function status(message, isError = false) {
  const s = $('status');
  s.textContent = message;
  s.classList.toggle('error', isError);
}

function fail(e) {
  if (e && e.name === 'AbortError') return;
  status(e instanceof ApiError ? e.message : String(e), true);
}

const fmtSecs = (s) => (s == null || !isFinite(s) ? '?' : s < 60 ? `${s.toFixed(0)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`);
const fmtBytes = (b) => (b > 1 << 20 ? `${(b / 1048576).toFixed(1)} MiB` : `${Math.ceil(b / 1024)} KiB`);

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null) e.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

// --------------------------------------------------------------- tabs ----

const TABS = ['scenes', 'training', 'viewer', 'videos'];
function showTab(name) {
  for (const t of TABS) {
    $(t).hidden = t !== name;
    $('tab-' + t).setAttribute('aria-selected', String(t === name));
  }
  if (name === 'scenes') refreshScenes().catch(fail);
  if (name === 'training') refreshJobs().catch(fail);
  if (name === 'viewer' || name === 'videos') refreshModels().catch(fail);
  if (name === 'videos') refreshVideos().catch(fail);
}

// ------------------------------------------------------------- scenes ----

let scenes = [];

async function refreshScenes() {
  scenes = await getJson('/v1/scenes');
  let jobs = [];
  try { jobs = await getJson('/v1/jobs'); } catch (e) { fail(e); }
  const list = $('scene-list');
  list.replaceChildren(...scenes.slice().reverse().map((s) => sceneCard(s, jobs)));
  $('demo-offer').hidden = scenes.length > 0;
  // A scene whose poses are being estimated is shown again every 2 s.
  clearTimeout(refreshScenes.timer);
  if (scenes.some((s) => s.status === 'posing')) refreshScenes.timer = setTimeout(() => refreshScenes().catch(fail), 2000);
  const select = $('train-scene');
  const chosen = select.value;
  select.replaceChildren(...scenes.slice().reverse().filter((s) => (s.status || 'ready') === 'ready').map((s) =>
    el('option', { value: s.id }, `${s.id} (${s.format}, ${s.images.train} views, ${s.resolution.join('x')})`)));
  if (chosen) select.value = chosen;
}

function sceneCard(s, jobs) {
  const warnings = s.warnings.length
    ? el('ul', { class: 'warn', 'aria-label': 'Warnings' }, ...s.warnings.map((w) => el('li', {}, w)))
    : null;
  // Photo-only uploads: the pose estimation (COLMAP) and what it found.
  const state = s.status || 'ready';
  const posing = [];
  if (state === 'posing') {
    const job = jobs.find((j) => s.poses && j.id === s.poses.job_id);
    const what = s.poses && s.poses.source === 'video' ? 'a video' : `${s.poses ? s.poses.photos : '?'} photos`;
    const p = job && job.progress;
    posing.push(el('p', { class: 'meta', role: 'status', 'data-posing': s.id },
      `estimating the camera poses of ${what} with COLMAP` +
      (job ? ` · ${job.status}` : '') + (p && p.stage ? ` · ${p.stage}` : '') +
      (p && p.total_steps ? ` · ${Math.round((100 * p.step) / p.total_steps)}%` : '') +
      (p && p.eta ? ` · about ${fmtSecs(p.eta)} left` : '')));
  } else if (state === 'failed') {
    posing.push(el('p', { class: 'warn', role: 'alert' }, s.error || 'pose estimation failed'));
  } else if (s.poses && s.poses.report) {
    const r = s.poses.report;
    const err = r.mean_reprojection_error_px == null ? '' : ` · mean reprojection error ${r.mean_reprojection_error_px.toFixed(2)} px`;
    posing.push(el('p', { class: 'meta' }, `poses estimated: ${r.registered} of ${r.images} ` +
      `${r.source === 'video' ? 'frames' : 'photos'} registered · ${r.points} points${err} · ${Math.round(r.seconds.total)} s`));
  }
  return el('li', { 'data-scene': s.id, 'data-status': state },
    el('strong', {}, s.id),
    el('div', { class: 'meta' }, state === 'ready'
      ? `format ${s.format} · ${s.images.train} training, ${s.images.val} validation, ` +
        `${s.images.test} test images · ${s.resolution[0]}x${s.resolution[1]} · ${fmtBytes(s.size_bytes || 0)}`
      : `photos without poses · ${s.resolution[0]}x${s.resolution[1]} as uploaded · ${fmtBytes(s.size_bytes || 0)}`),
    warnings, ...posing,
    el('p', {},
      el('button', { type: 'button', disabled: state === 'ready' ? undefined : '', onclick: () => { showTab('training'); $('train-scene').value = s.id; $('train-budget').focus(); } }, 'Train a model'),
      ' ',
      el('button', { type: 'button', onclick: () => deleteScene(s.id) }, 'Delete')));
}

async function deleteScene(id) {
  if (!confirm(`Delete scene ${id}? Models trained on it stay.`)) return;
  try {
    await api(`/v1/scenes/${id}`, { method: 'DELETE' });
    status(`deleted ${id}`);
    await refreshScenes();
  } catch (e) { fail(e); }
}

const ARCHIVES = [['.zip', 'application/zip'], ['.tar.gz', 'application/gzip'], ['.tgz', 'application/gzip'], ['.tar', 'application/x-tar']];

/** Uploads files ({file, path}): one archive as the body, else multipart with each file's path. */
function upload(items) {
  if (!items.length) return;
  let body, type = null;
  const archive = items.length === 1 && ARCHIVES.find(([ext]) => items[0].file.name.toLowerCase().endsWith(ext));
  if (archive) {
    body = items[0].file;
    type = archive[1];
  } else {
    body = new FormData();
    for (const { file, path } of items) body.append(path, file, path);
  }
  const total = items.reduce((n, i) => n + i.file.size, 0);
  $('upload').hidden = false;
  $('upload-label').textContent = `Uploading ${items.length} file${items.length > 1 ? 's' : ''} (${fmtBytes(total)})`;
  const send = () => new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('POST', '/v1/scenes');
    authHeaders(type ? { 'Content-Type': type } : {}).forEach((v, k) => xhr.setRequestHeader(k, v));
    xhr.upload.onprogress = (e) => {
      if (!e.lengthComputable) return;
      $('upload-progress').value = e.loaded / e.total;
      $('upload-text').textContent = `${Math.round((100 * e.loaded) / e.total)} %`;
    };
    xhr.upload.onload = () => { $('upload-text').textContent = 'checking the dataset...'; };
    xhr.onload = () => resolve(xhr);
    xhr.onerror = () => reject(new Error('the upload failed (network error)'));
    xhr.send(body);
  });
  (async () => {
    let xhr = await send();
    while (xhr.status === 401) { await askKey(); xhr = await send(); }
    const answer = JSON.parse(xhr.responseText || 'null');
    if (xhr.status !== 201) throw new ApiError(xhr.status, answer && answer.error ? answer.error.message : `upload failed (${xhr.status})`);
    $('upload-text').textContent = answer.status === 'posing'
      ? `stored as ${answer.id}: no camera poses, estimating them with COLMAP`
      : `stored as ${answer.id}: ${answer.format}, ${answer.images.train} training views`;
    status(`scene ${answer.id} stored`);
    await refreshScenes();
  })().catch((e) => { $('upload-text').textContent = 'refused'; fail(e); });
}

/** The files of dropped entries (folders walked), with their relative paths. */
async function droppedFiles(dataTransfer) {
  const entries = [...dataTransfer.items].map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
  if (!entries.length) return [...dataTransfer.files].map((f) => ({ file: f, path: f.name }));
  const out = [];
  const walk = async (entry) => {
    if (entry.isFile) {
      const file = await new Promise((res, rej) => entry.file(res, rej));
      out.push({ file, path: entry.fullPath.replace(/^\//, '') });
    } else if (entry.isDirectory) {
      const reader = entry.createReader();
      for (;;) {
        const batch = await new Promise((res, rej) => reader.readEntries(res, rej));
        if (!batch.length) break;
        for (const e of batch) await walk(e);
      }
    }
  };
  for (const e of entries) await walk(e);
  return out;
}

function setupScenes() {
  const drop = $('drop');
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => {
    e.preventDefault();
    drop.classList.remove('over');
    droppedFiles(e.dataTransfer).then(upload).catch(fail);
  });
  drop.addEventListener('keydown', (e) => {
    if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); $('file-input').click(); }
  });
  $('file-input').addEventListener('change', (e) => {
    upload([...e.target.files].map((f) => ({ file: f, path: f.name })));
    e.target.value = '';
  });
  $('folder-input').addEventListener('change', (e) => {
    upload([...e.target.files].map((f) => ({ file: f, path: f.webkitRelativePath || f.name })));
    e.target.value = '';
  });
  $('demo-button').addEventListener('click', async () => {
    $('demo-button').disabled = true;
    status('generating the demo scene...');
    try {
      const s = await postJson('/v1/demo', {});
      status(`demo scene ${s.id} ready: train it next`);
      await refreshScenes();
      showTab('training');
      $('train-scene').value = s.id;
      $('train-model').value = 'instant';
      $('train-budget-kind').value = 'seconds';
      $('train-budget').value = 20;
      $('train-start').focus();
    } catch (e) { fail(e); } finally { $('demo-button').disabled = false; }
  });
}

// ----------------------------------------------------------- training ----

const training = { id: null, abort: null, points: [], lastPreview: 0, previewBusy: false, modelId: null, lastStep: null, shown: null };

async function refreshJobs() {
  await refreshScenes();
  const jobs = (await getJson('/v1/jobs')).filter((j) => j.kind === 'train').reverse();
  $('job-list').replaceChildren(...jobs.slice(0, 12).map((j) => el('li', { class: j.id === training.id ? 'current' : '' },
    el('strong', {}, j.id), el('div', { class: 'meta' },
      `${j.model} on ${j.scene_id} · ${j.status} · step ${j.progress.step}` +
      (j.progress.test_psnr != null ? ` · ${j.progress.test_psnr.toFixed(2)} dB` : '')),
    j.error ? el('p', { class: 'err' }, j.error) : null,
    el('button', { type: 'button', onclick: () => watchJob(j) }, 'Follow'))));
}

function watchJob(job) {
  if (training.abort) training.abort.abort();
  training.abort = new AbortController();
  Object.assign(training, { id: job.id, points: [], lastPreview: 0, modelId: null, lastStep: null, shown: null });
  $('job-panel').hidden = false;
  $('job-id').textContent = job.id;
  $('preview').removeAttribute('src');
  $('preview').alt = 'Preview of the model: not rendered yet';
  showJob(job);
  followJob(job.id, showJob, training.abort.signal)
    .then(() => refreshJobs())
    .catch(fail);
}

function showJob(job) {
  if (job.id !== training.id) return;
  const p = job.progress;
  const b = job.budget || {};
  const fraction = p.total_steps ? p.step / p.total_steps : b.seconds ? Math.min(1, p.elapsed / b.seconds) : 0;
  $('job-progress').value = job.status === 'succeeded' ? 1 : fraction;
  const psnr = p.test_psnr != null ? ` · held-out PSNR ${p.test_psnr.toFixed(2)} dB` : '';
  $('job-line').textContent = `${job.status} · step ${p.step}${p.total_steps ? ' / ' + p.total_steps : ''}` +
    ` · ${fmtSecs(p.elapsed)} trained · ETA ${job.status === 'running' ? fmtSecs(p.eta) : '-'}` + psnr +
    (job.error ? ` · ${job.error}` : '');
  $('job-line').dataset.step = p.step;
  $('job-line').dataset.status = job.status;
  $('job-cancel').disabled = job.status !== 'queued' && job.status !== 'running';
  if ($('job-cancel').disabled) status(`job ${job.id} ${job.status}`, job.status === 'failed');
  // During training test_psnr is an estimate on a sample of held-out
  // pixels; once the job succeeded it is the measurement on whole views,
  // drawn apart so a lower final number does not read as a drop.
  const key = `${p.test_psnr_step}:${p.test_psnr}:${job.status}`;
  if (p.test_psnr != null && key !== training.lastStep) {
    training.lastStep = key;
    training.points.push([p.elapsed, p.test_psnr, job.status === 'succeeded']);
    drawChart();
  }
  if (job.model_id) {
    training.modelId = job.model_id;
    $('job-view').disabled = false;
    const final = job.status !== 'queued' && job.status !== 'running';
    if (final || performance.now() - training.lastPreview > 2000) refreshPreview(final);
  }
}

/**
 * Renders the fixed preview view of the job's model when its checkpoint
 * has changed (one request at a time; the server saves a checkpoint every
 * --checkpoint-every seconds of training).
 */
async function refreshPreview(force) {
  if (training.previewBusy && !force) return;
  training.previewBusy = true;
  training.lastPreview = performance.now();
  try {
    const id = training.modelId;
    const model = await getJson(`/v1/models/${id}`);
    const version = `${id}@${model.updated_at}`;
    if (version === training.shown) return;
    training.shown = version;
    const blob = await (await api(`/v1/models/${id}/render?width=240&height=240`)).blob();
    const img = $('preview');
    const old = img.src;
    const url = URL.createObjectURL(blob);
    img.src = url;
    img.alt = `Preview of model ${id} from 30 degrees azimuth, 25 degrees up, as trained so far`;
    if (old) URL.revokeObjectURL(old);
    // Counted once it is decoded and shown, not when its request starts; a
    // newer preview that replaced it before then counts instead.
    try {
      await img.decode();
    } catch (e) {
      if (img.src === url) throw e;
      return;
    }
    if (img.src === url) img.dataset.count = String(Number(img.dataset.count || 0) + 1);
  } catch (e) {
    if (!(e instanceof ApiError && e.status === 404)) fail(e);
  } finally {
    training.previewBusy = false;
  }
}

function drawChart() {
  const c = $('psnr-chart');
  const g = c.getContext('2d');
  const [w, h, left, bottom] = [c.width, c.height, 44, 28];
  g.clearRect(0, 0, w, h);
  g.fillStyle = '#fff';
  g.fillRect(0, 0, w, h);
  const pts = training.points;
  if (!pts.length) return;
  const tMax = Math.max(1, ...pts.map((p) => p[0])) * 1.05;
  const lo = Math.floor(Math.min(...pts.map((p) => p[1])) - 1);
  const hi = Math.ceil(Math.max(...pts.map((p) => p[1])) + 1);
  const x = (t) => left + ((w - left - 10) * t) / tMax;
  const y = (v) => h - bottom - ((h - bottom - 10) * (v - lo)) / (hi - lo);
  g.strokeStyle = '#d5dbe1';
  g.fillStyle = '#5a6672';
  g.font = '11px system-ui, sans-serif';
  for (let k = 0; k <= 4; k++) {
    const v = lo + ((hi - lo) * k) / 4;
    g.beginPath(); g.moveTo(left, y(v)); g.lineTo(w - 10, y(v)); g.stroke();
    g.fillText(v.toFixed(1), 4, y(v) + 4);
    const t = (tMax * k) / 4;
    g.fillText(`${t.toFixed(0)} s`, x(t) - 8, h - 8);
  }
  const estimates = pts.filter((p) => !p[2]);
  const measured = pts.filter((p) => p[2]);
  g.strokeStyle = '#1f5fbf';
  g.lineWidth = 2;
  g.beginPath();
  estimates.forEach(([t, v], i) => (i ? g.lineTo(x(t), y(v)) : g.moveTo(x(t), y(v))));
  g.stroke();
  g.fillStyle = '#1f5fbf';
  for (const [t, v] of estimates) { g.beginPath(); g.arc(x(t), y(v), 3, 0, 7); g.fill(); }
  g.fillStyle = '#c25400';
  for (const [t, v] of measured) g.fillRect(x(t) - 4, y(v) - 4, 8, 8);
  g.fillStyle = '#5a6672';
  g.fillText('● estimate (held-out pixels)', left + 6, 14);
  if (measured.length) { g.fillStyle = '#c25400'; g.fillText('■ measured (whole views)', left + 170, 14); }
  const [t, v, m] = pts[pts.length - 1];
  c.setAttribute('aria-label', `Held-out PSNR against training time: ${estimates.length} estimates` +
    `${m ? `, measured ${v.toFixed(2)} dB on whole views at the end` : `, latest ${v.toFixed(2)} dB`} after ${t.toFixed(0)} s`);
  c.dataset.points = String(pts.length);
}

function setupTraining() {
  $('train-budget-kind').addEventListener('change', (e) => {
    $('train-budget').value = { seconds: 60, target_psnr: 25, steps: 1000 }[e.target.value];
  });
  $('train-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const kind = $('train-budget-kind').value;
    const value = Number($('train-budget').value);
    const budget = { [kind]: kind === 'steps' ? Math.round(value) : value };
    try {
      const job = await postJson('/v1/jobs', { scene_id: $('train-scene').value, model: $('train-model').value, budget });
      status(`job ${job.id} queued`);
      watchJob(job);
      refreshJobs().catch(fail);
    } catch (err) { fail(err); }
  });
  $('job-cancel').addEventListener('click', async () => {
    try { await api(`/v1/jobs/${training.id}/cancel`, { method: 'POST' }); status(`asked ${training.id} to stop`); } catch (e) { fail(e); }
  });
  $('job-view').addEventListener('click', () => openViewer(training.modelId));
}

// ------------------------------------------------------------- viewer ----

let models = [];

async function refreshModels() {
  models = (await getJson('/v1/models')).reverse();
  for (const id of ['view-model', 'video-model']) {
    const s = $(id);
    const chosen = s.value;
    s.replaceChildren(...models.map((m) => el('option', { value: m.id },
      `${m.id} (${m.model}, ${m.steps} steps${m.test_psnr != null ? `, ${m.test_psnr.toFixed(1)} dB` : ''}${m.complete ? '' : ', training'})`)));
    if (chosen && models.some((m) => m.id === chosen)) s.value = chosen;
  }
  if (!viewer.model && models.length) selectModel(models[0].id);
}

const v3 = {
  add: (a, b) => a.map((x, i) => x + b[i]),
  sub: (a, b) => a.map((x, i) => x - b[i]),
  scale: (a, s) => a.map((x) => x * s),
  dot: (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
  cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
  norm: (a) => Math.hypot(a[0], a[1], a[2]),
  unit: (a) => v3.scale(a, 1 / (v3.norm(a) || 1)),
};

const viewer = {
  model: null, // the model record
  target: [0, 0, 0], azimuth: 30, elevation: 25, radius: 4, fov: 50,
  inflight: null, // { controller, full, issued }
  dirty: false, moving: false, stillTimer: 0,
  movedAt: 0, // when the latest movement began after a still view
  lastMove: 0,
  full: { blob: null },
  keyframes: [],
  pointers: new Map(), pinch: 0,
};

// Measurements, for people and for the browser tests.
window.radianceStats = { firstImageMs: [], fullImageMs: [], images: 0, renders: [] };

/**
 * The orbit's basis around the scene's up axis, as the engine's camera::Orbit:
 * azimuth 0 towards the side the training cameras saw (`view.front`; scenes
 * stored before it existed: world x).
 */
function orbitBasis(view) {
  const u = v3.unit(view.up);
  const ref = view.front || (Math.abs(u[0]) > 0.9 ? [0, 1, 0] : [1, 0, 0]);
  const a = v3.unit(v3.sub(ref, v3.scale(u, v3.dot(u, ref))));
  return [u, a, v3.cross(u, a)];
}

function eye() {
  const [u, a, b] = orbitBasis(viewer.model.view);
  const [az, elv] = [(viewer.azimuth * Math.PI) / 180, (viewer.elevation * Math.PI) / 180];
  const dir = v3.add(v3.scale(v3.add(v3.scale(a, Math.cos(az)), v3.scale(b, Math.sin(az))), Math.cos(elv)), v3.scale(u, Math.sin(elv)));
  return v3.add(viewer.target, v3.scale(dir, viewer.radius));
}

/** Camera-to-world rows (OpenGL: the camera looks down -z) looking from `from` at `at`. */
function lookAt(from, at, up) {
  const back = v3.unit(v3.sub(from, at));
  const right = v3.unit(v3.cross(up, back));
  const up2 = v3.cross(back, right);
  return [0, 1, 2].map((i) => [right[i], up2[i], back[i], from[i]]);
}

const c2w = () => lookAt(eye(), viewer.target, v3.unit(viewer.model.view.up));

/**
 * Full-resolution size: the training cameras' (at least 256 pixels on the
 * long side, so small scenes are not a blur), at most the size the image is
 * shown at (512 pixels wide) and the server's cap.
 */
function fullSize() {
  const { width, height } = viewer.model.view;
  const shown = $('view-img').clientWidth || 512;
  const s = Math.min(Math.max(1, 256 / Math.max(width, height)), shown / width, Math.sqrt(1048576 / (width * height)));
  return [Math.max(1, Math.round(width * s)), Math.max(1, Math.round(height * s))];
}

/** The small size shown while the view moves: about 128x128 pixels. */
function previewSize() {
  const [w, h] = fullSize();
  const s = Math.min(1, Math.sqrt(16384 / (w * h)));
  return [Math.max(8, Math.round(w * s)), Math.max(8, Math.round(h * s))];
}

function renderUrl(m, size, output, fov) {
  const flat = m.flat().map((x) => +x.toFixed(6)).join(',');
  return `/v1/models/${viewer.model.id}/render?c2w=${flat}&width=${size[0]}&height=${size[1]}&fov=${fov.toFixed(4)}&output=${output}`;
}

function selectModel(id) {
  const m = models.find((x) => x.id === id);
  if (!m) return;
  viewer.model = m;
  $('view-model').value = id;
  resetView();
}

function resetView() {
  const v = viewer.model.view;
  Object.assign(viewer, { target: v.centre.slice(), azimuth: 0, elevation: v.elevation ?? 25, radius: v.radius, fov: v.fov });
  changed(false);
}

/** The camera moved (moving: a drag, wheel or key still going on). */
function changed(moving = true) {
  if (!viewer.model) return;
  const now = performance.now();
  if (moving && !viewer.moving) viewer.movedAt = now;
  viewer.moving = moving;
  viewer.lastMove = now;
  viewer.dirty = true;
  clearTimeout(viewer.stillTimer);
  if (moving) {
    viewer.stillTimer = setTimeout(() => { viewer.moving = false; viewer.dirty = true; pump(); }, 120);
  }
  pump();
}

/**
 * Keeps at most one render in flight. While the view moves it asks for the
 * small size; once still, for full resolution. A full-size render still
 * running when the view moves again is aborted (the server stops it too),
 * so the image never lags behind the mouse by more than one small render.
 */
function pump() {
  const f = viewer.inflight;
  if (f) {
    if (f.full && viewer.dirty) f.controller.abort();
    else return;
  }
  if (!viewer.dirty || !viewer.model) return;
  viewer.dirty = false;
  const full = !viewer.moving;
  const size = full ? fullSize() : previewSize();
  const output = $('view-output').value;
  const controller = new AbortController();
  const issued = performance.now();
  const request = { controller, full, issued, movedAt: viewer.movedAt, lastMove: viewer.lastMove };
  viewer.inflight = request;
  const url = renderUrl(c2w(), size, output, viewer.fov);
  api(url, { signal: controller.signal })
    .then((r) => r.blob())
    .then((blob) => show(blob, request, size, output))
    .catch((e) => { if (e.name !== 'AbortError') fail(e); })
    .finally(() => {
      if (viewer.inflight === request) viewer.inflight = null;
      pump();
    });
}

async function show(blob, request, size, output) {
  const img = $('view-img');
  const url = URL.createObjectURL(blob);
  const next = new Image();
  next.src = url;
  await next.decode();
  const old = img.src;
  img.src = url;
  if (old) URL.revokeObjectURL(old);
  const now = performance.now();
  const stats = window.radianceStats;
  stats.images += 1;
  stats.renders.push({ full: request.full, ms: now - request.issued, width: size[0], height: size[1] });
  if (stats.renders.length > 200) stats.renders.shift();
  // From the start of a movement to its first new image; from the last
  // movement to the full-resolution image.
  if (request.movedAt && request.issued >= request.movedAt && !request.firstCounted && stats._firstFor !== request.movedAt) {
    stats._firstFor = request.movedAt;
    stats.firstImageMs.push(now - request.movedAt);
  }
  if (request.full && request.lastMove && stats._fullFor !== request.lastMove && request.issued >= request.lastMove) {
    stats._fullFor = request.lastMove;
    stats.fullImageMs.push(now - request.lastMove);
  }
  img.dataset.hash = String(await hashOf(blob));
  img.dataset.full = String(request.full);
  img.dataset.count = String(stats.images);
  const what = { rgb: 'colour', depth: 'depth (darker is nearer)', alpha: 'opacity' }[output];
  img.alt = `Model ${viewer.model.id}, ${what}, seen from ${viewer.azimuth.toFixed(0)} degrees azimuth and ` +
    `${viewer.elevation.toFixed(0)} degrees elevation at distance ${viewer.radius.toFixed(2)}` + (request.full ? '' : ' (low resolution while moving)');
  if (request.full) viewer.full.blob = blob;
  $('view-info').textContent = `${size[0]}x${size[1]} ${request.full ? 'full' : 'preview'} image in ${(now - request.issued).toFixed(0)} ms`;
}

async function hashOf(blob) {
  const bytes = new Uint8Array(await blob.arrayBuffer());
  let h = 2166136261;
  for (let i = 0; i < bytes.length; i++) h = Math.imul(h ^ bytes[i], 16777619) >>> 0;
  return h;
}

/** Recentres the orbit on the surface under pixel (px, py) of the shown image, from a 1-pixel depth render along that ray. */
async function recentre(px, py) {
  const img = $('view-img');
  const [w, h] = [img.clientWidth, img.clientHeight];
  const f = (0.5 * w) / Math.tan((viewer.fov * Math.PI) / 360);
  const m = c2w();
  const local = [px - w / 2, -(py - h / 2), -f];
  const dir = v3.unit([0, 1, 2].map((i) => m[i][0] * local[0] + m[i][1] * local[1] + m[i][2] * local[2]));
  const from = eye();
  const up = Math.abs(v3.dot(dir, v3.unit(viewer.model.view.up))) > 0.99 ? orbitBasis(viewer.model.view)[1] : viewer.model.view.up;
  const probe = lookAt(from, v3.add(from, dir), v3.unit(up));
  const blob = await (await api(renderUrl(probe, [1, 1], 'depth', 2))).blob();
  const bitmap = await createImageBitmap(blob);
  const canvas = document.createElement('canvas');
  canvas.width = canvas.height = 1;
  const g = canvas.getContext('2d');
  g.drawImage(bitmap, 0, 0);
  const value = g.getImageData(0, 0, 1, 1).data[0];
  if (value >= 254) { status('nothing there to centre on'); return; }
  const depth = (value / 255) * viewer.model.view.far;
  const target = v3.add(from, v3.scale(dir, depth));
  // Keep the camera where it is; turn it to the new centre.
  const back = v3.sub(from, target);
  const [u, a, b] = orbitBasis(viewer.model.view);
  const r = v3.norm(back);
  Object.assign(viewer, {
    target, radius: r,
    elevation: (Math.asin(Math.max(-1, Math.min(1, v3.dot(back, u) / r))) * 180) / Math.PI,
    azimuth: (Math.atan2(v3.dot(back, b), v3.dot(back, a)) * 180) / Math.PI,
  });
  status(`centred on the point ${target.map((x) => x.toFixed(2)).join(', ')}`);
  changed(false);
}

function orbitBy(dAz, dEl) {
  viewer.azimuth = (viewer.azimuth + dAz) % 360;
  viewer.elevation = Math.max(-89, Math.min(89, viewer.elevation + dEl));
  changed(true);
}

function zoomBy(factor) {
  viewer.radius = Math.max(0.05, Math.min(100, viewer.radius * factor));
  changed(true);
}

function setupViewer() {
  const stage = $('stage');
  stage.addEventListener('pointerdown', (e) => {
    stage.setPointerCapture(e.pointerId);
    viewer.pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (viewer.pointers.size === 2) {
      const [p, q] = [...viewer.pointers.values()];
      viewer.pinch = Math.hypot(p[0] - q[0], p[1] - q[1]);
    }
  });
  stage.addEventListener('pointermove', (e) => {
    const last = viewer.pointers.get(e.pointerId);
    if (!last) return;
    viewer.pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (viewer.pointers.size === 2) {
      const [p, q] = [...viewer.pointers.values()];
      const d = Math.hypot(p[0] - q[0], p[1] - q[1]);
      if (viewer.pinch > 0 && d > 0) zoomBy(viewer.pinch / d);
      viewer.pinch = d;
    } else {
      orbitBy(-(e.clientX - last[0]) * 0.4, (e.clientY - last[1]) * 0.4);
    }
  });
  const release = (e) => { viewer.pointers.delete(e.pointerId); viewer.pinch = 0; };
  stage.addEventListener('pointerup', release);
  stage.addEventListener('pointercancel', release);
  stage.addEventListener('wheel', (e) => { e.preventDefault(); zoomBy(Math.exp(e.deltaY * 0.001)); }, { passive: false });
  stage.addEventListener('dblclick', (e) => {
    const r = $('view-img').getBoundingClientRect();
    recentre(e.clientX - r.left, e.clientY - r.top).catch(fail);
  });
  stage.addEventListener('keydown', (e) => {
    const keys = {
      ArrowLeft: () => orbitBy(5, 0), ArrowRight: () => orbitBy(-5, 0),
      ArrowUp: () => orbitBy(0, 5), ArrowDown: () => orbitBy(0, -5),
      '+': () => zoomBy(0.9), '=': () => zoomBy(0.9), '-': () => zoomBy(1 / 0.9),
      Home: () => resetView(),
      Enter: () => { const i = $('view-img'); recentre(i.clientWidth / 2, i.clientHeight / 2).catch(fail); },
    };
    if (keys[e.key] && viewer.model) { e.preventDefault(); keys[e.key](); }
  });
  stage.addEventListener('keyup', () => { if (viewer.moving) { clearTimeout(viewer.stillTimer); viewer.stillTimer = setTimeout(() => { viewer.moving = false; viewer.dirty = true; pump(); }, 120); } });
  $('view-model').addEventListener('change', (e) => selectModel(e.target.value));
  $('view-output').addEventListener('change', () => changed(false));
  $('view-reset').addEventListener('click', () => resetView());
  $('view-save').addEventListener('click', () => {
    if (!viewer.full.blob) { status('no full-resolution image yet'); return; }
    const a = el('a', { href: URL.createObjectURL(viewer.full.blob), download: `${viewer.model.id}-${$('view-output').value}-az${viewer.azimuth.toFixed(0)}-el${viewer.elevation.toFixed(0)}.png` });
    document.body.append(a);
    a.click();
    a.remove();
  });
  $('view-add').addEventListener('click', () => {
    if (!viewer.model) return;
    viewer.keyframes.push({ c2w: c2w(), fov: viewer.fov, label: `azimuth ${viewer.azimuth.toFixed(0)}°, elevation ${viewer.elevation.toFixed(0)}°, distance ${viewer.radius.toFixed(2)}` });
    showKeyframes();
    status(`view ${viewer.keyframes.length} added to the path`);
  });
  $('path-clear').addEventListener('click', () => { viewer.keyframes = []; showKeyframes(); });
  $('path-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const path = viewer.keyframes.map((k) => ({ c2w: k.c2w, fov: k.fov }));
    await makeVideo(viewer.model.id, { path, frames: Number($('path-frames').value), format: $('path-format').value });
  });
}

function showKeyframes() {
  $('keyframes').replaceChildren(...viewer.keyframes.map((k, i) => el('li', {}, k.label, ' ',
    el('button', { type: 'button', 'aria-label': `Remove view ${i + 1}`, onclick: () => { viewer.keyframes.splice(i, 1); showKeyframes(); } }, 'Remove'))));
  $('path-make').disabled = viewer.keyframes.length < 2;
}

async function openViewer(modelId) {
  showTab('viewer');
  await refreshModels();
  selectModel(modelId);
  $('stage').focus();
}

// ------------------------------------------------------------- videos ----

const videoWatch = new Map();

async function makeVideo(modelId, body) {
  try {
    const job = await postJson(`/v1/models/${modelId}/videos`, body);
    status(`video job ${job.id} queued`);
    showTab('videos');
    watchVideo(job);
  } catch (e) { fail(e); }
}

async function refreshVideos() {
  const jobs = (await getJson('/v1/jobs')).filter((j) => j.kind === 'video').reverse();
  $('video-list').replaceChildren(...jobs.map(videoCard));
  for (const j of jobs) if (j.status === 'queued' || j.status === 'running') watchVideo(j);
}

function videoCard(j) {
  const p = j.progress;
  const what = j.path ? `path of ${j.path.length} views` : 'orbit';
  return el('li', { 'data-job': j.id, 'data-status': j.status },
    el('strong', {}, `${what}, ${j.format.toUpperCase()}`),
    el('div', { class: 'meta' }, `model ${j.model_id} · ${j.frames} frames at ${j.fps} fps · ${j.width}x${j.height} · ${j.status}`),
    j.status === 'running' || j.status === 'queued'
      ? el('progress', { max: j.frames, value: p.step, 'aria-label': `frames rendered: ${p.step} of ${j.frames}` })
      : null,
    j.error ? el('p', { class: 'err' }, j.error) : null,
    j.video_id ? el('p', {}, el('button', { type: 'button', onclick: () => play(j).catch(fail) }, 'Play'), ' ',
      el('button', { type: 'button', onclick: () => download(j).catch(fail) }, 'Download')) : null);
}

function watchVideo(job) {
  if (videoWatch.has(job.id)) return;
  videoWatch.set(job.id, true);
  followJob(job.id, (j) => {
    const card = document.querySelector(`#video-list li[data-job="${j.id}"]`);
    const fresh = videoCard(j);
    if (card) card.replaceWith(fresh); else $('video-list').prepend(fresh);
  }).catch(fail).finally(() => {
    videoWatch.delete(job.id);
    refreshVideos().catch(fail);
  });
}

async function videoBlob(j) {
  return (await api(`/v1/videos/${j.video_id}`)).blob();
}

async function play(j) {
  const blob = await videoBlob(j);
  const url = URL.createObjectURL(blob);
  const [video, gif] = [$('player-video'), $('player-gif')];
  for (const m of [video, gif]) if (m.src) URL.revokeObjectURL(m.src);
  $('player').hidden = false;
  $('player-title').textContent = `Video ${j.video_id}`;
  video.hidden = j.format !== 'mp4';
  gif.hidden = j.format !== 'gif';
  if (j.format === 'mp4') { video.src = url; gif.removeAttribute('src'); } else { gif.src = url; video.removeAttribute('src'); }
  gif.alt = `${j.path ? 'Camera path' : 'Orbit'} video of model ${j.model_id}, ${j.frames} frames`;
  video.setAttribute('aria-label', gif.alt);
  const a = $('player-download');
  a.href = url;
  a.download = `${j.video_id}.${j.format}`;
}

async function download(j) {
  const blob = await videoBlob(j);
  const a = el('a', { href: URL.createObjectURL(blob), download: `${j.video_id}.${j.format}` });
  document.body.append(a);
  a.click();
  a.remove();
}

function setupVideos() {
  $('video-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const body = { frames: Number($('video-frames').value), fps: Number($('video-fps').value), format: $('video-format').value };
    if ($('video-width').value) body.width = Number($('video-width').value);
    if ($('video-height').value) body.height = Number($('video-height').value);
    await makeVideo($('video-model').value, body);
  });
}

// -------------------------------------------------------------- start ----

function start() {
  for (const t of TABS) $('tab-' + t).addEventListener('click', () => showTab(t));
  setupScenes();
  setupTraining();
  setupViewer();
  setupVideos();
  showTab('scenes');
  document.body.dataset.ready = 'true';
}

start();
