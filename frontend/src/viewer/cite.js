/**
 * "Cite this view": a reference to what is on screen, as plain text and as BibTeX. It names
 * the tablet (designation, CDLI number), the model version shown, the view (shading, light,
 * measurement), the permalink that restores it, the access date, the licence and the
 * attribution. Pure functions: the page gathers `about`, these only format.
 */

const SITE = 'Digital Hammurabi library';

function describeView(view) {
  if (!view) return '';
  const parts = [];
  if (view.mode) parts.push(`${view.mode} shading`);
  if (view.light) {
    parts.push(`light azimuth ${Math.round(view.light.azimuthDeg)}°, elevation ${Math.round(90 - view.light.polarDeg)}°`);
  }
  if (view.measure?.lengthMm != null) parts.push(`${view.measure.tool} ${view.measure.lengthMm.toFixed(2)} mm`);
  return parts.join(', ');
}

/** ISO date (YYYY-MM-DD) of `date` in UTC. */
export function isoDate(date) {
  return date.toISOString().slice(0, 10);
}

/**
 * @param {{tablet: string, pNumber?: string|null, institution?: string|null, modelId: number,
 *   modelVersion: number, face?: string|null, view?: object, permalink: string, accessed: Date,
 *   licence?: string|null, attribution?: string|null}} about
 */
export function citeText(about) {
  const who = about.institution ? `${about.institution}. ` : '';
  const id = about.pNumber ? ` (${about.pNumber})` : '';
  const face = about.face ? `, ${about.face}` : '';
  const view = describeView(about.view);
  const lines = [
    `${who}${about.tablet}${id}${face}, 3-D model version ${about.modelVersion} (model ${about.modelId})` +
      `${view ? `, view: ${view}` : ''}. ${SITE}. ${about.permalink} (accessed ${isoDate(about.accessed)}).`,
  ];
  if (about.attribution) lines.push(about.attribution);
  if (about.licence) lines.push(`Licence: ${about.licence}`);
  return lines.join('\n');
}

/** A BibTeX key from the designation and model: letters and digits only. */
export function bibtexKey(about) {
  const base = `${about.pNumber || about.tablet}`.replace(/[^A-Za-z0-9]+/g, '');
  return `${base || 'tablet'}_m${about.modelId}v${about.modelVersion}`;
}

function bibEscape(text) {
  return String(text).replace(/[\\{}]/g, (c) => `\\${c}`).replace(/[%&$#_]/g, (c) => `\\${c}`);
}

/** The same reference as a BibTeX @misc entry (biblatex's urldate for the access date). */
export function citeBibtex(about) {
  const view = describeView(about.view);
  const fields = [
    ['author', about.institution ? `{${bibEscape(about.institution)}}` : null],
    ['title', `{${bibEscape(about.tablet)}${about.pNumber ? ` (${about.pNumber})` : ''}${about.face ? `, ${bibEscape(about.face)}` : ''}: 3-D model version ${about.modelVersion}}`],
    ['howpublished', `{${SITE}}`],
    ['note', `{Model ${about.modelId}, version ${about.modelVersion}${view ? `; view: ${bibEscape(view)}` : ''}${about.licence ? `; licence: \\url{${about.licence}}` : ''}${about.attribution ? `; ${bibEscape(about.attribution)}` : ''}}`],
    ['url', `{${about.permalink}}`],
    ['urldate', `{${isoDate(about.accessed)}}`],
    ['year', `{${about.accessed.getUTCFullYear()}}`],
  ].filter(([, v]) => v != null);
  return `@misc{${bibtexKey(about)},\n${fields.map(([k, v]) => `  ${k} = ${v}`).join(',\n')}\n}\n`;
}
