// Validate glTF/GLB files with the Khronos glTF validator; prints one JSON report per file
// (a JSON list) and exits 1 if any has an error. Used by the Python tests of model.glb.
import { readFile } from 'node:fs/promises';
import { validateBytes } from 'gltf-validator';

const files = process.argv.slice(2);
if (!files.length) {
  console.error('usage: node scripts/validate-gltf.mjs FILE.glb [...]');
  process.exit(2);
}
const reports = [];
for (const file of files) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validateBytes(bytes, { maxIssues: 100 });
  reports.push({ file, ...report });
}
console.log(JSON.stringify(reports));
process.exit(reports.some((r) => r.issues.numErrors > 0) ? 1 : 0);
