// The splat viewer: a model's 3D Gaussian splats (Niantic's `.spz` or the
// 3DGS `.ply`, whose spherical-harmonic colours Spark draws, so that the
// canvas is what the CPU rasteriser renders; a 32-byte `.splat` too, one
// colour a splat)
// drawn in the browser with WebGL2 by Spark (web/vendor/spark, on
// three.js), turned with the mouse, the wheel, touch and the arrow keys
// (three.js's OrbitControls). Once the file is fetched nothing more is
// asked of the server: every frame is the browser's.
//
// Our camera convention maps onto three.js's without a change of axes:
//   - world: Spark puts a splat at the position the file gives, in three.js
//     world coordinates (no flip of y or z; Spark's own demos rotate a 3DGS
//     .ply by 180 degrees about x in their code, not in the library). Our
//     exports write our world coordinates, so world = world.
//   - camera: ours is OpenGL's (x right, y up, looking down -z) and so is
//     three.js's; a camera's `matrixWorld` is our c2w with the row
//     [0, 0, 0, 1] added. (The 3DGS/COLMAP camera, x right, y down, z
//     forward, is ours times diag(1, -1, -1): not needed here.)
//   - intrinsics: the projection matrix is built from fx, fy, cx, cy in
//     pixels (pixel (i, j) centred at (i + 0.5, j + 0.5), as the engine's
//     rays), and Spark takes each splat's focal length from that matrix
//     (projectionMatrix[0][0] and [1][1] times half the render size) and its
//     centre from the projected point, so an off-centre cx, cy is honoured.
//     The canvas's drawing buffer is set to width x height at pixel ratio 1.
//
// How splats are drawn (RASTER below) follows the 3DGS paper's rasteriser,
// which the CPU rasteriser is to match: 0.3 px^2 added to each projected 2D
// covariance with opacity unchanged (Spark's default instead dims it,
// Mip-Splatting's anti-aliasing), cut off at 3 standard deviations, alpha
// below 1/255 skipped, sorted by view depth (Spark's default is distance
// from the eye). Spark keeps splats packed: colours and opacity in 8 bits,
// scales as 8-bit logarithms, positions as 16-bit floats relative to the
// splat's chunk, the higher spherical-harmonic terms in a few bits each.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { api } from './api.js';
import { SparkRenderer, SplatMesh } from './vendor/spark/spark.module.min.js';

/** Spark's settings that make it draw as the 3DGS rasteriser does. */
export const RASTER = {
  preBlurAmount: 0.3,
  blurAmount: 0,
  maxStdDev: 3,
  minAlpha: 1 / 255,
  sortRadial: false,
  enableLod: false,
};

/**
 * A projection matrix for a pinhole camera of `width x height` pixels with
 * focal lengths fx, fy and principal point cx, cy in pixels (y down from
 * the top, as image rows), clipping at `near` and `far`.
 */
export function projection({ fx, fy, cx, cy, width, height }, near, far) {
  return new THREE.Matrix4().set(
    (2 * fx) / width, 0, 1 - (2 * cx) / width, 0,
    0, (2 * fy) / height, (2 * cy) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
}

/** Our 3x4 camera-to-world rows as a three.js matrix. */
export function c2wMatrix(c2w) {
  const [a, b, c] = c2w;
  return new THREE.Matrix4().set(...a, ...b, ...c, 0, 0, 0, 1);
}

/**
 * A splat viewer on `canvas`. Options: `background` (RGB in 0..1, default
 * white, as the engine composites), `up` (the scene's up axis, which the
 * orbit turns around; default +y).
 */
export class SplatView {
  constructor(canvas, { background = [1, 1, 1], up = [0, 1, 0] } = {}) {
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(1);
    this.renderer.setClearColor(new THREE.Color(...background), 1);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1000);
    this.camera.up.set(...up);
    this.spark = new SparkRenderer({ renderer: this.renderer, onDirty: () => this.requestFrame(), ...RASTER });
    this.scene.add(this.spark);
    this.mesh = null;
    this.placed = false; // whether setCamera placed the camera
    this.near = 0.01;
    this.far = 1000;
    /** Frames drawn, the last one's time (ms), and when Spark last asked for one. */
    this.stats = { frames: 0, lastFrameMs: 0, dirtyAt: 0, drawnAt: 0 };
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.enableDamping = false;
    this.controls.screenSpacePanning = true;
    this.controls.listenToKeyEvents(canvas);
    this.controls.addEventListener('change', () => this.requestFrame());
    this.pending = false;
    this.resize(canvas.clientWidth || canvas.width, canvas.clientHeight || canvas.height);
  }

  /**
   * Fetches a splats file (with the API key) and shows it; returns the
   * splat count. The URL says its type: `.spz` or `format=spz`, `.ply` or
   * `format=ply`, else `.splat`.
   */
  async load(url) {
    const bytes = new Uint8Array(await (await api(url)).arrayBuffer());
    const type = url.match(/(?:\.|format=)(spz|ply)$/);
    return this.show(bytes, type ? type[1] : 'splat');
  }

  /** Shows the splats of a file's bytes (`fileType` 'spz', 'ply' or 'splat'); returns the splat count. */
  async show(bytes, fileType = 'ply') {
    if (this.mesh) {
      this.scene.remove(this.mesh);
      this.mesh.dispose();
    }
    this.mesh = new SplatMesh({ fileBytes: bytes, fileType });
    await this.mesh.initialized;
    this.scene.add(this.mesh);
    const box = new THREE.Box3();
    this.mesh.packedSplats.forEachSplat((_, centre) => box.expandByPoint(centre));
    this.bounds = box;
    if (!this.placed) this.frameAll();
    this.requestFrame();
    return this.mesh.packedSplats.numSplats;
  }

  /** Draws the canvas at `width x height` pixels with a 50-degree vertical field of view. */
  resize(width, height) {
    const fy = (0.5 * height) / Math.tan((25 * Math.PI) / 180);
    this.setIntrinsics({ fx: fy, fy, cx: width / 2, cy: height / 2, width, height });
  }

  setIntrinsics(k) {
    this.intrinsics = { ...k };
    this.renderer.setSize(k.width, k.height, false);
    this.camera.aspect = k.width / k.height;
    this.camera.fov = (2 * Math.atan((0.5 * k.height) / k.fy) * 180) / Math.PI;
    this.camera.projectionMatrix.copy(projection(k, this.near, this.far));
    this.camera.projectionMatrixInverse.copy(this.camera.projectionMatrix).invert();
    this.requestFrame();
  }

  /**
   * Sets the camera from our convention: `c2w` 3x4 rows (OpenGL: x right,
   * y up, looking down -z), pinhole `{ fx, fy, cx, cy, width, height }` in
   * pixels; `near`/`far` clip. The orbit then turns around the point
   * `target` (default: the splats' centre's depth straight ahead).
   */
  setCamera(c2w, intrinsics, { near, far, target } = {}) {
    this.placed = true;
    if (near) this.near = near;
    if (far) this.far = far;
    const m = c2wMatrix(c2w);
    const scale = new THREE.Vector3();
    m.decompose(this.camera.position, this.camera.quaternion, scale);
    this.camera.updateMatrixWorld(true);
    this.setIntrinsics(intrinsics || this.intrinsics);
    const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(this.camera.quaternion);
    if (target) {
      this.controls.target.set(...target);
    } else {
      const centre = this.bounds ? this.bounds.getCenter(new THREE.Vector3()) : new THREE.Vector3();
      const depth = Math.max(this.near * 10, centre.clone().sub(this.camera.position).dot(forward));
      this.controls.target.copy(this.camera.position).addScaledVector(forward, depth);
    }
    this.requestFrame();
  }

  /** Looks at all the splats from the +z side, a little above. */
  frameAll() {
    const box = this.bounds;
    if (!box || box.isEmpty()) return;
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(1e-3, box.getSize(new THREE.Vector3()).length() / 2);
    const up = this.camera.up.clone().normalize();
    const side = Math.abs(up.z) > 0.9 ? new THREE.Vector3(0, -1, 0) : new THREE.Vector3(0, 0, 1);
    const dir = side.addScaledVector(up, 0.4).normalize();
    this.camera.position.copy(centre).addScaledVector(dir, radius * 2.5);
    this.controls.target.copy(centre);
    this.camera.lookAt(centre);
    this.controls.update();
    this.requestFrame();
  }

  /** Our camera now: c2w 3x4 rows and the intrinsics. */
  getCamera() {
    this.camera.updateMatrixWorld(true);
    const e = this.camera.matrixWorld.elements; // column-major
    const c2w = [0, 1, 2].map((r) => [e[r], e[4 + r], e[8 + r], e[12 + r]]);
    const { width, height } = this.renderer.getSize(new THREE.Vector2());
    const p = this.camera.projectionMatrix.elements;
    return { c2w, fx: (p[0] * width) / 2, fy: (p[5] * height) / 2, cx: ((1 - p[8]) * width) / 2, cy: ((1 + p[9]) * height) / 2, width, height };
  }

  /** Draws on the next animation frame (once, however often it is asked). */
  requestFrame() {
    this.stats.dirtyAt = performance.now();
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      const t0 = performance.now();
      this.renderer.render(this.scene, this.camera);
      this.stats.frames += 1;
      this.stats.drawnAt = performance.now();
      this.stats.lastFrameMs = this.stats.drawnAt - t0;
    });
  }

  /**
   * Resolves once the picture is settled: drawn after Spark's last request
   * for a frame (its depth sort of the current view done), and nothing
   * asked for `quietMs` since.
   */
  async settled(quietMs = 250, timeoutMs = 20000) {
    const start = performance.now();
    for (;;) {
      await new Promise((r) => setTimeout(r, 50));
      const { dirtyAt, drawnAt } = this.stats;
      const now = performance.now();
      if (!this.pending && drawnAt >= dirtyAt && now - dirtyAt >= quietMs) return;
      if (now - start > timeoutMs) throw new Error('the splat view did not settle');
    }
  }

  dispose() {
    this.controls.dispose();
    if (this.mesh) this.mesh.dispose();
    this.renderer.dispose();
  }
}
