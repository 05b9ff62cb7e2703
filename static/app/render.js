// The 3D view: a three.js WebGPURenderer (WebGL2 backend when no WebGPU adapter), Draco glTF
// loading, orbit controls, fit-to-view, lights and named layers. Frames are drawn on demand
// (after a change), not continuously: software rasterisers and laptops both thank us.
import * as THREE from 'three/webgpu';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { DRACOLoader } from 'three/addons/loaders/DRACOLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

export { THREE };

const DRACO_DECODER_PATH = '/vendor/three/examples/jsm/libs/draco/';
export const BACKGROUND = new THREE.Color(0x1d2026);

// 'webgpu' when an adapter is there (and not overridden by ?backend=webgl2), else 'webgl2';
// `software` when the rasteriser is a CPU one (SwiftShader, llvmpipe, a fallback adapter).
async function chooseBackend(requested) {
  if (requested !== 'webgl2' && navigator.gpu) {
    try {
      const adapter = await (window.volumeshAdapter || navigator.gpu.requestAdapter());
      if (adapter) {
        const info = adapter.info || {};
        const name = `${info.vendor} ${info.architecture} ${info.description}`;
        return { backend: 'webgpu', software: !!info.isFallbackAdapter || SOFTWARE.test(name) };
      }
    } catch { /* no WebGPU: WebGL2 below */ }
  }
  return { backend: 'webgl2', software: webglIsSoftware() };
}

const SOFTWARE = /swiftshader|llvmpipe|softpipe|software|basic render/i;

function webglIsSoftware() {
  const gl = document.createElement('canvas').getContext('webgl2');
  if (!gl) return false;
  const ext = gl.getExtension('WEBGL_debug_renderer_info');
  const name = gl.getParameter(ext ? ext.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
  gl.getExtension('WEBGL_lose_context')?.loseContext();
  return SOFTWARE.test(String(name));
}

/** A GLTFLoader with the Draco decoder, which starts fetching and compiling right away. */
export function makeGltfLoader() {
  const draco = new DRACOLoader();
  draco.setDecoderPath(DRACO_DECODER_PATH);
  draco.preload(); // the decoder compiles while the mesh downloads and the GPU starts
  const loader = new GLTFLoader();
  loader.setDRACOLoader(draco);
  return loader;
}

/**
 * Parses GLB bytes (Draco allowed) into {root, meshes, triangles, vertices, decodeMs}. Needs no
 * renderer, so it can run while the GPU device is being set up.
 */
export async function parseGLB(loader, bytes) {
  performance.mark('vm:parse-start');
  const start = performance.now();
  const gltf = await loader.parseAsync(bytes, '');
  const decodeMs = performance.now() - start;
  performance.mark('vm:parsed');
  const meshes = [];
  gltf.scene.traverse((node) => { if (node.isMesh) meshes.push(node); });
  if (meshes.length === 0) throw new Error('the glTF file holds no mesh');
  let triangles = 0;
  let vertices = 0;
  for (const mesh of meshes) {
    const geometry = mesh.geometry;
    vertices += geometry.attributes.position.count;
    triangles += (geometry.index ? geometry.index.count : geometry.attributes.position.count) / 3;
  }
  gltf.scene.updateMatrixWorld(true);
  return { root: gltf.scene, meshes, triangles, vertices, decodeMs };
}

export class Viewer {
  /** Creates the renderer inside `container` (a block element that it fills). */
  static async create(container, { backend: requested = null, loader = null } = {}) {
    const { backend, software } = await chooseBackend(requested);
    performance.mark('vm:backend-chosen');
    // Multisampling multiplies a CPU rasteriser's work by four: only on real GPUs.
    const renderer = new THREE.WebGPURenderer({ antialias: !software, forceWebGL: backend === 'webgl2' });
    renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    renderer.setClearColor(BACKGROUND, 1);
    container.appendChild(renderer.domElement);
    performance.mark('vm:init-start');
    await renderer.init();
    const actual = renderer.backend.isWebGPUBackend ? 'webgpu' : 'webgl2';
    const viewer = new Viewer(container, renderer, actual, loader || makeGltfLoader());
    viewer.software = software;
    return viewer;
  }

  constructor(container, renderer, backend, loader) {
    this.container = container;
    this.renderer = renderer;
    this.backend = backend;
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.camera.position.set(0, 1, 3);
    this.controls = new OrbitControls(this.camera, renderer.domElement);
    this.controls.addEventListener('change', () => this.requestRender());
    this.layers = new Map();
    this.split = null; // {left: Object3D, right: Object3D, fraction} while comparing
    this.beforeRender = []; // callbacks (camera) => void, e.g. view-dependent uniforms
    this._pending = false;
    this._addLights();
    this.gltfLoader = loader;
    new ResizeObserver(() => this._resize()).observe(container);
    this._resize();
  }

  _addLights() {
    this.scene.add(new THREE.HemisphereLight(0xf2f4ff, 0x3a3630, 1.4));
    // A headlight that follows the camera: every side the user turns to is lit.
    const key = new THREE.DirectionalLight(0xffffff, 1.6);
    key.position.set(0.4, 0.6, 1);
    this.camera.add(key);
    this.scene.add(this.camera);
  }

  _resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (w === 0 || h === 0) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  parseGLB(bytes) {
    return parseGLB(this.gltfLoader, bytes);
  }

  /** Puts `object` in the scene under `name`, replacing (and freeing) what was there. */
  setLayer(name, object, { dispose = true } = {}) {
    const old = this.layers.get(name);
    if (old && old !== object) {
      this.scene.remove(old);
      if (dispose) disposeTree(old);
    }
    if (object) {
      this.scene.add(object);
      this.layers.set(name, object);
    } else {
      this.layers.delete(name);
    }
    this.requestRender();
  }

  /** A point cloud layer (room for a live preview): positions (N*3, metres), colours (N*3 0..1). */
  setPointCloud(name, positions, colors = null, sizePx = 2) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
    if (colors) geometry.setAttribute('color', new THREE.BufferAttribute(colors, 3));
    const material = new THREE.PointsNodeMaterial({ size: sizePx, vertexColors: !!colors });
    this.setLayer(name, new THREE.Points(geometry, material));
  }

  /** Moves the camera so `box` (THREE.Box3, world) fills the view from the front, slightly above. */
  fitToView(box) {
    if (box.isEmpty()) return;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, 1e-3);
    const fov = THREE.MathUtils.degToRad(this.camera.fov);
    const fitFov = this.camera.aspect < 1 ? 2 * Math.atan(Math.tan(fov / 2) * this.camera.aspect) : fov;
    const distance = (radius / Math.sin(fitFov / 2)) * 1.05;
    const direction = new THREE.Vector3(0, 0.25, 1).normalize();
    this.camera.position.copy(sphere.center).addScaledVector(direction, distance);
    this.camera.near = Math.max(distance - radius * 2, distance / 1000);
    this.camera.far = distance + radius * 4;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(sphere.center);
    this.controls.update();
    this.requestRender();
  }

  /**
   * Draws one pixel of a triangle with POSITION, NORMAL and (when `colour`) 8-bit COLOR_0 in
   * `material`, the layout our meshes have. Run while the mesh still downloads and decodes, it
   * takes the pipeline compile off the first frame's path, and with it the shader JIT that a
   * software rasteriser (SwiftShader) does only when it first draws.
   */
  async warmUp(material, { colour = true } = {}) {
    performance.mark('vm:warm-start');
    const geometry = new THREE.BufferGeometry();
    // Camera-local, in front of the near plane and covering the view: the scissored pixel
    // is always inside it.
    const corners = new Float32Array([-100, -100, -1, 100, -100, -1, 0, 100, -1]);
    geometry.setAttribute('position', new THREE.BufferAttribute(corners, 3));
    geometry.setAttribute('normal', new THREE.BufferAttribute(new Float32Array([0, 0, 1, 0, 0, 1, 0, 0, 1]), 3));
    if (colour) geometry.setAttribute('color', new THREE.BufferAttribute(new Uint8Array(9).fill(29), 3, true));
    geometry.setIndex(new THREE.BufferAttribute(new Uint32Array([0, 1, 2]), 1));
    const probe = new THREE.Mesh(geometry, material);
    this.camera.add(probe);
    const r = this.renderer;
    r.setScissorTest(true);
    r.setScissor(0, 0, 1, 1);
    try {
      await r.compileAsync(this.scene, this.camera);
      r.render(this.scene, this.camera);
      await this._gpuDone();
    } finally {
      r.setScissorTest(false);
      this.camera.remove(probe);
      geometry.dispose();
    }
    performance.mark('vm:warm-done');
  }

  requestRender() {
    if (this._pending) return;
    this._pending = true;
    requestAnimationFrame(() => {
      this._pending = false;
      this.renderNow();
    });
  }

  renderNow() {
    for (const hook of this.beforeRender) hook(this.camera);
    if (!this.split) {
      this.renderer.render(this.scene, this.camera);
      return;
    }
    this._renderSplit();
  }

  // Left of the split line shows `split.left`, right shows `split.right`: two passes, the
  // second clipped by a scissor rectangle and keeping the first pass's colour.
  _renderSplit() {
    const { left, right, fraction } = this.split;
    const r = this.renderer;
    const size = r.getSize(new THREE.Vector2());
    const x = Math.round(size.x * fraction);
    left.visible = true;
    right.visible = false;
    r.render(this.scene, this.camera);
    left.visible = false;
    right.visible = true;
    r.autoClearColor = false;
    r.setScissorTest(true);
    r.setScissor(x, 0, size.x - x, size.y);
    r.render(this.scene, this.camera);
    r.setScissorTest(false);
    r.autoClearColor = true;
    left.visible = true;
  }

  /**
   * Renders `count` frames while orbiting once around the target, each waited on until the GPU
   * is done; resolves with the frame times in ms (for benchmarks: frames are on demand).
   */
  async measureFrames(count = 60) {
    const times = [];
    const target = this.controls.target.clone();
    const offset = this.camera.position.clone().sub(target);
    const up = new THREE.Vector3(0, 1, 0);
    for (let i = 0; i < count; i += 1) {
      await new Promise((resolve) => requestAnimationFrame(resolve));
      const start = performance.now();
      offset.applyAxisAngle(up, (2 * Math.PI) / count);
      this.camera.position.copy(target).add(offset);
      this.camera.lookAt(target);
      this.renderNow();
      await this._gpuDone();
      times.push(performance.now() - start);
    }
    this.controls.update();
    return times;
  }

  async _gpuDone() {
    const { device, gl } = this.renderer.backend;
    if (device) {
      await device.queue.onSubmittedWorkDone();
    } else if (gl) {
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4)); // waits for the GPU
    }
  }

  /** Resolves once a frame has been drawn and handed to the compositor. */
  async drawn() {
    performance.mark('vm:draw-start');
    this.renderNow();
    performance.mark('vm:draw-submitted');
    await this._gpuDone();
    await new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve)));
  }
}

export function disposeTree(root) {
  root.traverse((node) => {
    if (node.geometry) node.geometry.dispose();
  });
}

/** World-space bounding box of an object tree. */
export function boundsOf(object) {
  return new THREE.Box3().setFromObject(object);
}
