#!/usr/bin/env node
// Validates one glTF/GLB file with the Khronos glTF-Validator and prints its JSON report.
// Usage: node tests/js/validate_gltf.mjs FILE.glb
// Exit status: 0 when the report has no errors, 1 when it has, 2 on bad usage or unreadable input.
import { readFile } from "node:fs/promises";
import { basename } from "node:path";
import { validateBytes } from "gltf-validator";

async function main(argv) {
  if (argv.length !== 1) {
    console.error("usage: validate_gltf.mjs FILE.glb");
    return 2;
  }
  const path = argv[0];
  let bytes;
  try {
    bytes = new Uint8Array(await readFile(path));
  } catch (err) {
    console.error(`validate_gltf: cannot read ${path}: ${err.message}`);
    return 2;
  }
  let report;
  try {
    // External resources are refused: our GLB files are self-contained.
    report = await validateBytes(bytes, {
      uri: basename(path),
      maxIssues: 100,
      externalResourceFunction: (uri) => Promise.reject(`external resource ${uri} not allowed`),
    });
  } catch (err) {
    console.error(`validate_gltf: ${path} is not glTF: ${err}`);
    return 2;
  }
  process.stdout.write(JSON.stringify(report, null, 2) + "\n");
  return report.issues.numErrors === 0 ? 0 : 1;
}

process.exitCode = await main(process.argv.slice(2));
