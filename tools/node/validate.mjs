// Validate glTF / GLB files with the Khronos glTF validator (npm package `gltf-validator`).
// Usage: node tools/node/validate.mjs FILE.glb [FILE2.gltf ...]
// Prints one JSON report per file (one line each) on stdout; exit code 1 if any file has errors, 2 on bad usage.
import { readFile } from "node:fs/promises";
import path from "node:path";
import { validateBytes } from "gltf-validator";

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error("usage: node validate.mjs FILE.glb [...]");
  process.exit(2);
}
let failed = false;
for (const file of files) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 100,
    externalResourceFunction: async (uri) =>
      new Uint8Array(await readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)))),
  });
  if (report.issues.numErrors > 0) failed = true;
  console.log(JSON.stringify({ file, issues: report.issues, info: report.info }));
}
process.exit(failed ? 1 : 0);
