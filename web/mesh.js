// The mesh panel: a model of any kind as a textured mesh, made by the server
// (`/v1/models/{id}/mesh`: tens of seconds the first time, while the server
// answers 202 with its progress; kept after) and
// shown in Google's <model-viewer> (vendored, loaded when first needed) with
// its AR button: the GLB for the page, WebXR and Android's Scene Viewer, the
// USDZ for AR Quick Look on iPhone and iPad. Both can be downloaded, and a
// static web site showing the mesh (a zip). The
// files come with the API key, so they are shown from object URLs.
// `#mesh-panel`'s `data-state` says where it is (`making`, `shown`,
// `failed`), for people's scripts and the browser tests.

import { api } from './api.js';
import { $, el, fail, fmtBytes } from './ui.js';

let library = null;
/** What is shown: the model's id, its object URLs, the fetch to stop. */
let shown = null;

const sleep = (ms, signal) => new Promise((resolve, reject) => {
  const t = setTimeout(resolve, ms);
  signal.addEventListener('abort', () => { clearTimeout(t); reject(new DOMException('stopped', 'AbortError')); }, { once: true });
});

/**
 * The mesh as `format`: while the server makes it (202, its progress),
 * asks again as it says, telling `onProgress`.
 */
async function fetchMesh(id, format, signal, onProgress = () => {}) {
  let res;
  for (;;) {
    res = await api(`/v1/models/${id}/mesh?format=${format}`, { signal });
    if (res.status !== 202) break;
    onProgress(await res.json());
    await sleep(1000 * Number(res.headers.get('retry-after') || 2), signal);
  }
  const name = /filename="([^"]+)"/.exec(res.headers.get('content-disposition') || '')?.[1] || `${id}.${format}`;
  const blob = await res.blob();
  return { name, blob, url: URL.createObjectURL(blob), triangles: Number(res.headers.get('x-triangles')) };
}

function offer(linkId, file) {
  const a = $(linkId);
  Object.assign(a, { href: file.url, download: file.name, hidden: false });
  a.title = `${file.name}, ${fmtBytes(file.blob.size)}`;
}

/** Makes (or fetches) `model`'s mesh and shows it. */
export async function showMesh(model) {
  closeMesh();
  const mine = { id: model.id, urls: [], controller: new AbortController() };
  shown = mine;
  const panel = $('mesh-panel');
  const state = $('mesh-state');
  panel.hidden = false;
  panel.dataset.state = 'making';
  panel.scrollIntoView({ block: 'nearest' });
  const t0 = performance.now();
  const secs = () => ((performance.now() - t0) / 1000).toFixed(0);
  let doing = 'starting';
  const say = () => { state.textContent = `making the mesh: ${doing}, ${secs()} s (about a minute on two cores the first time)`; };
  say();
  const tick = setInterval(say, 1000);
  const onProgress = (p) => { doing = `${p.stage} (${Math.round(100 * p.progress)}%)`; say(); };
  try {
    library ??= import('/assets/vendor/model-viewer/model-viewer.min.js');
    await library;
    const glb = await fetchMesh(model.id, 'glb', mine.controller.signal, onProgress);
    mine.urls.push(glb.url);
    if (shown !== mine) return;
    const view = $('mesh-view');
    const drawn = new Promise((resolve, reject) => {
      view.addEventListener('load', resolve, { once: true });
      view.addEventListener('error', (e) => reject(new Error(`the mesh did not load: ${e.detail?.type ?? 'error'}`)), { once: true });
    });
    view.src = glb.url;
    await drawn;
    clearInterval(tick);
    offer('mesh-glb', glb);
    state.textContent = `${glb.triangles.toLocaleString('en')} triangles, ${fmtBytes(glb.blob.size)} as GLB, ready in ${secs()} s; the USDZ for iPhone AR follows`;
    panel.dataset.state = 'shown';
    // From the mesh just made (the server keeps it): quick.
    const usdz = await fetchMesh(model.id, 'usdz', mine.controller.signal);
    mine.urls.push(usdz.url);
    if (shown !== mine) return;
    view.setAttribute('ios-src', usdz.url);
    offer('mesh-usdz', usdz);
    $('mesh-site').hidden = false;
    state.textContent = `${glb.triangles.toLocaleString('en')} triangles: ${fmtBytes(glb.blob.size)} as GLB, ${fmtBytes(usdz.blob.size)} as USDZ`;
  } catch (e) {
    if (shown === mine && e.name !== 'AbortError') {
      panel.dataset.state = 'failed';
      state.textContent = `no mesh: ${e.message}`;
    }
    fail(e);
  } finally {
    clearInterval(tick);
  }
}

/** Downloads the shown mesh as a static web site (a zip). */
export async function downloadSite() {
  if (!shown) return;
  const site = await fetchMesh(shown.id, 'html', shown.controller.signal);
  const a = el('a', { href: site.url, download: site.name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(site.url), 60000);
  $('mesh-site').dataset.file = site.name;
}

/** Hides the panel, stops what it was fetching, frees its files. */
export function closeMesh() {
  if (!shown) return;
  shown.controller.abort();
  for (const u of shown.urls) URL.revokeObjectURL(u);
  shown = null;
  const view = $('mesh-view');
  view.removeAttribute('src');
  view.removeAttribute('ios-src');
  for (const id of ['mesh-glb', 'mesh-usdz', 'mesh-site']) $(id).hidden = true;
  $('mesh-panel').hidden = true;
  delete $('mesh-panel').dataset.state;
}
