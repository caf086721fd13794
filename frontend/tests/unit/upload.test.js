import { createHash } from 'node:crypto';
import { describe, expect, it } from 'vitest';
import { missingChunks, pendingUploads, receivedBytes, uploadBundle, uploadKey } from '../../src/staff/upload.js';

class MemoryStorage {
  constructor() {
    this.map = new Map();
  }
  get length() {
    return this.map.size;
  }
  key(i) {
    return [...this.map.keys()][i] ?? null;
  }
  getItem(k) {
    return this.map.has(k) ? this.map.get(k) : null;
  }
  setItem(k, v) {
    this.map.set(k, String(v));
  }
  removeItem(k) {
    this.map.delete(k);
  }
}

/** An in-memory server with the upload endpoints' semantics, recording every PUT. */
function fakeServer({ chunkSize, failAfterPuts = Infinity }) {
  const uploads = new Map();
  const puts = [];
  let n = 0;
  const merge = (ranges, a, b) => {
    const all = [...ranges, [a, b]].sort((x, y) => x[0] - y[0]);
    const out = [];
    for (const r of all) {
      if (out.length && r[0] <= out[out.length - 1][1]) out[out.length - 1][1] = Math.max(out[out.length - 1][1], r[1]);
      else out.push([...r]);
    }
    return out;
  };
  return {
    puts,
    uploads,
    api: {
      async createUpload({ tablet_id, filename, size_bytes }) {
        const id = `u${++n}`;
        const u = { id, tablet_id, filename, size_bytes, ranges: [], chunk_size: chunkSize, state: 'open', data: new Uint8Array(size_bytes) };
        uploads.set(id, u);
        return { id, size_bytes, received_bytes: 0, ranges: [], chunk_size: chunkSize };
      },
      async getUpload(id) {
        const u = uploads.get(id);
        if (!u) throw Object.assign(new Error('upload not found'), { status: 404 });
        return { id, ranges: u.ranges.map((r) => [...r]), chunk_size: chunkSize, state: u.state };
      },
      async putChunk(id, offset, bytes) {
        if (puts.length >= failAfterPuts) throw Object.assign(new Error('connection lost'), { status: 0 });
        const u = uploads.get(id);
        u.data.set(bytes, offset);
        u.ranges = merge(u.ranges, offset, offset + bytes.length);
        puts.push([offset, offset + bytes.length]);
      },
      async completeUpload(id, sha256) {
        const u = uploads.get(id);
        const actual = createHash('sha256').update(u.data).digest('hex');
        if (actual !== sha256) throw Object.assign(new Error('checksum mismatch'), { status: 422 });
        u.state = 'complete';
        return { scan: { id: 7 }, job: { id: 9, state: 'queued' } };
      },
    },
  };
}

function makeFile(size, seed = 1) {
  const bytes = new Uint8Array(size);
  let x = seed;
  for (let i = 0; i < size; i++) {
    x = (x * 1103515245 + 12345) >>> 0;
    bytes[i] = x >>> 24;
  }
  const blob = new Blob([bytes]);
  return Object.assign(blob, { name: 'bundle.zip', lastModified: 1700000000000 });
}

describe('missing chunks', () => {
  it('are the complement of the received ranges, cut at chunk boundaries', () => {
    expect(missingChunks([], 25, 10)).toEqual([[0, 10], [10, 20], [20, 25]]);
    expect(missingChunks([[0, 10], [20, 25]], 25, 10)).toEqual([[10, 20]]);
    expect(missingChunks([[3, 14]], 25, 10)).toEqual([[0, 3], [14, 20], [20, 25]]);
    expect(missingChunks([[0, 25]], 25, 10)).toEqual([]);
    expect(receivedBytes([[3, 14], [12, 16]], 25)).toBe(13);
  });
});

describe('resumable upload', () => {
  it('sends every byte once and completes with the right SHA-256', async () => {
    const server = fakeServer({ chunkSize: 1000 });
    const storage = new MemoryStorage();
    const file = makeFile(4500);
    const result = await uploadBundle({ file, tabletId: 3, api: server.api, storage });
    expect(result.job.id).toBe(9);
    expect(server.puts).toEqual([[0, 1000], [1000, 2000], [2000, 3000], [3000, 4000], [4000, 4500]]);
    expect(storage.length).toBe(0); // forgotten once complete
  });

  it('resumes after an interruption, sending only what the server lacks', async () => {
    const server = fakeServer({ chunkSize: 1000, failAfterPuts: 2 });
    const storage = new MemoryStorage();
    const file = makeFile(4500, 7);
    await expect(uploadBundle({ file, tabletId: 3, api: server.api, storage })).rejects.toThrow(/connection lost/);
    expect(pendingUploads(storage)).toEqual([
      { key: uploadKey(3, file), tabletId: 3, name: 'bundle.zip', size: 4500, lastModified: '1700000000000', id: 'u1' },
    ]);
    // "reload": a new call with the same file finds the upload id in storage
    const progress = [];
    const unlimited = fakeServer({ chunkSize: 1000 });
    unlimited.uploads.set('u1', server.uploads.get('u1'));
    const result = await uploadBundle({
      file,
      tabletId: 3,
      api: unlimited.api,
      storage,
      onProgress: (sent, total, note) => progress.push([sent, total, note]),
    });
    expect(result.resumed).toBe(true);
    expect(result.uploadId).toBe('u1');
    expect(unlimited.puts).toEqual([[2000, 3000], [3000, 4000], [4000, 4500]]);
    expect(progress[0]).toEqual([2000, 4500, 'resuming: 2000 of 4500 bytes already on the server']);
  });

  it('starts afresh when the server has forgotten the upload', async () => {
    const server = fakeServer({ chunkSize: 2048 });
    const storage = new MemoryStorage();
    const file = makeFile(3000);
    storage.setItem(uploadKey(5, file), 'gone');
    const result = await uploadBundle({ file, tabletId: 5, api: server.api, storage });
    expect(result.resumed).toBe(false);
    expect(server.puts).toEqual([[0, 2048], [2048, 3000]]);
  });
});
