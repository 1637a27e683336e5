// The scenes page: the list of scenes (each card with a thumbnail of a
// photo and the upload's name), the upload of a dataset (an archive, a
// folder or photos, dropped or chosen) and the demo scene.

import { ApiError, api, askKey, authHeaders, getJson, postJson } from './api.js';
import { $, el, fail, fmtBytes, fmtSecs, showTab, status } from './ui.js';

let scenes = [];

export async function refreshScenes() {
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
    el('option', { value: s.id }, `${s.name ? `${s.name}, ${s.id}` : s.id} (${s.format}, ${s.images.train} views, ${s.resolution.join('x')})`)));
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
  const name = s.name || s.id;
  return el('li', { 'data-scene': s.id, 'data-status': state },
    el('div', { class: 'head' }, thumbnail(s, name),
      el('div', {}, el('strong', { class: 'name' }, name), el('div', { class: 'meta id' }, s.id))),
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

/** Thumbnails by scene id: object URLs of the fetched JPEGs (or null while
 * one is fetched, or when the scene has no photo), fetched once per page. */
const thumbnails = new Map();

/** A card's thumbnail: a photo of the scene, fetched with the API key. */
function thumbnail(s, name) {
  const img = el('img', { class: 'thumb', alt: `A photo of ${name}`, width: 96, height: 72, loading: 'lazy' });
  const known = thumbnails.get(s.id);
  if (known) {
    img.src = known;
    return img;
  }
  if (s.status === 'posing' && s.poses && s.poses.source === 'video') return el('div', { class: 'thumb' });
  if (!thumbnails.has(s.id)) {
    thumbnails.set(s.id, null);
    api(`/v1/scenes/${s.id}/thumbnail`)
      .then((r) => r.blob())
      .then((blob) => {
        const url = URL.createObjectURL(blob);
        thumbnails.set(s.id, url);
        // The card may have been drawn again meanwhile: fill whichever is shown.
        for (const i of document.querySelectorAll(`#scene-list li[data-scene="${s.id}"] img.thumb`)) i.src = url;
      })
      .catch((e) => { if (!(e instanceof ApiError && e.status === 404)) fail(e); });
  }
  return img;
}

async function deleteScene(id) {
  if (!confirm(`Delete scene ${id}? Models trained on it stay.`)) return;
  try {
    await api(`/v1/scenes/${id}`, { method: 'DELETE' });
    const url = thumbnails.get(id);
    if (url) URL.revokeObjectURL(url);
    thumbnails.delete(id);
    status(`deleted ${id}`);
    await refreshScenes();
  } catch (e) { fail(e); }
}

const ARCHIVES = [['.zip', 'application/zip'], ['.tar.gz', 'application/gzip'], ['.tgz', 'application/gzip'], ['.tar', 'application/x-tar']];

/**
 * What an upload is called: the archive's file name, the folder the files
 * are in, or the one file's name; null for loose photos.
 */
function uploadName(items) {
  if (items.length === 1) return items[0].file.name;
  const tops = new Set(items.map((i) => (i.path.includes('/') ? i.path.split('/')[0] : '')));
  return tops.size === 1 && !tops.has('') ? [...tops][0] : null;
}

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
  const name = uploadName(items);
  const target = '/v1/scenes' + (name ? `?name=${encodeURIComponent(name)}` : '');
  // The bar shows while the upload runs (sending, then the server's check).
  $('upload').hidden = false;
  $('upload-progress').value = 0;
  $('upload-percent').textContent = '';
  $('upload-text').textContent = '';
  $('upload-label').textContent = `Uploading ${items.length} file${items.length > 1 ? 's' : ''} (${fmtBytes(total)})`;
  const send = () => new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('POST', target);
    authHeaders(type ? { 'Content-Type': type } : {}).forEach((v, k) => xhr.setRequestHeader(k, v));
    xhr.upload.onprogress = (e) => {
      if (!e.lengthComputable) return;
      $('upload-progress').value = e.loaded / e.total;
      $('upload-percent').textContent = `${Math.round((100 * e.loaded) / e.total)} %`;
    };
    xhr.upload.onload = () => {
      $('upload-progress').value = 1;
      $('upload-percent').textContent = 'checking the dataset...';
    };
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
  })().catch((e) => { $('upload-text').textContent = 'refused'; fail(e); })
    .finally(() => { $('upload').hidden = true; });
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

export function setupScenes() {
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
