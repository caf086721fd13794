/**
 * Which parts (glTF nodes) of a multi-node model are shown: the whole-tablet model of the
 * registration holds one node per scanned face (node name = the face), and the page offers a
 * checkbox per part. Pure state; the viewer maps it onto its mesh's draw groups.
 */

/**
 * @param {string[]} names part names in draw order (duplicates and blanks get a numbered name)
 * @returns {{names: string[], isVisible: (name: string) => boolean,
 *   set: (name: string, visible: boolean) => boolean, visibleNames: () => string[],
 *   groupMaterialIndex: (i: number) => number}}
 *   `set` returns whether anything changed (so the caller renders only then);
 *   `groupMaterialIndex(i)` is 0 for a shown part i and 1 (the hidden material) otherwise.
 */
export function createPartToggles(names) {
  if (!Array.isArray(names)) throw new TypeError('names must be an array of part names');
  const seen = new Map();
  const unique = names.map((raw, i) => {
    let name = typeof raw === 'string' && raw.trim() ? raw.trim() : `part ${i + 1}`;
    const n = (seen.get(name) ?? 0) + 1;
    seen.set(name, n);
    if (n > 1) name = `${name} (${n})`;
    return name;
  });
  const shown = new Set(unique);
  const check = (name) => {
    if (!unique.includes(name)) throw new RangeError(`no part named ${JSON.stringify(name)}; parts: ${unique.join(', ')}`);
  };
  return {
    names: unique,
    isVisible(name) {
      check(name);
      return shown.has(name);
    },
    set(name, visible) {
      check(name);
      if (shown.has(name) === Boolean(visible)) return false;
      if (visible) shown.add(name);
      else shown.delete(name);
      return true;
    },
    visibleNames: () => unique.filter((n) => shown.has(n)),
    groupMaterialIndex: (i) => (shown.has(unique[i]) ? 0 : 1),
  };
}

/**
 * Make exactly the parts named in `hidden` hidden and every other part shown (the hidden faces
 * of a permalink). Names the model does not have are returned, never thrown: a link may come
 * from another model version, or be edited by hand.
 * @param {ReturnType<typeof createPartToggles> | null} toggles null for a one-part model
 * @param {unknown} hidden part names
 * @returns {{changed: boolean, unknown: string[]}}
 */
export function applyHiddenParts(toggles, hidden) {
  const wanted = new Set(Array.isArray(hidden) ? hidden.filter((n) => typeof n === 'string') : []);
  const known = new Set(toggles?.names ?? []);
  const unknown = [...wanted].filter((n) => !known.has(n));
  let changed = false;
  for (const name of toggles?.names ?? []) changed = toggles.set(name, !wanted.has(name)) || changed;
  return { changed, unknown };
}

/** Names of the hidden parts, in part order ([] without toggles). */
export function hiddenParts(toggles) {
  return toggles ? toggles.names.filter((n) => !toggles.isVisible(n)) : [];
}
