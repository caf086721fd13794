/**
 * Reader for NumPy's .npy format (versions 1–3), enough for the model's `height.npy`
 * (float32 µm, NaN outside the tablet). Spec: numpy.lib.format.
 */

const MAGIC = [0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59]; // "\x93NUMPY"

const DTYPES = {
  '<f4': Float32Array,
  '<f8': Float64Array,
  '|u1': Uint8Array,
  '|i1': Int8Array,
  '|b1': Uint8Array,
  '<u2': Uint16Array,
  '<i2': Int16Array,
  '<u4': Uint32Array,
  '<i4': Int32Array,
};

/**
 * Parse an .npy file.
 * @param {ArrayBuffer} buffer the file's bytes
 * @returns {{shape: number[], dtype: string, data: Float32Array|Float64Array|Uint8Array|Uint16Array|Int32Array}}
 *   data in C order (row-major), a view on a copy of the payload
 */
export function parseNpy(buffer) {
  if (!(buffer instanceof ArrayBuffer)) throw new TypeError('buffer must be an ArrayBuffer');
  const bytes = new Uint8Array(buffer);
  if (bytes.length < 10 || MAGIC.some((b, i) => bytes[i] !== b)) {
    throw new Error('not a .npy file (bad magic string)');
  }
  const major = bytes[6];
  const view = new DataView(buffer);
  let headerLen;
  let offset;
  if (major === 1) {
    headerLen = view.getUint16(8, true);
    offset = 10;
  } else if (major === 2 || major === 3) {
    headerLen = view.getUint32(8, true);
    offset = 12;
  } else {
    throw new Error(`unsupported .npy version ${major}`);
  }
  const header = new TextDecoder(major === 3 ? 'utf-8' : 'latin1').decode(
    bytes.subarray(offset, offset + headerLen),
  );
  const descr = /'descr'\s*:\s*'([^']+)'/.exec(header)?.[1];
  const fortran = /'fortran_order'\s*:\s*(True|False)/.exec(header)?.[1];
  const shapeText = /'shape'\s*:\s*\(([^)]*)\)/.exec(header)?.[1];
  if (!descr || !fortran || shapeText === undefined) throw new Error(`bad .npy header: ${header}`);
  if (fortran === 'True') throw new Error('Fortran-ordered .npy arrays are not supported');
  const Type = DTYPES[descr];
  if (!Type) throw new Error(`unsupported .npy dtype ${descr}`);
  const shape = shapeText
    .split(',')
    .map((s) => s.trim())
    .filter((s) => s.length > 0)
    .map(Number);
  const count = shape.reduce((a, b) => a * b, 1);
  const start = offset + headerLen;
  const nbytes = count * Type.BYTES_PER_ELEMENT;
  if (bytes.length < start + nbytes) throw new Error('truncated .npy file');
  // Copy so the typed array is aligned whatever the header length.
  const data = new Type(buffer.slice(start, start + nbytes));
  return { shape, dtype: descr, data };
}

/**
 * Encode a float32 array as .npy version 1.0 (used by tests and for exporting profiles).
 * @param {Float32Array} data C-order values
 * @param {number[]} shape
 * @returns {ArrayBuffer}
 */
export function encodeNpyFloat32(data, shape) {
  const count = shape.reduce((a, b) => a * b, 1);
  if (data.length !== count) throw new RangeError(`data has ${data.length} values, shape needs ${count}`);
  const shapeText = shape.length === 1 ? `(${shape[0]},)` : `(${shape.join(', ')})`;
  let header = `{'descr': '<f4', 'fortran_order': False, 'shape': ${shapeText}, }`;
  const pad = 64 - ((10 + header.length + 1) % 64);
  header = header + ' '.repeat(pad % 64) + '\n';
  const out = new Uint8Array(10 + header.length + data.byteLength);
  out.set(MAGIC, 0);
  out[6] = 1;
  out[7] = 0;
  new DataView(out.buffer).setUint16(8, header.length, true);
  for (let i = 0; i < header.length; i++) out[10 + i] = header.charCodeAt(i);
  out.set(new Uint8Array(data.buffer, data.byteOffset, data.byteLength), 10 + header.length);
  return out.buffer;
}
