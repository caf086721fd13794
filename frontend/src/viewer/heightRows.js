/**
 * Full-resolution heights of a streamed model for the measuring tools, read from
 * `tiles/height.f32` (raw little-endian float32, row-major, NaN outside the mask; the
 * `height_raw` entry of tiles/index.json) with HTTP Range requests (RFC 9110 §14) of only the
 * rows a profile touches, kept in an LRU of row blocks.
 *
 * A block is `blockRows` whole rows (one contiguous byte range: a Range request cannot ask
 * for a rectangle). A profile across a 10,000-pixel-wide face touches a few hundred rows, so a
 * few MB move instead of the 400 MB file.
 */

const BYTES_PER_VALUE = 4;

/**
 * @param {object} options
 * @param {string} options.url URL of height.f32
 * @param {number} options.rows image height H
 * @param {number} options.cols image width W
 * @param {number} [options.blockRows] rows per block (one Range request)
 * @param {number} [options.maxBytes] LRU budget of the cached blocks
 * @param {typeof fetch} [options.fetch] (tests pass a fake)
 */
export function createHeightRows({ url, rows, cols, blockRows = 32, maxBytes = 64 * 1024 * 1024, fetch: fetchFn = globalThis.fetch }) {
  if (!(Number.isInteger(rows) && rows > 0 && Number.isInteger(cols) && cols > 0)) {
    throw new RangeError(`height.f32 shape must be positive integers, got [${rows}, ${cols}]`);
  }
  if (!(Number.isInteger(blockRows) && blockRows > 0)) throw new RangeError(`blockRows must be a positive integer, got ${blockRows}`);
  const blockBytes = blockRows * cols * BYTES_PER_VALUE;
  const cache = new Map(); // block index → Promise<Float32Array>; Map order = recency
  let bytesFetched = 0;
  let requests = 0;

  function evict() {
    // Keep at least one block (the one just asked for), whatever the budget.
    while (cache.size > 1 && cache.size * blockBytes > maxBytes) cache.delete(cache.keys().next().value);
  }

  async function fetchBlock(b) {
    const r0 = b * blockRows;
    const r1 = Math.min(rows, r0 + blockRows);
    const first = r0 * cols * BYTES_PER_VALUE;
    const last = r1 * cols * BYTES_PER_VALUE - 1;
    requests++;
    const response = await fetchFn(url, { headers: { Range: `bytes=${first}-${last}` }, credentials: 'same-origin' });
    if (response.status !== 206) {
      // 200 would be the whole file: refuse rather than download hundreds of MB by surprise.
      throw new Error(`${url}: expected 206 Partial Content for rows ${r0}–${r1 - 1}, got HTTP ${response.status}`);
    }
    const buf = await response.arrayBuffer();
    const expected = last - first + 1;
    if (buf.byteLength !== expected) throw new Error(`${url}: rows ${r0}–${r1 - 1}: got ${buf.byteLength} bytes, expected ${expected}`);
    bytesFetched += buf.byteLength;
    // Little-endian on disk; every browser is little-endian, DataView would only slow it down.
    return new Float32Array(buf);
  }

  function block(b) {
    let p = cache.get(b);
    if (p) {
      cache.delete(b); // refresh recency
    } else {
      p = fetchBlock(b);
      p.catch(() => cache.delete(b)); // a failed block is asked for again next time
    }
    cache.set(b, p);
    evict();
    return p;
  }

  /**
   * Rows [r0, r1) of the height map, as one Float32Array ((r1 − r0) × cols, µm).
   * @param {number} r0 first row (clamped to the grid)
   * @param {number} r1 one past the last row (clamped)
   */
  async function readRows(r0, r1) {
    const a = Math.max(0, Math.floor(r0));
    const z = Math.min(rows, Math.ceil(r1));
    if (!(z > a)) return new Float32Array(0);
    const out = new Float32Array((z - a) * cols);
    const b0 = Math.floor(a / blockRows);
    const b1 = Math.floor((z - 1) / blockRows);
    const parts = await Promise.all(Array.from({ length: b1 - b0 + 1 }, (_, i) => block(b0 + i)));
    parts.forEach((data, i) => {
      const start = (b0 + i) * blockRows; // first row of this block
      const from = Math.max(a, start);
      const to = Math.min(z, start + blockRows);
      out.set(data.subarray((from - start) * cols, (to - start) * cols), (from - a) * cols);
    });
    return out;
  }

  /**
   * The part of the height grid a segment touches, for profile.js' `sampleProfile`: rows from
   * the segment's lowest to highest (with the bilinear neighbour), all columns, and the end
   * points moved into that sub-grid's frame.
   * @param {[number, number]} startMm object-plane (x, y) mm
   * @param {[number, number]} endMm
   * @param {number} pixelSizeUm
   * @returns {Promise<{grid: {heightUm: Float32Array, rows: number, cols: number, pixelSizeUm: number},
   *   start: [number, number], end: [number, number]}>}
   */
  async function gridForSegment(startMm, endMm, pixelSizeUm) {
    const pxPerMm = 1000 / pixelSizeUm;
    const rA = startMm[1] * pxPerMm;
    const rB = endMm[1] * pxPerMm;
    const r0 = Math.max(0, Math.min(rows - 1, Math.floor(Math.min(rA, rB))));
    const r1 = Math.max(r0 + 1, Math.min(rows, Math.floor(Math.max(rA, rB)) + 2));
    const heightUm = await readRows(r0, r1);
    const dy = (r0 * pixelSizeUm) / 1000;
    return {
      grid: { heightUm, rows: r1 - r0, cols, pixelSizeUm },
      start: [startMm[0], startMm[1] - dy],
      end: [endMm[0], endMm[1] - dy],
    };
  }

  return {
    readRows,
    gridForSegment,
    rows,
    cols,
    /** Figures for tests and the benchmark: bytes and requests so far, blocks cached. */
    get stats() {
      return { bytesFetched, requests, blocksCached: cache.size, blockBytes };
    },
  };
}
