// Volumetric video: plays a sequence manifest {version, fps, bounds: {min, max}, frames: [{url}]}
// (schema: SequenceManifest in the gateway's OpenAPI document). Frames are GLB files fetched
// ahead of the play head, so playback waits only when the network or decoder cannot keep up.
import { fetchBytes } from './api.js';
import { THREE } from './render.js';

export function parseManifest(doc, manifestUrl) {
  const fail = (why) => { throw new Error(`sequence manifest ${manifestUrl}: ${why}`); };
  if (!doc || typeof doc !== 'object') fail('is not a JSON object');
  if (!(typeof doc.fps === 'number' && doc.fps > 0 && doc.fps <= 240)) fail('fps must be a number in (0, 240]');
  const triple = (v) => Array.isArray(v) && v.length === 3 && v.every(Number.isFinite);
  if (!doc.bounds || !triple(doc.bounds.min) || !triple(doc.bounds.max)) fail('bounds needs min and max, three numbers each');
  if (!Array.isArray(doc.frames) || doc.frames.length === 0) fail('frames must be a non-empty list');
  const base = new URL(manifestUrl, location.href);
  // A manifest opened through a share link (?share=TOKEN) passes the token on to its frames on
  // the same server: the gateway's token of a sequence also opens the assets of its frames.
  const share = base.searchParams.get('share');
  const urls = doc.frames.map((frame, i) => {
    if (!frame || typeof frame.url !== 'string' || !frame.url) fail(`frames[${i}].url is missing`);
    const url = new URL(frame.url, base);
    if (share && url.origin === base.origin && !url.searchParams.has('share')) url.searchParams.set('share', share);
    return url.href;
  });
  const bounds = new THREE.Box3(new THREE.Vector3(...doc.bounds.min), new THREE.Vector3(...doc.bounds.max));
  return { fps: doc.fps, bounds, urls };
}

export class SequencePlayer {
  constructor(viewer, quality, { prefetch = 6, onFrame = () => {}, onError = () => {} } = {}) {
    this.viewer = viewer;
    this.quality = quality;
    this.prefetch = prefetch;
    this.onFrame = onFrame;
    this.onError = onError;
    this.cache = new Map(); // frame index -> Promise<parsed glTF>
    this.loaded = new Map(); // frame index -> parsed glTF, once decoded
    this.current = -1;
    this.playing = false;
    this.loop = true;
    this.stalls = 0; // times the play head waited for a frame still loading
    this.shown = 0; // frames shown so far
    this._tick = this._tick.bind(this);
  }

  get frameCount() { return this.manifest ? this.manifest.urls.length : 0; }

  /** Loads the manifest and shows frame 0; resolves with that frame's parsed glTF. */
  async load(manifestUrl) {
    const bytes = await fetchBytes(manifestUrl);
    let doc;
    try {
      doc = JSON.parse(new TextDecoder().decode(bytes));
    } catch {
      throw new Error(`sequence manifest ${manifestUrl} is not JSON`);
    }
    this.manifest = parseManifest(doc, manifestUrl);
    this.viewer.fitToView(this.manifest.bounds); // once: the view must not jump between frames
    const first = await this._ensure(0);
    this._show(0);
    return first;
  }

  play() {
    if (this.playing || !this.manifest) return;
    if (!this.loop && this.current === this.frameCount - 1) this._show(0);
    this.playing = true;
    this._clockStart = performance.now() - (this.current / this.manifest.fps) * 1000;
    requestAnimationFrame(this._tick);
  }

  pause() { this.playing = false; }

  /** Shows frame `index` as soon as it is decoded (scrubbing). */
  async seek(index) {
    const i = Math.max(0, Math.min(this.frameCount - 1, Math.round(index)));
    await this._ensure(i);
    this._show(i);
    if (this.playing) this._clockStart = performance.now() - (i / this.manifest.fps) * 1000;
  }

  _tick(now) {
    if (!this.playing) return;
    const n = this.frameCount;
    // rAF's timestamp can precede the performance.now() that play() read: never below 0.
    let target = Math.max(0, Math.floor(((now - this._clockStart) / 1000) * this.manifest.fps));
    if (target >= n) {
      if (!this.loop) {
        this._show(n - 1);
        this.playing = false;
        this.onFrame(this);
        return;
      }
      target %= n;
      this._clockStart = now - (target / this.manifest.fps) * 1000;
    }
    if (target !== this.current) {
      if (this.loaded.has(target)) {
        this._show(target);
      } else {
        // Not decoded yet: hold the clock on the current frame instead of skipping frames.
        this.stalls += 1;
        this._clockStart = now - (this.current / this.manifest.fps) * 1000;
        this._ensure(target);
        this.onFrame(this);
      }
    }
    requestAnimationFrame(this._tick);
  }

  _show(index) {
    const parsed = this.loaded.get(index);
    if (!parsed) return;
    this.current = index;
    this.shown += 1;
    this.viewer.setLayer('sequence', parsed.root, { dispose: false });
    this._prefetchFrom(index);
    this._evict(index);
    this.onFrame(this);
  }

  _ensure(index) {
    if (!(index >= 0 && index < this.frameCount)) throw new RangeError(`no frame ${index}`);
    if (!this.cache.has(index)) {
      const promise = fetchBytes(this.manifest.urls[index])
        .then((bytes) => this.viewer.parseGLB(bytes))
        .then((parsed) => {
          if (this.cache.get(index) !== promise) { // evicted while loading
            parsed.root.traverse((node) => node.geometry?.dispose());
            return parsed;
          }
          this.quality.adopt(parsed.meshes);
          this.loaded.set(index, parsed);
          return parsed;
        });
      promise.catch((err) => {
        this.cache.delete(index);
        this.pause();
        this.onError(new Error(`frame ${index}: ${err.message}`));
      });
      this.cache.set(index, promise);
    }
    return this.cache.get(index);
  }

  _window(index) {
    const keep = new Set([index]);
    for (let k = 1; k <= this.prefetch; k += 1) {
      const next = index + k;
      if (next < this.frameCount) keep.add(next);
      else if (this.loop) keep.add(next % this.frameCount);
    }
    return keep;
  }

  _prefetchFrom(index) {
    for (const i of this._window(index)) this._ensure(i);
  }

  _evict(index) {
    const keep = this._window(index);
    for (const i of [...this.cache.keys()]) {
      if (keep.has(i)) continue;
      const parsed = this.loaded.get(i);
      this.cache.delete(i);
      this.loaded.delete(i);
      if (parsed) {
        this.quality.forget(parsed.meshes);
        parsed.root.traverse((node) => node.geometry?.dispose());
      }
    }
  }
}

/** Wires the play/pause button, scrub slider, loop box and frame label to a player. */
export function bindSequenceControls(player, { bar, playButton, scrub, loopBox, label, onUpdate = () => {} }) {
  bar.hidden = false;
  scrub.max = String(player.frameCount - 1);
  loopBox.checked = player.loop;
  const update = () => {
    scrub.value = String(player.current);
    label.textContent = `${player.current + 1} / ${player.frameCount}`;
    playButton.textContent = player.playing ? 'Pause' : 'Play';
    playButton.setAttribute('aria-pressed', String(player.playing));
    onUpdate(player);
  };
  player.onFrame = update;
  playButton.addEventListener('click', () => {
    if (player.playing) player.pause();
    else player.play();
    update();
  });
  scrub.addEventListener('input', () => player.seek(Number(scrub.value)));
  loopBox.addEventListener('change', () => { player.loop = loopBox.checked; });
  update();
}
