// Quality views: shading by colour, normals, normal-angle bands or per-vertex error; wireframe;
// raw vs enhanced (toggle or split); the camera rig as frusta; the report's figures.
import { THREE } from './render.js';
import {
  abs, attribute, clamp, color, dot, mix, normalView, normalWorld, normalize, positionViewDirection,
  uniform,
} from 'three/tsl';

// The paper's bands of the angle between surface normal and view direction.
export const BANDS = [
  { label: '0–30°', colour: '#2fa866', minCos: Math.cos(THREE.MathUtils.degToRad(30)) },
  { label: '31–60°', colour: '#e8c547', minCos: Math.cos(THREE.MathUtils.degToRad(60)) },
  { label: '61–90°', colour: '#d9534f', minCos: -1 },
];
export const HEAT_STOPS = ['#2b3dbd', '#27b0a0', '#f1d04b', '#d7301f'];
const ERROR_ATTRIBUTE = '_error_m'; // glTF custom attribute _ERROR_M, as GLTFLoader names it

// |cos| of the angle between the surface normal and the direction to the eye.
const facing = () => abs(dot(normalize(normalView), positionViewDirection));
// Flat false colours still show the shape when darkened a little at grazing angles.
const shaded = (node) => node.mul(facing().mul(0.45).add(0.55));

function bandColour() {
  const [b0, b1, b2] = BANDS;
  const cosA = facing();
  return cosA.greaterThanEqual(b0.minCos).select(color(b0.colour),
    cosA.greaterThanEqual(b1.minCos).select(color(b1.colour), color(b2.colour)));
}

// Piecewise-linear ramp through HEAT_STOPS for t in [0, 1], branch-free.
function heatColour(t) {
  const stops = HEAT_STOPS.map((hex) => color(hex));
  const segments = stops.length - 1;
  let node = stops[0];
  for (let i = 1; i <= segments; i += 1) {
    node = mix(node, stops[i], clamp(t.mul(segments).sub(i - 1), 0, 1));
  }
  return node;
}

export class QualityView {
  constructor(viewer) {
    this.viewer = viewer;
    this.mode = 'colour';
    this.wireframe = false;
    this.maxErrorM = uniform(0.005);
    this.materials = new Map();
    this.meshes = new Set();
  }

  /** Takes over the meshes of a loaded glTF: our materials, their flags in userData. */
  adopt(meshes) {
    for (const mesh of meshes) {
      const attributes = mesh.geometry.attributes;
      mesh.userData.hasColour = 'color' in attributes;
      mesh.userData.hasError = ERROR_ATTRIBUTE in attributes;
      const previous = Array.isArray(mesh.material) ? mesh.material : [mesh.material];
      for (const material of previous) material.dispose();
      this.meshes.add(mesh);
      mesh.material = this._materialFor(mesh);
    }
  }

  forget(meshes) {
    for (const mesh of meshes) this.meshes.delete(mesh);
  }

  /** True when some shown mesh carries per-vertex ground-truth error. */
  get hasError() {
    for (const mesh of this.meshes) if (mesh.userData.hasError) return true;
    return false;
  }

  setMode(mode) {
    if (!['colour', 'normals', 'bands', 'error'].includes(mode)) throw new Error(`unknown shading ${mode}`);
    this.mode = mode;
    this._apply();
  }

  setWireframe(on) {
    this.wireframe = !!on;
    this._apply();
  }

  /** Sets the heat map's top from the errors of the shown meshes (their 95th percentile). */
  fitErrorRange() {
    const values = [];
    for (const mesh of this.meshes) {
      const attr = mesh.geometry.attributes[ERROR_ATTRIBUTE];
      if (attr) for (let i = 0; i < attr.count; i += 1) values.push(Math.abs(attr.getX(i)));
    }
    if (values.length === 0) return null;
    values.sort((a, b) => a - b);
    const top = Math.max(values[Math.floor(0.95 * (values.length - 1))], 1e-5);
    this.maxErrorM.value = top;
    return top;
  }

  _apply() {
    for (const mesh of this.meshes) mesh.material = this._materialFor(mesh);
    this.viewer.requestRender();
  }

  /** The material a glTF mesh with (or without) vertex colours gets in the current mode. */
  materialFor({ hasColour = true, hasError = false } = {}) {
    return this._materialFor({ userData: { hasColour, hasError } });
  }

  _materialFor(mesh) {
    let mode = this.mode;
    if (mode === 'error' && !mesh.userData.hasError) mode = 'colour';
    const vertexColors = mode === 'colour' && mesh.userData.hasColour;
    const key = `${mode}|${vertexColors}|${this.wireframe}`;
    if (!this.materials.has(key)) this.materials.set(key, this._build(mode, vertexColors));
    return this.materials.get(key);
  }

  _build(mode, vertexColors) {
    const common = { side: THREE.DoubleSide, wireframe: this.wireframe };
    if (mode === 'colour') {
      const colour = { ...common, color: vertexColors ? 0xffffff : 0xb9bec7, vertexColors };
      // A CPU rasteriser compiles and runs every shader on the CPU: Lambert costs a fraction
      // of the physically based shader and looks alike on a matte scan.
      if (this.viewer.software) return new THREE.MeshLambertNodeMaterial(colour);
      // Neutral: no metal (glTF's default metallic 1 renders scans dark), matte.
      return new THREE.MeshStandardNodeMaterial({ ...colour, metalness: 0, roughness: 0.8 });
    }
    const material = new THREE.MeshBasicNodeMaterial(common);
    if (mode === 'normals') material.colorNode = normalize(normalWorld).mul(0.5).add(0.5);
    if (mode === 'bands') material.colorNode = shaded(bandColour());
    if (mode === 'error') {
      const error = abs(attribute(ERROR_ATTRIBUTE, 'float'));
      material.colorNode = shaded(heatColour(clamp(error.div(this.maxErrorM), 0, 1)));
    }
    return material;
  }
}

/** The camera rig as frusta (LineSegments, world frame), or null when the report has none. */
export function rigFrusta(report, depthM = 0.25) {
  const cameras = rigCameras(report);
  if (cameras.length === 0) return null;
  const points = [];
  for (const cam of cameras) {
    const m = new THREE.Matrix4().fromArray(cam.worldFromDepth.flat()).transpose(); // rows -> column-major
    // OpenCV camera frame: x right, y down, z forward; corners at depth depthM.
    const corners = [[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]].map(([u, v]) =>
      new THREE.Vector3(((u - cam.cx) / cam.fx) * depthM, ((v - cam.cy) / cam.fy) * depthM, depthM).applyMatrix4(m));
    const eye = new THREE.Vector3().applyMatrix4(m);
    for (let i = 0; i < 4; i += 1) points.push(eye, corners[i], corners[i], corners[(i + 1) % 4]);
  }
  const geometry = new THREE.BufferGeometry().setFromPoints(points);
  return new THREE.LineSegments(geometry, new THREE.LineBasicNodeMaterial({ color: 0x7fb4ff }));
}

// Accepts rig.json's shape ({world_from_depth: {id: 4x4}}) under `rig`, at the top or in the
// job's `options`, or a `cameras` list with world_from_depth and depth_intrinsics
// (capture.json's shape).
function rigCameras(report) {
  if (!report || typeof report !== 'object') return [];
  const fallback = { width: 640, height: 576, fx: 504, fy: 504, cx: 320, cy: 288 }; // ~75°x65°
  const found = [];
  const poses = report.rig?.world_from_depth ?? report.world_from_depth ?? report.options?.world_from_depth;
  if (poses && typeof poses === 'object') {
    for (const [id, pose] of Object.entries(poses)) found.push({ id, pose, intr: report.rig?.intrinsics?.[id] });
  } else if (Array.isArray(report.cameras)) {
    for (const cam of report.cameras) found.push({ id: cam.id, pose: cam.world_from_depth, intr: cam.depth_intrinsics });
  }
  return found
    .filter(({ pose }) => Array.isArray(pose) && pose.length === 4 && pose.every((row) => row.length === 4))
    .map(({ id, pose, intr }) => ({ id, worldFromDepth: pose, ...fallback, ...(intr || {}) }));
}

/** Fills `container` with the report's figures (nested one level), person-readable. */
export function renderReport(container, report) {
  container.replaceChildren();
  if (!report) return;
  const table = document.createElement('table');
  const addRows = (object, prefix = '') => {
    for (const [key, value] of Object.entries(object)) {
      if (value && typeof value === 'object' && !Array.isArray(value)) {
        if (prefix === '') addRows(value, `${key}.`);
        continue;
      }
      if (Array.isArray(value)) continue; // matrices and lists do not fit a table
      const row = table.insertRow();
      row.insertCell().textContent = prefix + key;
      row.insertCell().textContent = formatFigure(prefix + key, value);
    }
  };
  addRows(report);
  container.appendChild(table);
}

// `key` is the figure's path (e.g. stage_seconds.mesh); its unit comes from the name.
export function formatFigure(key, value) {
  if (typeof value !== 'number') return String(value);
  if (/_m$/.test(key)) return `${(value * 1000).toPrecision(3)} mm`;
  if (/(_s|seconds)$/.test(key) || /(_s|seconds)\./.test(key)) return `${value.toFixed(2)} s`;
  if (/bytes$/.test(key)) return formatBytes(value);
  return Number.isInteger(value) ? value.toLocaleString('en') : value.toPrecision(4);
}

export function formatBytes(bytes) {
  if (bytes >= 1 << 20) return `${(bytes / (1 << 20)).toFixed(2)} MB`;
  if (bytes >= 1 << 10) return `${(bytes / (1 << 10)).toFixed(1)} KB`;
  return `${bytes} B`;
}
