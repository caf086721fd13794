/**
 * The "Cite this view" dialog: fills plain text and BibTeX (cite.js) from what the page says
 * about the tablet and the view, and copies either to the clipboard.
 */
import { citeBibtex, citeText } from './cite.js';

/**
 * @param {{getAbout: () => object|null}} context `getAbout` returns cite.js's `about` without
 *   `accessed` (null while no model is shown).
 */
export function bindCite({ getAbout }) {
  const $ = (id) => document.getElementById(id);
  const dialog = $('cite-dialog');
  function open() {
    const about = getAbout();
    if (!about) return;
    const full = { ...about, accessed: new Date() };
    $('cite-text').value = citeText(full);
    $('cite-bibtex').value = citeBibtex(full);
    dialog.showModal();
  }
  for (const [button, field] of [
    ['cite-copy-text', 'cite-text'],
    ['cite-copy-bibtex', 'cite-bibtex'],
  ]) {
    $(button).addEventListener('click', () => {
      $(field).select();
      navigator.clipboard?.writeText($(field).value).catch(() => {});
    });
  }
  $('cite').addEventListener('click', open);
  return { open };
}
