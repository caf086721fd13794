/** Tiny DOM helpers shared by the pages (no framework: plain elements). */

/**
 * Create an element: el('a', {href: '/x'}, 'text', child…). Text is set as text, never HTML.
 * @param {string} tag
 * @param {Record<string, string|number|boolean|null|undefined>} [attrs]
 * @param {...(Node|string|number|null|undefined)} children
 */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    node.setAttribute(k, v === true ? '' : String(v));
  }
  for (const c of children) {
    if (c === null || c === undefined) continue;
    node.append(c instanceof Node ? c : String(c));
  }
  return node;
}

/** A date from the API (ISO 8601) as "2026-11-21 14:03". */
export function formatDate(iso) {
  if (!iso) return '';
  const d = new Date(iso);
  if (Number.isNaN(d.getTime())) return String(iso);
  return d.toISOString().slice(0, 16).replace('T', ' ');
}

/** Show a message in an error element (role=alert), or hide it for an empty message. */
export function showError(node, message) {
  node.hidden = !message;
  node.textContent = message ?? '';
}

/** Bytes as "12.3 MB". */
export function formatBytes(n) {
  if (!(n >= 0)) return '';
  const units = ['B', 'kB', 'MB', 'GB', 'TB'];
  let i = 0;
  let v = n;
  while (v >= 1000 && i < units.length - 1) {
    v /= 1000;
    i++;
  }
  return `${v.toFixed(i ? 1 : 0)} ${units[i]}`;
}
