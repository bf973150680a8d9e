// Validates one .glb with the Khronos glTF validator and prints its report's issue counts as one
// JSON line: {"errors":N,"warnings":N,"infos":N,"hints":N,"messages":[...]} (messages: every
// error and warning, code + pointer + text). Exit 0 if the validator ran (whatever it found),
// 2 if it could not run. Usage: node validate.js FILE.glb
'use strict';
const fs = require('fs');
const validator = require('gltf-validator');

const file = process.argv[2];
if (!file) {
  console.error('usage: node validate.js FILE.glb');
  process.exit(2);
}
const bytes = new Uint8Array(fs.readFileSync(file));
validator
  .validateBytes(bytes, { maxIssues: 0, writeTimestamp: false })
  .then((report) => {
    const i = report.issues;
    const messages = i.messages
      .filter((m) => m.severity <= 1)
      .map((m) => ({ severity: m.severity, code: m.code, pointer: m.pointer, message: m.message }));
    console.log(JSON.stringify({
      errors: i.numErrors,
      warnings: i.numWarnings,
      infos: i.numInfos,
      hints: i.numHints,
      messages,
    }));
  })
  .catch((e) => {
    console.error('validator failed: ' + e);
    process.exit(2);
  });
