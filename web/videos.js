// The videos page: orbit videos and camera-path videos made by jobs,
// followed while they render, played and downloaded.

import { api, followJob, getJson, postJson } from './api.js';
import { $, el, fail, showTab, status } from './ui.js';

const videoWatch = new Map();

export async function makeVideo(modelId, body) {
  try {
    const job = await postJson(`/v1/models/${modelId}/videos`, body);
    status(`video job ${job.id} queued`);
    showTab('videos');
    watchVideo(job);
  } catch (e) { fail(e); }
}

export async function refreshVideos() {
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

export function setupVideos() {
  $('video-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const body = { frames: Number($('video-frames').value), fps: Number($('video-fps').value), format: $('video-format').value };
    if ($('video-width').value) body.width = Number($('video-width').value);
    if ($('video-height').value) body.height = Number($('video-height').value);
    await makeVideo($('video-model').value, body);
  });
}
