/**
 * What each shading mode needs, and what the page says when a model lacks it. Pure: works on
 * the loaded-asset record of assets.js ({names, normals, albedo, curvature, accessibility,
 * quality}; a lazily loaded kind is null until loaded, false/[] when absent).
 */

/** Shading modes whose maps load on first use. */
export const LAZY_KINDS = Object.freeze({
  curvature: 'curvature',
  accessibility: 'accessibility',
  quality: 'quality',
  trust: 'trust',
});

/** Which texture each shading mode needs. */
export const MODE_NEEDS = Object.freeze({
  natural: 'albedo',
  curvature: 'curvature',
  accessibility: 'accessibility',
  relief: 'normals',
  normals: 'normals',
  quality: 'quality',
  trust: 'trust',
});

const FILE_OF = {
  normals: 'normals.png',
  albedo: 'albedo.png',
  curvature: 'curvature.png',
  accessibility: 'accessibility.png',
  quality: 'quality map (quality/*.npy)',
  trust: 'trust.png (made by the worker from the quality maps)',
};

/**
 * The sentence to show for `mode` on a model with these assets, or null when all is there.
 * @param {string} mode a shading mode
 * @param {object} assets the loaded-asset record
 * @param {Record<string, string>} [errors] load errors by kind
 * @param {{normalsNote?: boolean}} [options] normalsNote: also say when the model lacks
 *   normals.png (false for the lens: the main mode's notice says it already)
 * @returns {string | null}
 */
export function missingMessage(mode, assets, errors = {}, { normalsNote = true } = {}) {
  const need = MODE_NEEDS[mode];
  const names = assets.names;
  const faces = assets.faces ?? [];
  if (faces.length) return missingOnFaces(mode, assets, errors, normalsNote);
  const present = {
    normals: Boolean(assets.normals),
    albedo: Boolean(assets.albedo),
    curvature: names.curvature.length > 0,
    accessibility: Boolean(names.accessibility),
    quality: names.quality.length > 0,
    trust: Boolean(names.trust),
  }[need];
  const file = FILE_OF[need];
  const notes = [];
  if (need !== undefined && !present) notes.push(`This model has no ${file}: the ${mode} view is not available.`);
  else if (errors[need]) notes.push(`Could not load ${file}: ${errors[need]}`);
  else if (LAZY_KINDS[mode] && assets[need] === null) notes.push(`Loading ${file}…`);
  if (normalsNote && !assets.normals && need !== 'normals') {
    notes.push('No normals.png: lit by the mesh normals, so fine wedges are smoothed away.');
  }
  return notes.length ? notes.join(' ') : null;
}

/**
 * The same for a whole tablet ({@link missingMessage} with `assets.faces`: one entry per face,
 * {name, assets: {normals, curvature, accessibility}, normals, albedo}): each face brings its own
 * maps, so the notice names the faces that lack one.
 */
function missingOnFaces(mode, assets, errors, normalsNote) {
  const need = MODE_NEEDS[mode];
  const faces = assets.faces;
  // A streamed face's tiles carry its normals, albedo, curvature and accessibility (the
  // tiles' contract, docs/tiles.md); its whole-face maps are assets as on model.glb's faces.
  const has = {
    normals: (f) => f.streamed || Boolean(f.normals),
    albedo: (f) => f.streamed || Boolean(f.albedo),
    curvature: (f) => f.streamed || f.assets.curvature.length > 0,
    accessibility: (f) => f.streamed || Boolean(f.assets.accessibility),
    quality: (f) => (f.assets.quality?.length ?? 0) > 0, // each face's own (quality/*.npy)
    trust: (f) => Boolean(f.assets.trust), // each face's own (worker/register/run.py)
  };
  const notes = [];
  const list = (fs) => fs.map((f) => f.name).join(', ');
  if (need !== undefined) {
    const lacking = faces.filter((f) => !has[need](f));
    const file = FILE_OF[need];
    if (lacking.length === faces.length) notes.push(`This model has no ${file}: the ${mode} view is not available.`);
    else if (lacking.length) notes.push(`No ${file} for ${list(lacking)}: drawn in half-lit clay there.`);
    else if (errors[need]) notes.push(`Could not load ${file}: ${errors[need]}`);
    else if (LAZY_KINDS[mode] && assets[need] === null) notes.push(`Loading ${file}…`);
  }
  const flat = faces.filter((f) => !has.normals(f));
  if (normalsNote && flat.length && need !== 'normals') {
    notes.push(
      flat.length === faces.length
        ? 'No normals.png for the faces: lit by the mesh normals, so fine wedges are smoothed away.'
        : `No normals.png for ${list(flat)}: lit by the mesh normals there.`,
    );
  }
  return notes.length ? notes.join(' ') : null;
}

/**
 * What the lens' mode lacks (enhance.js), as a sentence starting "In the lens:", or null when
 * the lens is off, shows the main mode, or has what it needs.
 * @param {string | null} lensMode
 * @param {string} mainMode
 * @param {object} assets the loaded-asset record
 * @param {Record<string, string>} [errors]
 */
export function lensMissingMessage(lensMode, mainMode, assets, errors = {}) {
  if (!lensMode || lensMode === mainMode) return null;
  const note = missingMessage(lensMode, assets, errors, { normalsNote: false });
  return note ? `In the lens: ${note}` : null;
}

/**
 * Why a mode cannot be chosen on this model, or null when it can: a mode whose maps the
 * model does not have at all (the page disables it in its selects, with this as the reason).
 * Only trust is decided here: a model without any trust.png (a model made before
 * worker/trust_assets.py; a streamed face or whole tablet gets its tiles' from the face's,
 * tiles.js) has nothing to show in it.
 * @param {string} mode
 * @param {object} assets the loaded-asset record
 * @param {{streamed?: boolean}} [options] streamed: the model is streamed (tiles.js)
 * @returns {string | null}
 */
export function unavailableModeReason(mode, assets, { streamed = false } = {}) {
  if (mode !== 'trust' || !assets) return null;
  const faces = assets.faces ?? [];
  const has = faces.length ? faces.some((f) => f.assets.trust) : Boolean(assets.names?.trust);
  if (has) return null;
  return streamed
    ? 'Trust: this streamed model has no trust map (trust.png), made by the worker from its quality maps.'
    : 'Trust: this model has no trust map (trust.png), made by the worker from its quality maps.';
}
