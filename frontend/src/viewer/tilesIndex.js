/**
 * Whether a model version is streamed: the asset `tiles/index.json` (written last by the worker,
 * so its presence means the tiles are complete). Kept apart from tiles.js so that the viewer
 * loads the 3D Tiles renderer only for models that have tiles.
 */
export const TILES_INDEX = 'tiles/index.json';

/** The URL of a model's tiles/index.json among its assets, or null (no tiles: today's path). */
export function tilesIndexUrl(assets) {
  return assets?.[TILES_INDEX] ?? null;
}

/** Largest tile budget accepted from a URL (MB): beyond it the browser, not the cache, decides. */
const MAX_BUDGET_MB = 4096;

/**
 * Streaming settings from the page's query string: `tile_budget_mb` (GPU memory budget of the
 * tile cache, default in tiles.js) and `tile_error_px` (screen-space error target). Invalid
 * values are ignored (the defaults stand), and reported in `ignored`.
 * @param {string} search location.search
 * @returns {{options: {budgetMb?: number, errorTarget?: number}, ignored: string[]}}
 */
export function tileOptionsFromSearch(search) {
  const q = new URLSearchParams(search);
  const options = {};
  const ignored = [];
  const budget = q.get('tile_budget_mb');
  if (budget !== null) {
    const mb = Number(budget);
    if (mb >= 1 && mb <= MAX_BUDGET_MB) options.budgetMb = mb;
    else ignored.push(`tile_budget_mb=${budget} (1 to ${MAX_BUDGET_MB})`);
  }
  const error = q.get('tile_error_px');
  if (error !== null) {
    const px = Number(error);
    if (px >= 0.25 && px <= 64) options.errorTarget = px;
    else ignored.push(`tile_error_px=${error} (0.25 to 64)`);
  }
  return { options, ignored };
}
