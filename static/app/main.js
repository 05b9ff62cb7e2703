// The viewer page: reads ?asset=ID (with ?share=TOKEN, a share link's token, for a viewer with
// no API key), ?compare=ID, ?sequence=URL, ?live=STREAM_ID and ?backend=webgl2,
// wires the panels, and publishes its state for automation:
//   document.body.dataset.state = loading | ready (first frames drawn) | error
//   window.viewerStats = {backend, triangles, bytes, decodeMs, firstRenderMs, ...}
//   (with ?live: viewerStats.live = {state, frameIndex, points, updates, rate, ageMs, closed})
import { Viewer, boundsOf, makeGltfLoader, parseGLB } from './render.js';
import { API, ApiError, apiFetch, apiKey, fetchBytes, recentJobs, setApiKey } from './api.js';
import { BANDS, HEAT_STOPS, QualityView, formatBytes, renderReport, rigFrusta } from './quality.js';
import { bindUpload } from './upload.js';
import { SequencePlayer, bindSequenceControls } from './sequence.js';
import { listLiveStreams, start as startLive } from './live.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const stats = { backend: null, triangles: 0, bytes: 0, decodeMs: 0, loadMs: 0, firstRenderMs: null };
window.viewerStats = stats;
document.body.dataset.state = 'loading';

const share = params.get('share');
// A share token opens the shared asset only; others (a comparison) need the viewer's own key.
const assetPath = (id, file = '') => `${API}/assets/${encodeURIComponent(id)}${file}`
  + (share && id === params.get('asset') ? `?share=${encodeURIComponent(share)}` : '');
const meshUrl = (id) => assetPath(id, '/mesh.glb');
const reportUrl = (id) => assetPath(id, '/report.json');

async function fetchReport(id) {
  try {
    return JSON.parse(new TextDecoder().decode(await fetchBytes(reportUrl(id))));
  } catch {
    return null; // an asset without a (readable) report still shows
  }
}

// Download and decode start before the GPU device is up, so the two overlap.
const loader = makeGltfLoader();
const assetId = params.get('asset');
const early = assetId ? loadAsset(assetId, window.volumeshMeshResponse) : null;
let meshParsed = false;
early?.parsed.then(() => { meshParsed = true; }, () => {}); // errors are handled where awaited

function loadAsset(id, started = null) {
  const since = started ? window.volumeshMeshStart : performance.now();
  const mesh = fetchBytes(meshUrl(id), started);
  const parsed = mesh.then((bytes) => parseGLB(loader, bytes)).then((result) => {
    result.loadMs = performance.now() - since; // download and decode
    return result;
  });
  return { mesh, parsed, report: fetchReport(id) };
}

export function showMessage(text, kind = 'error') {
  const box = $('message');
  box.textContent = text || '';
  box.dataset.kind = kind;
  box.hidden = !text;
}

function showStats() {
  $('stat-backend').textContent = stats.backend === 'webgpu' ? 'WebGPU' : 'WebGL2 (no WebGPU adapter)';
  $('stat-triangles').textContent = stats.triangles ? Math.round(stats.triangles).toLocaleString('en') : '–';
  $('stat-bytes').textContent = stats.bytes ? formatBytes(stats.bytes) : '–';
  $('stat-decode').textContent = stats.decodeMs
    ? `${(stats.loadMs || stats.decodeMs).toFixed(0)} ms (decode ${stats.decodeMs.toFixed(0)} ms)` : '–';
  $('stat-first').textContent = stats.firstRenderMs ? `${stats.firstRenderMs.toFixed(0)} ms` : '–';
}

class Page {
  constructor(viewer) {
    this.viewer = viewer;
    this.quality = new QualityView(viewer);
    this.primary = null; // parsed glTF shown as "enhanced"
    this.compare = null; // parsed glTF shown as "raw"
    this.frusta = null;
  }

  async showAsset(id, loading = loadAsset(id)) {
    const [bytes, parsed, report] = await Promise.all([loading.mesh, loading.parsed, loading.report]);
    this.quality.adopt(parsed.meshes);
    if (this.primary) this.quality.forget(this.primary.meshes);
    this.primary = parsed;
    this._dropCompare();
    this.viewer.setLayer('primary', parsed.root);
    $('hint').hidden = true;
    Object.assign(stats, {
      triangles: parsed.triangles, bytes: bytes.byteLength, decodeMs: parsed.decodeMs, loadMs: parsed.loadMs,
    });
    this.viewer.fitToView(boundsOf(parsed.root));
    this.assetId = id;
    $('share-section').hidden = !apiKey(); // a share link is made with the owner's key
    $('share-url').hidden = true;
    this.report = report;
    renderReport($('report'), report);
    $('report-section').hidden = !report;
    this.frusta = rigFrusta(report);
    $('frusta').disabled = !this.frusta;
    this._showFrusta();
    this._refreshQualityControls();
    showStats();
  }

  /** Loads the "raw" side of the before/after comparison. */
  async loadCompare(url) {
    const parsed = await this.viewer.parseGLB(await fetchBytes(url));
    this.quality.adopt(parsed.meshes);
    this.compare = parsed;
    parsed.root.visible = false;
    this.viewer.setLayer('compare', parsed.root);
    this._refreshQualityControls();
  }

  _dropCompare() {
    if (!this.compare) return;
    this.quality.forget(this.compare.meshes);
    this.compare = null;
    this.viewer.setLayer('compare', null);
    $('compare-mode').value = 'enhanced';
    this.setCompareMode('enhanced');
  }

  /** Loads the raw side of the comparison when there is one (after the first frame). */
  discoverCompare(id) {
    rawMeshUrl(id, this.report)
      .then((url) => url && this.loadCompare(url))
      .catch((err) => showMessage(`comparison mesh: ${err.message}`));
  }

  setCompareMode(mode) {
    const { primary, compare, viewer } = this;
    if (!primary) return;
    viewer.split = null;
    primary.root.visible = mode !== 'raw' || !compare;
    if (compare) compare.root.visible = mode === 'raw';
    if (mode === 'split' && compare) {
      viewer.split = { left: compare.root, right: primary.root, fraction: Number($('split').value) };
    }
    $('split').hidden = !(mode === 'split' && compare);
    $('split-line').hidden = $('split').hidden;
    this._placeSplitLine();
    viewer.requestRender();
  }

  _placeSplitLine() {
    $('split-line').style.left = `${Number($('split').value) * 100}%`;
  }

  _showFrusta() {
    this.viewer.setLayer('frusta', $('frusta').checked ? this.frusta : null, { dispose: false });
  }

  _refreshQualityControls() {
    const errorOption = $('shading').querySelector('option[value="error"]');
    errorOption.disabled = !this.quality.hasError;
    if (this.quality.hasError) this.quality.fitErrorRange();
    $('compare-mode').disabled = !this.compare;
    this._legend();
  }

  _legend() {
    const legend = $('legend');
    legend.replaceChildren();
    if (this.quality.mode === 'bands') {
      for (const band of BANDS) {
        const item = document.createElement('span');
        item.className = 'swatch';
        item.style.setProperty('--swatch', band.colour);
        item.textContent = band.label;
        legend.appendChild(item);
      }
    } else if (this.quality.mode === 'error') {
      const bar = document.createElement('div');
      bar.className = 'heat';
      bar.style.background = `linear-gradient(to right, ${HEAT_STOPS.join(', ')})`;
      const top = (this.quality.maxErrorM.value * 1000).toPrecision(2);
      const labels = document.createElement('div');
      labels.className = 'heat-labels';
      labels.innerHTML = `<span>0 mm</span><span>distance to ground truth</span><span>≥ ${top} mm</span>`;
      legend.append(bar, labels);
    }
    legend.hidden = legend.childElementCount === 0;
  }

  bindControls() {
    $('shading').addEventListener('change', (e) => { this.quality.setMode(e.target.value); this._legend(); });
    $('wireframe').addEventListener('change', (e) => this.quality.setWireframe(e.target.checked));
    $('compare-mode').addEventListener('change', (e) => this.setCompareMode(e.target.value));
    $('split').addEventListener('input', () => this.setCompareMode('split'));
    $('frusta').addEventListener('change', () => {
      this._showFrusta();
      if (!this.primary) return;
      // Frame the rig with the mesh while it is shown, the mesh alone otherwise.
      const box = boundsOf(this.primary.root);
      if ($('frusta').checked && this.frusta) box.union(boundsOf(this.frusta));
      this.viewer.fitToView(box);
    });
    $('share').addEventListener('click', () => this.share().catch((err) => showMessage(err.message)));
    $('api-key').value = apiKey();
    $('api-key-form').addEventListener('submit', (e) => {
      e.preventDefault();
      setApiKey($('api-key').value.trim());
      this.refreshJobs();
      listLiveStreams($('streams'), $('streams-section'));
    });
  }

  /** Makes a share link of the asset shown (POST /assets/{id}/share) and copies it. */
  async share() {
    const link = await apiFetch(`assets/${encodeURIComponent(this.assetId)}/share`, { method: 'POST', json: {} });
    const url = new URL(link.viewer_url, location.href).href;
    $('share-url').value = url;
    $('share-url').hidden = false;
    $('share-url').select();
    await navigator.clipboard?.writeText(url).catch(() => {}); // the field shows it either way
  }

  async refreshJobs() {
    const list = $('jobs');
    if (!apiKey()) {
      list.textContent = 'Enter an API key below to see your jobs.';
      return;
    }
    try {
      const jobs = await recentJobs(10);
      list.replaceChildren(...jobs.map(jobItem));
      if (jobs.length === 0) list.textContent = 'No jobs yet.';
    } catch (err) {
      list.textContent = err instanceof ApiError ? err.message : String(err);
    }
  }
}

// The "raw" (before enhancement) side of the comparison: ?compare=ASSET_ID, the report's
// raw_asset_id, or a mesh_raw.glb among the asset's files; null when there is none.
async function rawMeshUrl(id, report) {
  const compareId = params.get('compare') || report?.raw_asset_id;
  if (compareId) return meshUrl(compareId);
  const asset = await apiFetch(assetPath(id));
  return asset?.files?.['mesh_raw.glb']?.url ?? null;
}

function jobItem(job) {
  const item = document.createElement('li');
  // A job's mesh opens in the viewer, a sequence plays; a job that only calibrated links to its
  // rig file.
  const href = job.links?.viewer ?? (job.asset_id ? `/?asset=${encodeURIComponent(job.asset_id)}` : job.links?.rig ?? null);
  const name = href ? document.createElement('a') : document.createElement('span');
  if (href) name.href = href;
  name.textContent = String(job.id).slice(0, 12);
  const state = document.createElement('span');
  state.className = `job-state job-${job.state}`;
  const frames = job.frames_total ? ` (${job.frames_done}/${job.frames_total} frames${job.frames_failed ? `, ${job.frames_failed} failed` : ''})` : '';
  state.textContent = (job.state === 'running' && job.stage ? `${job.stage} ${Math.round((job.progress || 0) * 100)} %` : job.state) + frames;
  item.append(name, ' ', state);
  return item;
}

async function main() {
  performance.mark('vm:main');
  const viewer = await Viewer.create($('viewport'), { backend: params.get('backend'), loader });
  performance.mark('vm:renderer');
  stats.backend = viewer.backend;
  showStats();
  const page = new Page(viewer);
  // While the mesh still decodes, a one-pixel draw of its layout (our meshes carry vertex
  // colours) compiles the shaders; once it is decoded, drawing it at once is quicker.
  const warm = assetId && !meshParsed
    ? viewer.warmUp(page.quality.materialFor({ hasColour: true })).catch(() => {}) : null;
  window.volumesh = { viewer, page }; // for the console and for later modules (live preview)
  page.bindControls();
  bindUpload({
    dropTarget: document.body, input: $('file'), enhance: $('enhance'), bar: $('upload-progress'), label: $('upload-label'),
    onAsset: async (id) => {
      showMessage('');
      history.replaceState(null, '', `/?asset=${encodeURIComponent(id)}`);
      await page.showAsset(id);
      page.refreshJobs();
      await viewer.drawn();
      page.discoverCompare(id);
    },
    onError: (err) => showMessage(err.message),
    onJobChange: (job) => {
      const updates = (stats.job?.id === job.id ? stats.job.updates : 0) + 1;
      stats.job = { id: job.id, state: job.state, stage: job.stage, progress: job.progress, updates };
    },
  });
  page.refreshJobs();

  const sequenceUrl = params.get('sequence');
  const liveId = params.get('live');
  if (assetId) {
    await warm;
    await page.showAsset(assetId, early);
  } else if (sequenceUrl) {
    const player = new SequencePlayer(viewer, page.quality, { onError: (err) => showMessage(err.message) });
    const first = await player.load(sequenceUrl);
    Object.assign(stats, { triangles: first.triangles, decodeMs: first.decodeMs });
    window.volumesh.player = player;
    bindSequenceControls(player, {
      bar: $('sequence-bar'), playButton: $('play'), scrub: $('scrub'), loopBox: $('loop'), label: $('frame-label'),
      onUpdate: (p) => {
        stats.sequence = { frames: p.frameCount, current: p.current, playing: p.playing, shown: p.shown, stalls: p.stalls };
      },
    });
    showStats();
  } else if (liveId) {
    await startLive({
      viewer, streamId: liveId, showMessage, bar: $('live-bar'), status: $('live-status'),
      onJob: () => page.refreshJobs(),
    });
  } else {
    $('hint').hidden = false;
  }
  await viewer.drawn();
  stats.firstRenderMs = performance.now(); // since navigation start
  showStats();
  document.body.dataset.state = 'ready';
  listLiveStreams($('streams'), $('streams-section')); // after the first frame: off its path
  if (assetId) page.discoverCompare(assetId);
}

main().catch((err) => {
  document.body.dataset.state = 'error';
  showMessage(err.message || String(err));
});
