// The training page: start a job, follow it over its event stream (step,
// ETA, held-out PSNR chart, a preview render refreshed as it trains), and
// the list of training jobs.

import { ApiError, api, followJob, getJson, postJson } from './api.js';
import { refreshScenes } from './scenes.js';
import { $, bakeLine, el, fail, fmtSecs, status } from './ui.js';
import { openViewer } from './viewer.js';

const training = { id: null, abort: null, points: [], lastPreview: 0, previewBusy: false, modelId: null, lastStep: null, shown: null };

export async function refreshJobs() {
  await refreshScenes();
  const jobs = (await getJson('/v1/jobs')).filter((j) => j.kind === 'train' || j.kind === 'bake').reverse();
  $('job-list').replaceChildren(...jobs.slice(0, 12).map((j) => el('li', { class: j.id === training.id ? 'current' : '' },
    el('strong', {}, j.id), el('div', { class: 'meta' },
      `${j.kind === 'bake' ? `splats of ${j.source_model_id}` : j.model} on ${j.scene_id} · ${j.status} · step ${j.progress.step}` +
      (j.progress.test_psnr != null ? ` · ${j.progress.test_psnr.toFixed(2)} dB` : '')),
    j.error ? el('p', { class: 'err' }, j.error) : null,
    el('button', { type: 'button', onclick: () => watchJob(j) }, 'Follow'))));
}

function watchJob(job) {
  if (training.abort) training.abort.abort();
  training.abort = new AbortController();
  Object.assign(training, { id: job.id, points: [], lastPreview: 0, modelId: null, lastStep: null, shown: null, baking: null });
  $('bake-line').hidden = true;
  $('job-panel').hidden = false;
  $('job-id').textContent = job.id;
  $('preview').removeAttribute('src');
  $('preview').alt = 'Preview of the model: not rendered yet';
  $('transients').hidden = true;
  showJob(job);
  followJob(job.id, showJob, training.abort.signal)
    .then(() => refreshJobs())
    .catch(fail);
}

/**
 * Follows the bake a training job asked for; when it succeeds and the
 * training page is still shown, opens its splats in the viewer: a dropped
 * set of photos ends on the real-time view.
 */
function followBake(id) {
  training.baking = id;
  const line = $('bake-line');
  line.hidden = false;
  line.textContent = `baking the real-time view (job ${id})...`;
  const show = (j) => {
    line.dataset.status = j.status;
    line.textContent = `real-time view (job ${j.id}): ${bakeLine(j)}`;
    if (j.status === 'succeeded' && j.model_id && !$('training').hidden) openViewer(j.model_id).catch(fail);
  };
  followJob(id, show).catch(fail);
}

function showJob(job) {
  if (job.id !== training.id) return;
  const p = job.progress;
  const b = job.budget || { seconds: job.seconds };
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
  if (job.kind === 'train' && job.bake && job.status === 'succeeded' && training.baking !== job.bake.job_id) {
    followBake(job.bake.job_id);
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
    showTransients(model);
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

export function setupTraining() {
  $('train-budget-kind').addEventListener('change', (e) => {
    $('train-budget').value = { seconds: 60, target_psnr: 25, steps: 1000 }[e.target.value];
  });
  $('train-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const kind = $('train-budget-kind').value;
    const value = Number($('train-budget').value);
    const budget = { [kind]: kind === 'steps' ? Math.round(value) : value };
    try {
      const body = { scene_id: $('train-scene').value, model: $('train-model').value, budget };
      if ($('train-bake').checked) body.bake = { seconds: Number($('train-bake-seconds').value) || 60 };
      // Checked: the service's default (capture models drop transients,
      // others do not); unchecked: every pixel is trained on.
      if (!$('train-transients').checked) body.drop_transients = false;
      const job = await postJson('/v1/jobs', body);
      status(`job ${job.id} queued`);
      watchJob(job);
      refreshJobs().catch(fail);
    } catch (err) { fail(err); }
  });
  $('job-cancel').addEventListener('click', async () => {
    try { await api(`/v1/jobs/${training.id}/cancel`, { method: 'POST' }); status(`asked ${training.id} to stop`); } catch (e) { fail(e); }
  });
  $('job-view').addEventListener('click', () => openViewer(training.modelId));
  $('transients-show').addEventListener('click', () => showMasks().catch(fail));
}

/**
 * What a job that dropped transients dropped: the share of the training
 * pixels, the photos mostly masked (worth retaking), and on demand every
 * photo's mask, most masked first (black where a pixel was dropped).
 */
function showTransients(model) {
  const t = model.transients;
  $('transients').hidden = !t;
  if (!t) return;
  const withSome = t.photos.filter((p) => p.share > 0);
  const mostly = t.photos.filter((p) => p.share >= 0.5).map((p) => p.name);
  $('transients-line').textContent = `transient occluders: ${(100 * t.dropped).toFixed(2)}% of the training pixels ` +
    `dropped, in ${withSome.length} of ${t.photos.length} photos` +
    (mostly.length ? `; mostly masked, worth retaking: ${mostly.join(', ')}` : '');
  $('transients').dataset.model = model.id;
  $('transients-list').replaceChildren();
}

async function showMasks() {
  const id = $('transients').dataset.model;
  const model = await getJson(`/v1/models/${id}`);
  const photos = [...model.transients.photos].sort((a, b) => b.share - a.share);
  const items = photos.map((p) => {
    const img = el('img', { alt: `Transient mask of ${p.name}: black where dropped`, width: 120 });
    const item = el('li', {}, el('figure', {}, img, el('figcaption', {}, `${p.name} · ${(100 * p.share).toFixed(1)}%`)));
    return [item, img, p.name];
  });
  $('transients-list').replaceChildren(...items.map((i) => i[0]));
  for (const [, img, name] of items) {
    const blob = await (await api(`/v1/models/${id}/transients/${encodeURIComponent(name)}`)).blob();
    img.src = URL.createObjectURL(blob);
  }
}
