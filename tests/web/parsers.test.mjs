// service/static/parsers.js in node: every file of a manifest (written by test_viewer.py) parses to the
// expected points, every "bad" file to a CloudParseError. Usage: node parsers.test.mjs MANIFEST.json
import { readFileSync } from "node:fs";
import { CloudParseError, encodeCloud, parseCloud } from "../../service/static/parsers.js";

const manifest = JSON.parse(readFileSync(process.argv[2], "utf8"));
const problems = [];
const toBuffer = (path) => {
  const b = readFileSync(path);
  return b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength);
};
for (const f of manifest.good) {
  try {
    const v = parseCloud(f.name, toBuffer(f.path));
    const n = v.length / 3;
    if (n !== f.points.length) problems.push(`${f.name}: ${n} points, expected ${f.points.length}`);
    for (let i = 0; i < Math.min(n, f.points.length); i++) {
      for (let k = 0; k < 3; k++) {
        if (Math.abs(v[3 * i + k] - f.points[i][k]) > f.atol) {
          problems.push(`${f.name}: point ${i} is ${[...v.slice(3 * i, 3 * i + 3)]}, expected ${f.points[i]}`);
          i = n;
          break;
        }
      }
    }
  } catch (e) {
    problems.push(`${f.name}: ${e.message}`);
  }
}
for (const f of manifest.bad) {
  try {
    parseCloud(f.name, toBuffer(f.path));
    problems.push(`${f.name}: parsed, expected an error`);
  } catch (e) {
    if (!(e instanceof CloudParseError)) problems.push(`${f.name}: ${e.constructor.name} ${e.message}`);
    else if (f.match && !e.message.includes(f.match)) problems.push(`${f.name}: message '${e.message}'`);
  }
}
// The compact encoding: base64 of little-endian float32.
const enc = encodeCloud(Float64Array.from([1, -2.5, 3, 0.25, 1e6, -7]));
if (enc.encoding !== "base64-float32-le" || enc.data !== manifest.encoded) problems.push(`encoding: ${enc.data}`);
console.log(JSON.stringify({ ok: problems.length === 0, problems, files: manifest.good.length + manifest.bad.length }));
process.exitCode = problems.length ? 1 : 0;
