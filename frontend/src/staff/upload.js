/**
 * Resumable upload of a scan bundle (POST /uploads, PUT /uploads/{id}/chunks?offset=N,
 * POST /uploads/{id}/complete; docs/architecture.md).
 *
 * The upload id is kept in localStorage under a key made of the tablet and the file's name,
 * size and modification time, so after a reload (or a lost connection) choosing the same file
 * again asks the server which byte ranges it already holds and sends only the rest. The
 * SHA-256 of the whole file is computed incrementally while the file is read chunk by chunk,
 * so even a many-gigabyte bundle never sits in memory at once.
 */
import { sha256 } from '@noble/hashes/sha2.js';
import { bytesToHex } from '@noble/hashes/utils.js';

const KEY_PREFIX = 'hammurabi.upload:';

/** localStorage key of an upload of `file` for `tabletId`. */
export function uploadKey(tabletId, file) {
  return `${KEY_PREFIX}${tabletId}:${file.name}:${file.size}:${file.lastModified ?? 0}`;
}

/** Uploads started in this browser and not finished: [{key, tabletId, name, size, id}]. */
export function pendingUploads(storage) {
  const out = [];
  for (let i = 0; i < storage.length; i++) {
    const key = storage.key(i);
    if (!key?.startsWith(KEY_PREFIX)) continue;
    const [tabletId, ...rest] = key.slice(KEY_PREFIX.length).split(':');
    const lastModified = rest.pop();
    const size = Number(rest.pop());
    out.push({ key, tabletId: Number(tabletId), name: rest.join(':'), size, lastModified, id: storage.getItem(key) });
  }
  return out;
}

/**
 * The chunks still to send: the complement of the received `ranges` ([start, end) pairs) in
 * [0, size), cut into pieces of at most `chunkSize` bytes aligned to multiples of chunkSize.
 * @returns {[number, number][]} [start, end) pairs in increasing order
 */
export function missingChunks(ranges, size, chunkSize) {
  if (!(chunkSize > 0)) throw new RangeError(`chunkSize must be > 0, got ${chunkSize}`);
  if (!(size >= 0)) throw new RangeError(`size must be ≥ 0, got ${size}`);
  const have = [...(ranges ?? [])].map(([a, b]) => [Math.max(0, a), Math.min(size, b)]).filter(([a, b]) => b > a);
  have.sort((x, y) => x[0] - y[0]);
  const out = [];
  for (let start = 0; start < size; start += chunkSize) {
    const end = Math.min(size, start + chunkSize);
    // Sub-pieces of this chunk not covered by any received range.
    let cursor = start;
    for (const [a, b] of have) {
      if (b <= cursor || a >= end) continue;
      if (a > cursor) out.push([cursor, a]);
      cursor = Math.max(cursor, b);
      if (cursor >= end) break;
    }
    if (cursor < end) out.push([cursor, end]);
  }
  return out;
}

/** Bytes covered by the ranges within [0, size). */
export function receivedBytes(ranges, size) {
  return size - missingChunks(ranges, size, Math.max(1, size)).reduce((n, [a, b]) => n + (b - a), 0);
}

/**
 * Upload a bundle file, resuming a previous attempt when there is one.
 * @param {object} options
 * @param {File|Blob} options.file (Blob needs a `name`)
 * @param {number} options.tabletId
 * @param {object} options.api the functions of src/api.js (injected for tests)
 * @param {Storage} options.storage localStorage
 * @param {(sent: number, total: number, note: string) => void} [options.onProgress]
 * @param {AbortSignal} [options.signal]
 * @returns {Promise<{scan: object, job: object, uploadId: string, resumed: boolean}>}
 */
export async function uploadBundle({ file, tabletId, api, storage, onProgress = () => {}, signal }) {
  const key = uploadKey(tabletId, file);
  let upload = null;
  let resumed = false;
  const known = storage.getItem(key);
  if (known) {
    try {
      upload = await api.getUpload(known);
      resumed = upload.state === 'open' || upload.state === undefined;
      if (!resumed) upload = null;
    } catch (err) {
      if (err.status !== 404 && err.status !== 410) throw err;
      upload = null;
    }
  }
  if (!upload) {
    upload = await api.createUpload({ tablet_id: tabletId, filename: file.name, size_bytes: file.size });
    storage.setItem(key, upload.id);
  }
  const size = file.size;
  const chunkSize = upload.chunk_size || 8 * 1024 * 1024;
  const todo = missingChunks(upload.ranges, size, chunkSize);
  let sent = receivedBytes(upload.ranges, size);
  onProgress(sent, size, resumed ? `resuming: ${sent} of ${size} bytes already on the server` : 'uploading');

  const hash = sha256.create();
  let todoIndex = 0;
  for (let start = 0; start < size; start += chunkSize) {
    if (signal?.aborted) throw new DOMException('upload paused', 'AbortError');
    const end = Math.min(size, start + chunkSize);
    const bytes = new Uint8Array(await file.slice(start, end).arrayBuffer());
    hash.update(bytes);
    while (todoIndex < todo.length && todo[todoIndex][0] < end) {
      const [a, b] = todo[todoIndex];
      await api.putChunk(upload.id, a, bytes.subarray(a - start, b - start), { signal });
      sent += b - a;
      onProgress(sent, size, 'uploading');
      todoIndex++;
    }
  }
  onProgress(size, size, 'checking the bundle');
  const result = await api.completeUpload(upload.id, bytesToHex(hash.digest()));
  storage.removeItem(key);
  return { ...result, uploadId: upload.id, resumed };
}
