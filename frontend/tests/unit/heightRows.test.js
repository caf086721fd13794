import { describe, expect, it } from 'vitest';
import { createHeightRows } from '../../src/viewer/heightRows.js';
import { sampleProfile } from '../../src/viewer/profile.js';

/** A height map as height.f32 bytes, and a fake fetch that serves Range requests of it (RFC
 * 9110: 206 with exactly the bytes asked for), recording every request. */
function fakeServer(rows, cols, f, { status = 206 } = {}) {
  const values = new Float32Array(rows * cols);
  for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) values[r * cols + c] = f(r, c);
  const bytes = new Uint8Array(values.buffer);
  const log = [];
  const fetch = async (url, init = {}) => {
    const range = init.headers?.Range;
    log.push(range ?? null);
    const m = /^bytes=(\d+)-(\d+)$/.exec(range ?? '');
    const body = status === 206 && m ? bytes.slice(Number(m[1]), Number(m[2]) + 1) : bytes.slice();
    return { status: m && status === 206 ? 206 : 200, arrayBuffer: async () => body.buffer };
  };
  return { values, fetch, log };
}

describe('height rows over HTTP Range', () => {
  it('reads exactly the rows asked for, across block boundaries', async () => {
    const { values, fetch } = fakeServer(100, 7, (r, c) => r * 1000 + c);
    const h = createHeightRows({ url: 'h.f32', rows: 100, cols: 7, blockRows: 8, fetch });
    const out = await h.readRows(5, 21); // blocks 0, 1, 2
    expect(Array.from(out)).toEqual(Array.from(values.subarray(5 * 7, 21 * 7)));
    expect(h.stats.requests).toBe(3);
    expect(h.stats.bytesFetched).toBe(3 * 8 * 7 * 4);
  });

  it('asks the server only for the blocks a segment touches, once (LRU)', async () => {
    const { fetch, log } = fakeServer(1000, 50, (r, c) => r + c);
    const h = createHeightRows({ url: 'h.f32', rows: 1000, cols: 50, blockRows: 10, fetch });
    // rows 400.0 .. 430.0 at 100 µm per pixel: y from 40 mm to 43 mm
    await h.gridForSegment([1, 40], [4, 43], 100);
    // rows 400–431 (the last sample's bilinear neighbour included): blocks 40–43 of 2000 bytes
    expect(log).toEqual(['bytes=80000-81999', 'bytes=82000-83999', 'bytes=84000-85999', 'bytes=86000-87999']);
    await h.gridForSegment([1, 43], [4, 40], 100); // the same rows again: from the cache
    expect(h.stats.requests).toBe(4);
    expect(h.stats.bytesFetched).toBeLessThan(1000 * 50 * 4 / 10);
  });

  it('gives the same profile as the whole grid', async () => {
    const rows = 300;
    const cols = 40;
    const f = (r, c) => 50 * Math.sin(r / 7) + 3 * c + (r === 150 && c === 20 ? Number.NaN : 0);
    const { values, fetch } = fakeServer(rows, cols, f);
    const h = createHeightRows({ url: 'h.f32', rows, cols, blockRows: 16, fetch });
    const whole = { heightUm: values, rows, cols, pixelSizeUm: 50 };
    const a = [0.3, 6.1];
    const b = [1.7, 8.9];
    const ref = sampleProfile(whole, a, b);
    const part = await h.gridForSegment(a, b, 50);
    const got = sampleProfile(part.grid, part.start, part.end, { samples: ref.heightUm.length });
    expect(got.lengthMm).toBeCloseTo(ref.lengthMm, 12);
    for (let i = 0; i < ref.heightUm.length; i++) {
      if (Number.isNaN(ref.heightUm[i])) expect(got.heightUm[i]).toBeNaN();
      else expect(got.heightUm[i]).toBeCloseTo(ref.heightUm[i], 3);
    }
    expect(ref.heightUm.some(Number.isNaN)).toBe(true); // the hole at (150, 20) is on the line
  });

  it('keeps the cache within its byte budget, dropping the least recently used block', async () => {
    const { fetch } = fakeServer(64, 4, (r) => r);
    const blockBytes = 8 * 4 * 4;
    const h = createHeightRows({ url: 'h.f32', rows: 64, cols: 4, blockRows: 8, maxBytes: 2 * blockBytes, fetch });
    await h.readRows(0, 1); // block 0
    await h.readRows(8, 9); // block 1
    await h.readRows(0, 1); // block 0 again: most recent
    await h.readRows(16, 17); // block 2 evicts block 1
    expect(h.stats.blocksCached).toBe(2);
    await h.readRows(0, 1);
    expect(h.stats.requests).toBe(3);
    await h.readRows(8, 9);
    expect(h.stats.requests).toBe(4);
  });

  it('refuses a server that ignores Range (would send the whole file)', async () => {
    const { fetch } = fakeServer(16, 4, () => 1, { status: 200 });
    const h = createHeightRows({ url: 'h.f32', rows: 16, cols: 4, fetch });
    await expect(h.readRows(0, 2)).rejects.toThrow(/expected 206 Partial Content.*HTTP 200/);
  });

  it('rejects a bad shape', () => {
    expect(() => createHeightRows({ url: 'x', rows: 0, cols: 3 })).toThrow(/positive integers/);
  });
});
