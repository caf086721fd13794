/**
 * Measuring marks drawn over the model (picked points and the line between them), and the
 * conversions between page positions and model points. The marks own their GPU resources:
 * clearing them disposes every geometry and material.
 */
import * as THREE from 'three';

const MARK_COLOUR = 0xffcc00;

/**
 * @param {THREE.Object3D} parent where the marks are added (the scene)
 * @returns {{set: (points: number[][], radiusMm: number) => void, clear: () => void}}
 */
export function createMarks(parent) {
  const group = new THREE.Group();
  group.renderOrder = 10;
  parent.add(group);
  const material = () => ({ color: MARK_COLOUR, depthTest: false, transparent: true });

  function clear() {
    for (const child of [...group.children]) {
      group.remove(child);
      child.geometry?.dispose();
      child.material?.dispose();
    }
  }

  function set(points, radiusMm) {
    clear();
    for (const p of points) {
      const dot = new THREE.Mesh(new THREE.SphereGeometry(radiusMm, 12, 8), new THREE.MeshBasicMaterial(material()));
      dot.position.set(...p);
      dot.renderOrder = 11;
      group.add(dot);
    }
    if (points.length > 1) {
      const geometry = new THREE.BufferGeometry().setFromPoints(points.map((p) => new THREE.Vector3(...p)));
      const line = new THREE.Line(geometry, new THREE.LineBasicMaterial(material()));
      line.renderOrder = 11;
      group.add(line);
    }
  }

  return { set, clear };
}

const raycaster = new THREE.Raycaster();

/**
 * The point of `object` under a page (CSS pixel) position, or null.
 * @returns {{point: number[], uv: number[] | null, group: number | null, part: number | null} | null}
 *   point in world units (mm); group: the material index hit; part: the face of a
 *   multi-part model (the same index, null for a one-mesh model)
 */
export function pickPoint(canvas, camera, object, clientX, clientY) {
  const rect = canvas.getBoundingClientRect();
  const ndc = new THREE.Vector2(
    ((clientX - rect.left) / rect.width) * 2 - 1,
    -((clientY - rect.top) / rect.height) * 2 + 1,
  );
  raycaster.setFromCamera(ndc, camera);
  // Hidden parts (draw groups with an invisible material) are not there to be picked.
  const materialOf = (h) => (Array.isArray(h.object.material) ? h.object.material[h.face?.materialIndex ?? 0] : h.object.material);
  // A streamed model is a group whose children are the tiles drawn now (tiles.js): search them.
  const targets = object.isMesh ? [object] : object.children;
  const hit = raycaster.intersectObjects(targets, !object.isMesh).find((h) => materialOf(h)?.visible !== false);
  if (!hit) return null;
  // part: the draw group's material index, i.e. the face of a whole tablet (null: one mesh).
  const part = Array.isArray(object.material) ? (hit.face?.materialIndex ?? null) : null;
  const out = { point: hit.point.toArray(), uv: hit.uv ? hit.uv.toArray() : null, group: hit.face?.materialIndex ?? null, part };
  // The mesh hit (a tile of a streamed model says which: tiles.js `describeTile`), kept out of
  // JSON and structured clones.
  Object.defineProperty(out, 'object', { value: hit.object, enumerable: false });
  return out;
}

/** Page (CSS pixel) position of a world point (mm). */
export function projectPoint(canvas, camera, point) {
  const rect = canvas.getBoundingClientRect();
  const v = new THREE.Vector3(...point).project(camera);
  return { x: rect.left + ((v.x + 1) / 2) * rect.width, y: rect.top + ((1 - v.y) / 2) * rect.height };
}
