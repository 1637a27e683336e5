// radiance web app: plain JavaScript modules, no framework, no build step.
// It uses the service's REST API like any client (api.js): scenes
// (scenes.js), jobs followed over their Server-Sent Events (training.js),
// renders (viewer.js) and videos (videos.js). Images and videos are fetched
// with the API key (when the server has one) and shown from object URLs.

import { refreshScenes, setupScenes } from './scenes.js';
import { refreshJobs, setupTraining } from './training.js';
import { $, TABS, fail, showTab, whenShown } from './ui.js';
import { refreshVideos, setupVideos } from './videos.js';
import { openFromLink, refreshModels, setupViewer } from './viewer.js';

function start() {
  whenShown('scenes', () => refreshScenes().catch(fail));
  whenShown('training', () => refreshJobs().catch(fail));
  whenShown('viewer', () => refreshModels().catch(fail));
  whenShown('videos', () => { refreshModels().catch(fail); refreshVideos().catch(fail); });
  for (const t of TABS) $('tab-' + t).addEventListener('click', () => showTab(t));
  setupScenes();
  setupTraining();
  setupViewer();
  setupVideos();
  // A link to a model's view (`#/models/ID?...`) opens it there.
  if (!openFromLink()) showTab('scenes');
  document.body.dataset.ready = 'true';
}

start();
