// Validates a .glb with Khronos' glTF-Validator and prints its report's
// issues as JSON (tests/splats.rs reads them). Usage: node validate-gltf.mjs FILE.glb
import fs from 'node:fs';
import validator from 'gltf-validator';

const bytes = new Uint8Array(fs.readFileSync(process.argv[2]));
const report = await validator.validateBytes(bytes, { maxIssues: 1000, writeTimestamp: false });
console.log(JSON.stringify(report.issues));
