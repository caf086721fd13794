/**
 * Screenshots a scholar can publish: the scale bar drawn into the pixels and what the image
 * shows written into the PNG as text chunks (iTXt, UTF-8: PNG 1.2 §4.2.3.3), readable with
 * `exiftool`, `identify -verbose` or Pillow's `Image.open(f).text`. Pure functions on bytes
 * and numbers, plus one that draws on a 2-D canvas context.
 */
import { niceStep } from './profile.js';

/**
 * Millimetres per pixel of a screenshot of `shotW` × `shotH` taken from a canvas of
 * `canvasW` × `canvasH` showing `mmPerScreenPx`: the viewer's screenshot keeps the vertical
 * extent unless the shot is narrower than the canvas, which grows both ("contain").
 */
export function shotMmPerPixel({ mmPerScreenPx, canvasW, canvasH, shotW, shotH }) {
  const grow = Math.max(1, canvasW / canvasH / (shotW / shotH));
  return (mmPerScreenPx * canvasH * grow) / shotH;
}

const CRC_TABLE = (() => {
  const table = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    table[n] = c >>> 0;
  }
  return table;
})();

/** CRC-32 of PNG chunks (ISO 3309, as in PNG 1.2 §3.4). */
export function crc32(bytes) {
  let c = 0xffffffff;
  for (const b of bytes) c = CRC_TABLE[(c ^ b) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

function chunk(type, data) {
  const out = new Uint8Array(12 + data.length);
  const view = new DataView(out.buffer);
  view.setUint32(0, data.length);
  out.set(new TextEncoder().encode(type), 4);
  out.set(data, 8);
  view.setUint32(8 + data.length, crc32(out.subarray(4, 8 + data.length)));
  return out;
}

/** An iTXt chunk: keyword (Latin-1, 1-79 bytes), no compression, UTF-8 text. */
export function itxtChunk(keyword, text) {
  if (!/^[\x20-\x7e]{1,79}$/.test(keyword)) throw new RangeError(`bad PNG keyword ${JSON.stringify(keyword)}`);
  const enc = new TextEncoder();
  const body = [...enc.encode(keyword), 0, 0, 0, 0, 0, ...enc.encode(String(text))];
  return chunk('iTXt', new Uint8Array(body));
}

/**
 * `png` (bytes of a PNG file) with an iTXt chunk per entry inserted after IHDR.
 * @param {Uint8Array} png
 * @param {Record<string, string|null|undefined>} entries empty values are left out
 */
export function pngWithText(png, entries) {
  const signature = [137, 80, 78, 71, 13, 10, 26, 10];
  if (png.length < 33 || signature.some((b, i) => png[i] !== b)) throw new Error('not a PNG file');
  const ihdrEnd = 8 + 12 + new DataView(png.buffer, png.byteOffset).getUint32(8);
  const chunks = Object.entries(entries)
    .filter(([, v]) => v != null && v !== '')
    .map(([k, v]) => itxtChunk(k, v));
  const size = png.length + chunks.reduce((n, c) => n + c.length, 0);
  const out = new Uint8Array(size);
  out.set(png.subarray(0, ihdrEnd), 0);
  let at = ihdrEnd;
  for (const c of chunks) {
    out.set(c, at);
    at += c.length;
  }
  out.set(png.subarray(ihdrEnd), at);
  return out;
}

/** Text chunks of a PNG (iTXt, uncompressed) as {keyword: text}: for tests and checks. */
export function pngText(png) {
  const view = new DataView(png.buffer, png.byteOffset);
  const dec = new TextDecoder();
  const found = {};
  for (let at = 8; at + 8 <= png.length; ) {
    const length = view.getUint32(at);
    const type = dec.decode(png.subarray(at + 4, at + 8));
    if (type === 'iTXt') {
      const data = png.subarray(at + 8, at + 8 + length);
      const zero = data.indexOf(0);
      let p = zero + 3;
      p = data.indexOf(0, p) + 1; // language tag
      p = data.indexOf(0, p) + 1; // translated keyword
      found[dec.decode(data.subarray(0, zero))] = dec.decode(data.subarray(p));
    }
    at += 12 + length;
  }
  return found;
}

/**
 * Draw a scale bar (white bar with a dark outline and its length) at the bottom left of a
 * `width` × `height` image whose pixels are `mmPerPx` millimetres; returns the bar's length
 * in mm (null when the scale is unknown, and nothing is drawn).
 */
export function drawScaleBar(ctx, { width, height, mmPerPx }) {
  if (!(mmPerPx > 0)) return null;
  const mm = niceStep(mmPerPx * width * 0.2);
  const barPx = mm / mmPerPx;
  const unit = Math.max(2, Math.round(height / 150));
  const x = 6 * unit;
  const y = height - 8 * unit;
  ctx.save();
  ctx.fillStyle = '#000';
  ctx.fillRect(x - 1, y - 1, barPx + 2, unit * 1.5 + 2);
  ctx.fillStyle = '#fff';
  ctx.fillRect(x, y, barPx, unit * 1.5);
  ctx.font = `${6 * unit}px sans-serif`;
  ctx.lineWidth = unit;
  ctx.strokeStyle = '#000';
  const label = mm >= 1 ? `${mm} mm` : `${Math.round(mm * 1000)} µm`;
  ctx.strokeText(label, x, y - 2 * unit);
  ctx.fillText(label, x, y - 2 * unit);
  ctx.restore();
  return mm;
}

/**
 * The viewer's screenshot `blob` with the scale bar drawn in and `text` written as PNG
 * text chunks (browser only: decodes and re-encodes through a 2-D canvas).
 * @returns {Promise<{blob: Blob, scaleMm: number|null}>}
 */
export async function annotateScreenshot(blob, { mmPerPx, text }) {
  const bitmap = await createImageBitmap(blob);
  const canvas = document.createElement('canvas');
  canvas.width = bitmap.width;
  canvas.height = bitmap.height;
  const ctx = canvas.getContext('2d');
  ctx.drawImage(bitmap, 0, 0);
  bitmap.close?.();
  const scaleMm = drawScaleBar(ctx, { width: canvas.width, height: canvas.height, mmPerPx });
  const drawn = await new Promise((resolve, reject) =>
    canvas.toBlob((b) => (b ? resolve(b) : reject(new Error('the browser could not encode the PNG'))), 'image/png'),
  );
  const entries = { ...text };
  if (scaleMm != null) entries['Scale'] = `${scaleMm} mm bar; ${mmPerPx.toPrecision(6)} mm per pixel`;
  const bytes = pngWithText(new Uint8Array(await drawn.arrayBuffer()), entries);
  return { blob: new Blob([bytes], { type: 'image/png' }), scaleMm };
}
