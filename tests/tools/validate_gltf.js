#!/usr/bin/env node
// Validates one .gltf or .glb file with the Khronos glTF-Validator.
// Prints the report as JSON; exits 1 on any error (or if the file cannot be read), else 0.
// Usage: node tests/tools/validate_gltf.js FILE
'use strict';
const fs = require('fs');
const path = require('path');
const validator = require('gltf-validator');

const file = process.argv[2];
if (!file) {
  console.error('usage: validate_gltf.js FILE');
  process.exit(2);
}
const bytes = new Uint8Array(fs.readFileSync(file));
validator
  .validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 0,
    // Willow writes self-contained files: any external resource is itself an error.
    externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
  })
  .then((report) => {
    console.log(JSON.stringify(report, null, 2));
    process.exit(report.issues.numErrors > 0 ? 1 : 0);
  })
  .catch((err) => {
    console.error(`validation failed: ${err}`);
    process.exit(1);
  });
