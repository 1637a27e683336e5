// What every page of the web app shares: element lookup and creation, the
// status line, number formats, and the tabs (each page registers what to
// refresh when its tab is shown).

import { ApiError } from './api.js';

export const $ = (id) => document.getElementById(id);

export function status(message, isError = false) {
  const s = $('status');
  s.textContent = message;
  s.classList.toggle('error', isError);
}

export function fail(e) {
  if (e && e.name === 'AbortError') return;
  status(e instanceof ApiError ? e.message : String(e), true);
}

export const fmtSecs = (s) => (s == null || !isFinite(s) ? '?' : s < 60 ? `${s.toFixed(0)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`);
/**
 * A bake job's progress in a line: its status, the step (of the steps
 * asked for), the time spent and left, the Gaussians so far and, once
 * measured, the held-out PSNR.
 */
export function bakeLine(j) {
  const p = j.progress;
  const running = j.status === 'running';
  return `${j.status} · step ${p.step}${p.total_steps ? ' / ' + p.total_steps : ''}` +
    (p.elapsed ? ` · ${fmtSecs(p.elapsed)} baked` : '') + (running && p.eta != null ? ` · ETA ${fmtSecs(p.eta)}` : '') +
    (p.gaussians ? ` · ${p.gaussians.toLocaleString('en')} Gaussians` : '') +
    (p.test_psnr != null ? ` · held-out PSNR ${p.test_psnr.toFixed(2)} dB` : '') + (j.error ? ` · ${j.error}` : '');
}

export const fmtBytes = (b) => (b > 1 << 20 ? `${(b / 1048576).toFixed(1)} MiB` : `${Math.ceil(b / 1024)} KiB`);

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null) e.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

export const TABS = ['scenes', 'training', 'viewer', 'videos'];
const onShow = {};

/** What to refresh when `name`'s tab is shown. */
export function whenShown(name, refresh) {
  onShow[name] = refresh;
}

export function showTab(name) {
  for (const t of TABS) {
    $(t).hidden = t !== name;
    $('tab-' + t).setAttribute('aria-selected', String(t === name));
  }
  if (onShow[name]) onShow[name]();
}
