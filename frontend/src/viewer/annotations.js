/**
 * Annotations of signs on the model: pure helpers (no DOM, no three.js) and the overlay that
 * draws their regions over the model.
 *
 * Frames (docs/architecture.md): model points are in the scan frame in mm; in `model.glb`
 * texture coordinates are the image grid, u = (c + 0.5)/W, v = (r + 0.5)/H, so a picked
 * point's uv gives its pixel (column c, row r) in the face's image.
 */
import * as THREE from 'three';

const REGION_COLOUR = 0x35d0ff;
const HIGHLIGHT_COLOUR = 0xff3dbb;
const DRAFT_COLOUR = 0xffcc00;

/**
 * Pixel (column, row) of the image grid for texture coordinates (u, v) of a W × H image.
 * @param {number[]} uv
 * @param {number} width W in pixels
 * @param {number} height H in pixels
 * @returns {number[]} [c, r], rounded to 0.01 px
 */
export function uvToPixel(uv, width, height) {
  if (!(width > 0 && height > 0)) throw new RangeError('width and height must be > 0');
  const round = (x) => Math.round(x * 100) / 100;
  return [round(uv[0] * width - 0.5), round(uv[1] * height - 0.5)];
}

/** A reference as the API writes it ("o 2 3"), or null for one that is not like it. */
export function normaliseReference(text) {
  const parts = String(text ?? '').trim().toLowerCase().split(/\s+/);
  if (parts.length !== 3) return null;
  const [surface, line, sign] = parts;
  if (!/^(o|r|le|re|te|be)$/.test(surface)) return null;
  if (!/^[1-9]\d{0,3}('{1,2}|[a-z])?$/.test(line) || !/^[1-9]\d{0,3}$/.test(sign)) return null;
  return `${surface} ${line} ${sign}`;
}

/**
 * May `me` change or delete `annotation` of `tablet`? The author, staff of the institution
 * that holds the tablet and admins (the API decides; this only hides buttons).
 */
export function canEdit(me, annotation, tablet) {
  if (!me) return false;
  if (me.role === 'admin') return true;
  if (annotation.creatorId === me.id) return true;
  return me.role === 'staff' && me.institution_id != null && me.institution_id === tablet?.institution_id;
}

/** Staff and registered users annotate; anonymous readers only read. */
export function canAnnotate(me) {
  return Boolean(me && ['admin', 'staff', 'reader'].includes(me.role));
}

/** The annotations (of the page) whose reference is `reference` ("o 2 3"). */
export function annotationsOfSign(annotations, reference) {
  return annotations.filter((a) => a.reference?.text === reference);
}

/** Centroid of a polygon's points (mm): where a region's label sits. */
export function centroid(points) {
  const n = points.length;
  if (!n) throw new RangeError('a polygon needs points');
  const sum = points.reduce((acc, p) => acc.map((v, i) => v + p[i]), [0, 0, 0]);
  return sum.map((v) => v / n);
}

/**
 * The body of a POST/PATCH for a drawn region: polygon_mm always; the image grid's polygon
 * only for a whole tablet (a face model's follows from mm and its pixel size, on the server).
 * @param {{point: number[], uv: number[] | null, part: string | null}[]} picks
 * @param {{whole: boolean, gridOf: (part: string) => {width: number, height: number} | null}} model
 */
export function regionBody(picks, { whole, gridOf }) {
  const body = { polygon_mm: picks.map((p) => p.point.map((v) => Math.round(v * 10000) / 10000)) };
  if (!whole) return body;
  const part = picks[0]?.part;
  const grid = part ? gridOf(part) : null;
  // One face's image grid only: a region over an edge between two faces has none.
  if (grid && picks.every((p) => p.part === part && p.uv)) {
    body.polygon_px = picks.map((p) => uvToPixel(p.uv, grid.width, grid.height));
    body.image_face = part;
  }
  return body;
}

/**
 * Regions drawn over the model (outline always on top, a translucent fill when highlighted)
 * and the polygon being drawn. Owns its GPU resources: `clear` disposes them.
 * @param {(object: THREE.Object3D) => () => void} addOverlay the viewer's hook
 */
export function createRegionOverlay(addOverlay) {
  const group = new THREE.Group();
  group.renderOrder = 12;
  const remove = addOverlay(group);
  const material = (colour, opacity = 1) =>
    new THREE.LineBasicMaterial({ color: colour, depthTest: false, transparent: true, opacity });

  function clear() {
    for (const child of [...group.children]) {
      group.remove(child);
      child.geometry?.dispose();
      child.material?.dispose();
    }
  }

  function outline(points, colour, closed) {
    const geometry = new THREE.BufferGeometry().setFromPoints(points.map((p) => new THREE.Vector3(...p)));
    const line = closed ? new THREE.LineLoop(geometry, material(colour)) : new THREE.Line(geometry, material(colour));
    line.renderOrder = 13;
    group.add(line);
  }

  function fill(points, colour) {
    // A fan from the first point: regions are drawn around a sign, nearly convex.
    const positions = [];
    for (let i = 1; i + 1 < points.length; i++) positions.push(...points[0], ...points[i], ...points[i + 1]);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.Float32BufferAttribute(positions, 3));
    const mesh = new THREE.Mesh(
      geometry,
      new THREE.MeshBasicMaterial({ color: colour, transparent: true, opacity: 0.35, depthTest: false, side: THREE.DoubleSide }),
    );
    mesh.renderOrder = 12;
    group.add(mesh);
  }

  function dots(points, radiusMm, colour) {
    for (const p of points) {
      const dot = new THREE.Mesh(
        new THREE.SphereGeometry(radiusMm, 10, 6),
        new THREE.MeshBasicMaterial({ color: colour, depthTest: false, transparent: true }),
      );
      dot.position.set(...p);
      dot.renderOrder = 14;
      group.add(dot);
    }
  }

  /**
   * @param {{points: number[][], highlighted: boolean}[]} regions
   * @param {number[][]} draft the polygon being drawn (mm)
   * @param {number} radiusMm size of the draft's dots
   */
  function set(regions, draft, radiusMm) {
    clear();
    for (const r of regions) {
      if (r.points.length < 2) continue;
      if (r.highlighted) fill(r.points, HIGHLIGHT_COLOUR);
      outline(r.points, r.highlighted ? HIGHLIGHT_COLOUR : REGION_COLOUR, true);
    }
    if (draft.length) {
      dots(draft, radiusMm, DRAFT_COLOUR);
      if (draft.length > 1) outline(draft, DRAFT_COLOUR, draft.length > 2);
    }
  }

  return {
    set,
    clear,
    dispose() {
      clear();
      remove();
    },
  };
}
