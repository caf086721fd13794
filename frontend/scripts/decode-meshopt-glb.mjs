// Decode the EXT_meshopt_compression streams of GLB files with meshoptimizer's own decoder
// (the one three.js ships and its GLTFLoader uses) and print, per file, each accessor's
// decoded values as a JSON list (used by the Python tests of worker/tiles: the Khronos
// validator cannot read this extension, so the geometry is checked after decoding here).
import { readFile } from 'node:fs/promises';
import { MeshoptDecoder } from 'three/examples/jsm/libs/meshopt_decoder.module.js';

const EXT = 'EXT_meshopt_compression';
const COMPONENTS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };
const ARRAYS = { 5126: Float32Array, 5125: Uint32Array, 5123: Uint16Array };

function chunks(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  if (view.getUint32(0, true) !== 0x46546c67) throw new Error('not a GLB');
  const jsonLength = view.getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
  const binStart = 20 + jsonLength + 8;
  const binLength = view.getUint32(20 + jsonLength, true);
  return { json, bin: bytes.subarray(binStart, binStart + binLength) };
}

await MeshoptDecoder.ready;
const out = [];
for (const file of process.argv.slice(2)) {
  const { json, bin } = chunks(new Uint8Array(await readFile(file)));
  const accessors = json.accessors.map((acc) => {
    const view = json.bufferViews[acc.bufferView];
    const ext = view.extensions?.[EXT];
    if (!ext) return null;
    const target = new Uint8Array(ext.count * ext.byteStride);
    const source = bin.subarray(ext.byteOffset, ext.byteOffset + ext.byteLength);
    MeshoptDecoder.decodeGltfBuffer(target, ext.count, ext.byteStride, source, ext.mode, ext.filter);
    const Arr = ARRAYS[acc.componentType];
    const values = new Arr(target.buffer, 0, acc.count * COMPONENTS[acc.type]);
    return { count: acc.count, type: acc.type, values: Array.from(values) };
  });
  out.push({ file, accessors });
}
console.log(JSON.stringify(out));
