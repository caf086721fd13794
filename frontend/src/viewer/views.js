/**
 * Canonical views of a tablet in the scan frame (x right, y DOWN, z AWAY from the camera).
 * Pure functions on plain arrays.
 *
 * The obverse is seen as scanned: camera on the −z side looking along +z, screen-up = −y.
 * The reverse is the tablet turned over its bottom edge, as Assyriologists turn tablets: camera
 * on the +z side, screen-up = +y, so the bottom edge of the obverse meets the top of the
 * reverse. Edges are placed as in the usual "fat cross" layout around the obverse: the top
 * edge seen from −y with the obverse side down, the bottom edge from +y with the obverse side
 * up, the left and right edges from −x and +x.
 */

export const VIEW_NAMES = Object.freeze(['obverse', 'reverse', 'top', 'bottom', 'left', 'right']);

const VIEWS = {
  // dir: the direction the camera looks in; up: screen-up
  obverse: { dir: [0, 0, 1], up: [0, -1, 0] },
  reverse: { dir: [0, 0, -1], up: [0, 1, 0] },
  top: { dir: [0, 1, 0], up: [0, 0, 1] },
  bottom: { dir: [0, -1, 0], up: [0, 0, -1] },
  left: { dir: [1, 0, 0], up: [0, -1, 0] },
  right: { dir: [-1, 0, 0], up: [0, -1, 0] },
};

/**
 * Where to put the camera for a canonical view of a bounding box.
 * @param {string} name one of VIEW_NAMES
 * @param {{min: number[], max: number[]}} box axis-aligned bounds in mm
 * @param {object} [options]
 * @param {number} [options.aspect] viewport width / height (default 1)
 * @param {number} [options.margin] fraction of free space around the object (default 0.08)
 * @returns {{position: number[], target: number[], up: number[], halfHeight: number, distance: number}}
 *   halfHeight: half the visible height in mm at the target, so the box fits the viewport
 */
export function canonicalView(name, box, { aspect = 1, margin = 0.08 } = {}) {
  const view = VIEWS[name];
  if (!view) throw new RangeError(`name must be one of ${VIEW_NAMES.join(', ')}, got ${name}`);
  if (!(aspect > 0)) throw new RangeError(`aspect must be > 0, got ${aspect}`);
  const target = box.min.map((lo, i) => (lo + box.max[i]) / 2);
  const size = box.max.map((hi, i) => hi - box.min[i]);
  const right = screenRight(view.dir, view.up);
  const width = Math.abs(dot(right, size));
  const height = Math.abs(dot(view.up, size));
  const depth = Math.abs(dot(view.dir, size));
  const halfHeight = (Math.max(height, width / aspect) / 2) * (1 + 2 * margin) || 1;
  const radius = Math.hypot(...size) / 2 || 1;
  const distance = radius * 3 + depth;
  const position = target.map((t, i) => t - view.dir[i] * distance);
  return { position, target, up: [...view.up], halfHeight, distance };
}

/**
 * Screen-right direction of a camera looking along `dir` with screen-up `up`: a three.js
 * camera looks along its −Z with +Y up, so right = Y × Z = up × (−dir) = dir × up.
 */
export function screenRight(dir, up) {
  return cross(dir, up).map((v) => v + 0); // no negative zeros
}

function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}

function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/**
 * The canonical views a model has. A whole tablet (the registration's model) has all six. A
 * face model is one scan: a height field seen from its own camera, so only its scanned side
 * exists; the view "reverse" would show that same side from behind, mirrored with its relief
 * inverted (easily taken for the reverse), and the edge views show its rim sideways.
 * @param {'face' | 'tablet'} kind
 * @returns {string[]} names from VIEW_NAMES
 */
export function availableViews(kind) {
  if (kind === 'tablet') return [...VIEW_NAMES];
  if (kind === 'face') return ['obverse'];
  throw new RangeError(`kind must be face or tablet, got ${kind}`);
}

/** Why a canonical view is not offered on a face model (the button's tooltip). */
export function unavailableViewReason(name, face) {
  const side = face ? `the ${face} scan` : 'one scan';
  return (
    `This model is ${side}: it has only the side its camera saw, so a ${name} view would show ` +
    'that side from behind (mirrored, relief inverted). Open the whole tablet for the other sides.'
  );
}
