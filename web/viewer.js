// The viewer: a model rendered by the server from a camera the user turns
// (drag, wheel, pinch, keys), small renders while the view moves and a
// full-resolution one once it is still; depth and opacity; a camera path
// for a video. A splats model is drawn by the browser instead (splats.js,
// loaded when first needed): its `.splat` file is fetched once from
// `/v1/models/{id}/export` and nothing more is asked of the server. The
// page's address follows the camera (`#/models/ID?eye=x,y,z&target=x,y,z&fov=F`,
// both kinds), so a link opens the model at that view.
// `window.radianceStats` keeps its timings for people and for the browser
// tests.

import { api, followJob, getJson, postJson } from './api.js';
import { closeMesh, downloadSite, showMesh } from './mesh.js';
import { $, bakeLine, el, fail, showTab, status } from './ui.js';
import { makeVideo } from './videos.js';

let models = [];

export async function refreshModels() {
  models = (await getJson('/v1/models')).reverse();
  for (const id of ['view-model', 'video-model']) {
    const s = $(id);
    const chosen = s.value;
    s.replaceChildren(...models.map((m) => el('option', { value: m.id },
      `${m.id} (${m.model}${m.gaussians ? `, ${m.gaussians.toLocaleString('en')} Gaussians` : ''}, ${m.steps} steps` +
      `${m.test_psnr != null ? `, ${m.test_psnr.toFixed(1)} dB` : ''}${m.complete ? '' : ', training'})`)));
    if (chosen && models.some((m) => m.id === chosen)) s.value = chosen;
  }
  if (!viewer.model && models.length && !opening) selectModel(models[0].id).catch(fail);
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

const isSplats = (m) => m.model === 'splats' || (m.config && m.config.kind === 'splats');

/** The splat viewer (created once, when a splats model is first shown). */
let splats = null;

async function selectModel(id, camera) {
  const m = models.find((x) => x.id === id);
  if (!m) return;
  viewer.model = m;
  $('view-model').value = id;
  const drawn = isSplats(m);
  $('view-img').hidden = drawn;
  $('view-splats').hidden = !drawn;
  $('view-output').disabled = drawn;
  $('view-bake').hidden = drawn || !m.complete;
  $('view-export').hidden = !drawn;
  $('view-crop').hidden = !drawn;
  $('view-mesh').hidden = !m.complete;
  closeCrop();
  closeMesh();
  const v = m.view;
  Object.assign(viewer, { target: v.centre.slice(), azimuth: 0, elevation: v.elevation ?? 25, radius: v.radius, fov: v.fov });
  if (camera) setFromLink(camera);
  if (drawn) await showSplats(m);
  else changed(false);
}

function resetView() {
  const v = viewer.model.view;
  Object.assign(viewer, { target: v.centre.slice(), azimuth: 0, elevation: v.elevation ?? 25, radius: v.radius, fov: v.fov });
  if (isSplats(viewer.model) && splats) placeSplatCamera();
  else changed(false);
}

/** The orbit from a link's camera: eye and target points, field of view. */
function setFromLink({ eye: from, target, fov }) {
  const back = v3.sub(from, target);
  const r = v3.norm(back);
  if (!(r > 0)) return;
  const [u, a, b] = orbitBasis(viewer.model.view);
  Object.assign(viewer, {
    target, radius: r, fov: fov || viewer.fov,
    elevation: (Math.asin(Math.max(-1, Math.min(1, v3.dot(back, u) / r))) * 180) / Math.PI,
    azimuth: (Math.atan2(v3.dot(back, b), v3.dot(back, a)) * 180) / Math.PI,
  });
}

/** The address of the current view: `#/models/ID?eye=...&target=...&fov=...`. */
export function viewLink() {
  if (!viewer.model) return '#';
  const num = (a) => a.map((x) => +x.toFixed(4)).join(',');
  return `#/models/${viewer.model.id}?eye=${num(eye())}&target=${num(viewer.target)}&fov=${+viewer.fov.toFixed(3)}`;
}

function updateLink() {
  const link = viewLink();
  $('view-link').href = link;
  if (!$('viewer').hidden && location.hash !== link) history.replaceState(null, '', link);
}

/** Parses `#/models/ID?eye=x,y,z&target=x,y,z&fov=F` (camera optional). */
export function parseLink(hash) {
  const m = /^#\/models\/([a-z0-9_]+)(?:\?(.*))?$/.exec(hash);
  if (!m) return null;
  const q = new URLSearchParams(m[2] || '');
  const vec = (k) => {
    const v = (q.get(k) || '').split(',').map(Number);
    return v.length === 3 && v.every(Number.isFinite) ? v : null;
  };
  const [from, target, fov] = [vec('eye'), vec('target'), Number(q.get('fov'))];
  const camera = from && target ? { eye: from, target, fov: Number.isFinite(fov) && fov > 1 && fov < 179 ? fov : null } : null;
  return { id: m[1], camera };
}

/**
 * The splat canvas's size: the photos' shape, 720 pixels on its longer
 * side (at most 1 MP and 90% of the window's width). The browser draws it,
 * so unlike a server render it need not stay within the photos' size.
 */
function splatSize() {
  const { width, height } = viewer.model.view;
  const s = Math.min(720 / Math.max(width, height), (0.9 * (window.innerWidth || 1000)) / width, Math.sqrt(1048576 / (width * height)));
  return [Math.max(1, Math.round(width * s)), Math.max(1, Math.round(height * s))];
}

/** Our pinhole camera for the splat canvas: its size and the orbit's field of view. */
function splatIntrinsics() {
  const [width, height] = splatSize();
  const f = (0.5 * width) / Math.tan((viewer.fov * Math.PI) / 360);
  return { fx: f, fy: f, cx: width / 2, cy: height / 2, width, height };
}

// The near plane: the capture's near bound, from which the field's rays
// start and the server draws the splats (records before it: a hundredth
// of the orbit's radius).
function splatNear(v) {
  return v.near > 0 ? v.near : Math.max(1e-4, viewer.radius * 0.01);
}

function placeSplatCamera() {
  const v = viewer.model.view;
  splats.camera.up.set(...v3.unit(v.up));
  splats.setCamera(c2w(), splatIntrinsics(), { near: splatNear(v), far: Math.max(v.far * 4, viewer.radius * 10), target: viewer.target });
  splats.controls.update();
  updateLink();
}

/** The orbit follows the splat view's camera (its controls moved it). */
function splatMoved() {
  if (!viewer.model || !isSplats(viewer.model)) return;
  const p = splats.camera.position, t = splats.controls.target;
  setFromLink({ eye: [p.x, p.y, p.z], target: [t.x, t.y, t.z], fov: viewer.fov });
  updateLink();
}

/**
 * Downloads the shown splats model in the chosen format (with the API key,
 * so through a blob), named as the server names it, and says what the
 * floater cleanup removed.
 */
async function downloadSplats() {
  const m = viewer.model;
  const format = $('view-export-format').value;
  status(`preparing the ${format} file...`);
  const res = await api(`/v1/models/${m.id}/export?format=${format}`);
  const name = /filename="([^"]+)"/.exec(res.headers.get('content-disposition') || '')?.[1] || `${m.id}.${format}`;
  const blob = await res.blob();
  const a = el('a', { href: URL.createObjectURL(blob), download: name });
  document.body.append(a);
  a.click();
  a.remove();
  const kept = res.headers.get('x-gaussians');
  const removed = res.headers.get('x-gaussians-removed');
  $('view-export-go').dataset.file = name;
  status(`${name}: ${(blob.size / 1048576).toFixed(2)} MiB, ${kept} Gaussians (${removed} floaters removed)`);
}

/** The crop box editor while it is open (crop.js). */
let cropEditor = null;

/**
 * Opens the crop box over every Gaussian of the shown model (so that what
 * it leaves out shows): the model's crop, else a box around all of them.
 */
async function editCrop() {
  const m = viewer.model;
  const { CropEditor, boxAround } = await import('./crop.js');
  closeCrop();
  delete $('view-splats').dataset.cropDone;
  await showSplats(m, { crop: false });
  const box = m.crop || boxAround(splats.bounds);
  cropEditor = new CropEditor(splats, box, cropCounted);
  window.cropEditor = cropEditor;
  cropEditor.setMode($('crop-mode').value);
  $('crop-tools').hidden = false;
  $('crop-edit').hidden = true;
  cropCounted(cropEditor.preview());
}

/** Says how many Gaussians the box holds (and keeps it for the tests). */
function cropCounted({ inside, all }) {
  $('view-splats').dataset.cropInside = String(inside);
  status(`the crop box holds ${inside} of the ${all} Gaussians`);
}

function closeCrop() {
  if (cropEditor) cropEditor.dispose();
  cropEditor = null;
  window.cropEditor = null;
  $('crop-tools').hidden = true;
  $('crop-edit').hidden = false;
}

/** Stores the box on the model, then shows what is inside it. */
async function saveCrop(body) {
  const m = viewer.model;
  const res = await api(`/v1/models/${m.id}/crop`, {
    method: 'PUT', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  });
  m.crop = await res.json();
  return m.crop;
}

async function cropAction(what) {
  const m = viewer.model;
  if (what === 'auto') {
    status('finding the object...');
    cropCounted(cropEditor.set(await saveCrop({ auto: true })));
    return;
  }
  if (what === 'save') await saveCrop(cropEditor.box());
  if (what === 'remove') {
    await api(`/v1/models/${m.id}/crop`, { method: 'DELETE' });
    delete m.crop;
  }
  closeCrop();
  await showSplats(m);
  // What the tests wait for: the view drawn again after this action.
  $('view-splats').dataset.cropDone = what;
  if (what !== 'close') status(m.crop ? 'cropped: views, videos and downloads keep what is inside the box' : 'the crop is removed');
}

async function showSplats(m, { crop = true } = {}) {
  if (!splats) {
    const { SplatView } = await import('./splats.js');
    splats = new SplatView($('view-splats'), { background: [1, 1, 1], up: m.view.up });
    splats.controls.addEventListener('change', splatMoved);
    window.splatView = splats;
  }
  placeSplatCamera();
  $('view-info').textContent = 'loading the splats...';
  const t0 = performance.now();
  const n = await splats.load(`/v1/models/${m.id}/export?${crop ? '' : 'crop=false&'}format=spz`);
  if (viewer.model !== m) return;
  placeSplatCamera();
  await splats.settled();
  $('view-splats').dataset.model = m.id;
  $('view-splats').dataset.count = String(n);
  $('view-info').textContent = `${n} Gaussians, fetched and drawn by this browser in ${(performance.now() - t0).toFixed(0)} ms`;
}

/** Bakes the shown model into splats, then shows them. */
async function bakeShown() {
  const m = viewer.model;
  if (!m) return;
  const job = await postJson('/v1/jobs', { kind: 'bake', model_id: m.id, seconds: 60 });
  status(`baking model ${m.id} into splats (job ${job.id})`);
  $('view-bake').disabled = true;
  let end = job;
  try {
    await followJob(job.id, (j) => {
      end = j;
      $('view-info').textContent = `baking (job ${j.id}): ${bakeLine(j)}`;
    });
  } finally {
    $('view-bake').disabled = false;
  }
  if (end.status !== 'succeeded') { status(`bake ${end.id} ${end.status}${end.error ? ': ' + end.error : ''}`, true); return; }
  await refreshModels();
  await selectModel(end.model_id);
}

/** The camera moved (moving: a drag, wheel or key still going on). */
function changed(moving = true) {
  // A splats model is drawn by the browser: its own controls move it.
  if (!viewer.model || isSplats(viewer.model)) return;
  const now = performance.now();
  if (moving && !viewer.moving) viewer.movedAt = now;
  viewer.moving = moving;
  viewer.lastMove = now;
  viewer.dirty = true;
  updateLink();
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
  if (isSplats(viewer.model)) return;
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

export function setupViewer() {
  const stage = $('stage');
  // A splats model's canvas has its own controls (splats.js).
  const drawnHere = () => viewer.model && isSplats(viewer.model);
  stage.addEventListener('pointerdown', (e) => {
    if (drawnHere()) return;
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
  stage.addEventListener('wheel', (e) => { if (drawnHere()) return; e.preventDefault(); zoomBy(Math.exp(e.deltaY * 0.001)); }, { passive: false });
  stage.addEventListener('dblclick', (e) => {
    const r = $('view-img').getBoundingClientRect();
    recentre(e.clientX - r.left, e.clientY - r.top).catch(fail);
  });
  stage.addEventListener('keydown', (e) => {
    if (drawnHere()) return;
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
  $('view-model').addEventListener('change', (e) => selectModel(e.target.value).catch(fail));
  $('view-bake').addEventListener('click', () => bakeShown().catch(fail));
  $('view-link').addEventListener('click', (e) => { e.preventDefault(); navigator.clipboard?.writeText(location.href.split('#')[0] + viewLink()).catch(() => {}); status('link to this view copied (and in the address bar)'); });
  $('view-output').addEventListener('change', () => changed(false));
  $('view-reset').addEventListener('click', () => resetView());
  $('view-export-go').addEventListener('click', () => downloadSplats().catch(fail));
  $('view-mesh').addEventListener('click', () => showMesh(viewer.model).catch(fail));
  $('mesh-close').addEventListener('click', () => closeMesh());
  $('mesh-site').addEventListener('click', () => downloadSite().catch(fail));
  $('crop-edit').addEventListener('click', () => editCrop().catch(fail));
  $('crop-mode').addEventListener('change', (e) => cropEditor?.setMode(e.target.value));
  for (const what of ['auto', 'save', 'remove', 'close']) {
    $(`crop-${what}`).addEventListener('click', () => cropAction(what).catch(fail));
  }
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

/** Whether a model is being opened (the list's refresh then selects none). */
let opening = false;

export async function openViewer(modelId, camera) {
  opening = true;
  try {
    showTab('viewer');
    await refreshModels();
    await selectModel(modelId, camera);
  } finally {
    opening = false;
  }
  (isSplats(viewer.model) ? $('view-splats') : $('stage')).focus();
}

/** Opens the model a link names (`#/models/ID?...`), if any; true if it did. */
export function openFromLink() {
  const link = parseLink(location.hash);
  if (!link) return false;
  openViewer(link.id, link.camera).catch(fail);
  return true;
}
