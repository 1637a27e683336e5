// The crop box editor: a model's crop volume (an oriented box: `centre`,
// unit `axes` as rows, `half` extents, as `PUT /v1/models/{id}/crop`
// takes it) drawn over its splats, with three.js's TransformControls
// handles to move, turn and resize it. The box is a three.js object whose
// position is the centre, whose rotation's columns are the axes and whose
// scale is the half extents, drawn as the edges of the cube [-1, 1]^3.
// The view follows the box: the splats outside it are hidden (drawn at
// opacity 0) after each move, and shown again when the editor closes.

import * as THREE from 'three';
import { TransformControls } from 'three/addons/controls/TransformControls.js';

/** The smallest half extent the handles leave a box. */
const MIN_HALF = 1e-3;

/** `{centre, axes, half}` for an object's position, rotation and scale. */
export function boxOf(object) {
  object.updateMatrixWorld(true);
  const r = new THREE.Matrix4().extractRotation(object.matrix).elements; // column-major
  const axes = [0, 1, 2].map((a) => [r[4 * a], r[4 * a + 1], r[4 * a + 2]]);
  const half = ['x', 'y', 'z'].map((k) => Math.max(MIN_HALF, Math.abs(object.scale[k])));
  return { centre: object.position.toArray(), axes, half };
}

/** Places `object` as the box says (a left-handed set of axes turned right-handed: the same box). */
export function placeBox(object, { centre, axes, half }) {
  const x = new THREE.Vector3(...axes[0]);
  const y = new THREE.Vector3(...axes[1]);
  let z = new THREE.Vector3(...axes[2]);
  if (new THREE.Vector3().crossVectors(x, y).dot(z) < 0) z = z.negate();
  const m = new THREE.Matrix4().makeBasis(x, y, z);
  object.position.set(...centre);
  object.quaternion.setFromRotationMatrix(m);
  object.scale.set(...half);
  object.updateMatrixWorld(true);
}

/** The axis-aligned box around a THREE.Box3. */
export function boxAround(bounds) {
  const c = bounds.getCenter(new THREE.Vector3());
  const s = bounds.getSize(new THREE.Vector3());
  return { centre: c.toArray(), axes: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], half: s.toArray().map((v) => Math.max(MIN_HALF, v / 2)) };
}

/** Whether world point `p` (a THREE.Vector3) is inside the box. */
export function inside(box, p) {
  const d = [p.x - box.centre[0], p.y - box.centre[1], p.z - box.centre[2]];
  return box.axes.every((a, i) => Math.abs(a[0] * d[0] + a[1] * d[1] + a[2] * d[2]) <= box.half[i]);
}

/**
 * The box over a SplatView (`view`: its scene, camera, canvas and orbit
 * controls), with handles; `onChange(box)` after each drag.
 */
export class CropEditor {
  constructor(view, box, onChange = () => {}) {
    this.view = view;
    this.object = new THREE.Object3D();
    const cube = new THREE.EdgesGeometry(new THREE.BoxGeometry(2, 2, 2));
    this.edges = new THREE.LineSegments(cube, new THREE.LineBasicMaterial({ color: 0xff6a00, depthTest: false }));
    this.edges.renderOrder = 1;
    this.object.add(this.edges);
    placeBox(this.object, box);
    view.scene.add(this.object);
    this.controls = new TransformControls(view.camera, view.canvas);
    this.controls.setSpace('local');
    this.controls.attach(this.object);
    this.helper = this.controls.getHelper();
    view.scene.add(this.helper);
    // The orbit waits while a handle is dragged.
    this.controls.addEventListener('dragging-changed', (e) => {
      view.controls.enabled = !e.value;
      if (!e.value) onChange(this.preview());
    });
    // The splats shown, and each one's opacity as loaded, to show it again.
    this.mesh = view.mesh;
    this.opacities = null;
    this.controls.addEventListener('change', () => view.requestFrame());
    view.requestFrame();
  }

  /** 'translate' (move), 'rotate' (turn) or 'scale' (resize). */
  setMode(mode) {
    this.controls.setMode(mode);
    this.view.requestFrame();
  }

  box() {
    return boxOf(this.object);
  }

  set(box) {
    placeBox(this.object, box);
    return this.preview();
  }

  /**
   * Hides the splats whose centres are outside the box and shows those
   * inside (`all`: every one, as loaded); how many are inside, of all.
   */
  preview(all = false) {
    const mesh = this.mesh;
    if (!mesh || mesh !== this.view.mesh) return { inside: 0, all: 0 };
    const splats = mesh.packedSplats;
    if (!this.opacities) {
      this.opacities = new Float32Array(splats.numSplats);
      splats.forEachSplat((i, c, s, q, opacity) => { this.opacities[i] = opacity; });
    }
    const box = this.box();
    let n = 0;
    splats.forEachSplat((i, centre, scales, quaternion, opacity, colour) => {
      const keep = all || inside(box, centre);
      if (keep) n += 1;
      const want = keep ? this.opacities[i] : 0;
      if (opacity !== want) splats.setSplat(i, centre, scales, quaternion, want, colour);
    });
    splats.needsUpdate = true;
    this.view.requestFrame();
    return { inside: n, all: splats.numSplats };
  }

  dispose() {
    if (this.opacities) this.preview(true);
    this.controls.detach();
    this.controls.dispose();
    this.view.scene.remove(this.helper, this.object);
    this.edges.geometry.dispose();
    this.edges.material.dispose();
    this.view.controls.enabled = true;
    this.view.requestFrame();
  }
}
