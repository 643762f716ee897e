// Point cloud files parsed in the browser: PLY (ascii, binary little/big endian), PCD (ascii, binary),
// XYZ (whitespace- or comma-separated text, x y z first), NPY ((N, 3) float32/float64, C order).
// Every parser returns a Float64Array of N*3 coordinates (x0 y0 z0 x1 ...). No DOM: node can import it.

export class CloudParseError extends Error {}

const decoder = new TextDecoder("latin1");

function finish(values, name) {
  if (values.length < 9 || values.length % 3 !== 0) {
    throw new CloudParseError(`${name}: needs at least 3 points of x, y, z`);
  }
  for (let i = 0; i < values.length; i++) {
    if (!Number.isFinite(values[i])) throw new CloudParseError(`${name}: contains NaN or infinite coordinates`);
  }
  return values;
}

// Header lines up to and including the line `terminator` (PLY: end_header); returns [lines, byte offset after].
function readHeader(bytes, name, isLast) {
  const lines = [];
  let start = 0;
  for (let i = 0; i < Math.min(bytes.length, 1 << 20); i++) {
    if (bytes[i] === 10) {
      const line = decoder.decode(bytes.subarray(start, i)).replace(/\r$/, "").trim();
      lines.push(line);
      start = i + 1;
      if (isLast(line)) return [lines, start];
    }
  }
  throw new CloudParseError(`${name}: header not terminated`);
}

const PLY_TYPES = {
  char: ["Int8", 1], int8: ["Int8", 1], uchar: ["Uint8", 1], uint8: ["Uint8", 1],
  short: ["Int16", 2], int16: ["Int16", 2], ushort: ["Uint16", 2], uint16: ["Uint16", 2],
  int: ["Int32", 4], int32: ["Int32", 4], uint: ["Uint32", 4], uint32: ["Uint32", 4],
  float: ["Float32", 4], float32: ["Float32", 4], double: ["Float64", 8], float64: ["Float64", 8],
};

export function parsePLY(buffer, name = "PLY") {
  const bytes = new Uint8Array(buffer);
  const [lines, offset] = readHeader(bytes, name, (l) => l === "end_header");
  if (lines[0] !== "ply") throw new CloudParseError(`${name}: not a PLY file (no 'ply' magic)`);
  const format = (lines.find((l) => l.startsWith("format ")) || "").split(/\s+/)[1];
  if (!["ascii", "binary_little_endian", "binary_big_endian"].includes(format)) {
    throw new CloudParseError(`${name}: unsupported PLY format ${format}`);
  }
  // Elements in file order, each with its properties (a list property: [count type, item type]).
  const elements = [];
  for (const l of lines) {
    const f = l.split(/\s+/);
    if (f[0] === "element") elements.push({ name: f[1], count: parseInt(f[2], 10), props: [] });
    else if (f[0] === "property" && elements.length) {
      const el = elements[elements.length - 1];
      if (f[1] === "list") el.props.push({ name: f[4], list: [f[2], f[3]] });
      else el.props.push({ name: f[2], type: f[1] });
    }
  }
  const vi = elements.findIndex((e) => e.name === "vertex");
  if (vi < 0) throw new CloudParseError(`${name}: no vertex element`);
  const vertex = elements[vi];
  const axes = ["x", "y", "z"].map((a) => vertex.props.findIndex((p) => p.name === a));
  if (axes.some((i) => i < 0)) throw new CloudParseError(`${name}: vertices have no x, y, z properties`);
  if (vertex.props.some((p) => p.list)) throw new CloudParseError(`${name}: list properties on vertices`);
  for (const p of vertex.props) {
    if (!PLY_TYPES[p.type]) throw new CloudParseError(`${name}: unknown property type ${p.type}`);
  }
  const n = vertex.count;
  const out = new Float64Array(n * 3);
  if (format === "ascii") {
    const text = decoder.decode(bytes.subarray(offset));
    const rows = text.split(/\r?\n/).filter((l) => l.trim() !== "");
    let row = elements.slice(0, vi).reduce((s, e) => s + e.count, 0); // elements before the vertices
    for (let i = 0; i < n; i++, row++) {
      if (row >= rows.length) throw new CloudParseError(`${name}: ${n} vertices declared, fewer found`);
      const f = rows[row].trim().split(/\s+/);
      for (let k = 0; k < 3; k++) out[3 * i + k] = Number(f[axes[k]]);
    }
    return finish(out, name);
  }
  const little = format === "binary_little_endian";
  const view = new DataView(buffer);
  let pos = offset;
  // Skip the elements before the vertices (fixed-size properties only, or lists read one by one).
  for (const el of elements.slice(0, vi)) {
    for (let j = 0; j < el.count; j++) {
      for (const p of el.props) {
        if (p.list) {
          const [ct, it] = [PLY_TYPES[p.list[0]], PLY_TYPES[p.list[1]]];
          const count = view[`get${ct[0]}`](pos, little);
          pos += ct[1] + count * it[1];
        } else pos += PLY_TYPES[p.type][1];
      }
    }
  }
  const offsets = [];
  let stride = 0;
  for (const p of vertex.props) {
    offsets.push(stride);
    stride += PLY_TYPES[p.type][1];
  }
  if (pos + n * stride > buffer.byteLength) throw new CloudParseError(`${name}: file shorter than its header says`);
  const getters = axes.map((a) => `get${PLY_TYPES[vertex.props[a].type][0]}`);
  for (let i = 0; i < n; i++, pos += stride) {
    for (let k = 0; k < 3; k++) out[3 * i + k] = view[getters[k]](pos + offsets[axes[k]], little);
  }
  return finish(out, name);
}

export function parseXYZ(buffer, name = "XYZ") {
  const text = decoder.decode(new Uint8Array(buffer));
  const values = [];
  for (const line of text.split(/\r?\n/)) {
    const t = line.trim();
    if (!t || t.startsWith("#") || t.startsWith("//")) continue;
    const f = t.split(/[\s,;]+/);
    if (f.length < 3) throw new CloudParseError(`${name}: a line with fewer than 3 numbers: '${t.slice(0, 40)}'`);
    for (let k = 0; k < 3; k++) {
      const v = Number(f[k]);
      if (Number.isNaN(v)) throw new CloudParseError(`${name}: not a number: '${f[k].slice(0, 20)}'`);
      values.push(v);
    }
  }
  return finish(Float64Array.from(values), name);
}

const PCD_TYPES = { F4: ["Float32", 4], F8: ["Float64", 8], I1: ["Int8", 1], U1: ["Uint8", 1], I2: ["Int16", 2],
  U2: ["Uint16", 2], I4: ["Int32", 4], U4: ["Uint32", 4] };

export function parsePCD(buffer, name = "PCD") {
  const bytes = new Uint8Array(buffer);
  const [lines, offset] = readHeader(bytes, name, (l) => l.startsWith("DATA"));
  const header = {};
  for (const l of lines) {
    if (!l || l.startsWith("#")) continue;
    const [key, ...rest] = l.split(/\s+/);
    header[key.toUpperCase()] = rest;
  }
  const fields = header.FIELDS || [];
  const sizes = (header.SIZE || []).map(Number);
  const types = header.TYPE || [];
  const counts = (header.COUNT || fields.map(() => "1")).map(Number);
  const n = Number((header.POINTS || [header.WIDTH?.[0] * (header.HEIGHT?.[0] || 1)])[0]);
  const axes = ["x", "y", "z"].map((a) => fields.indexOf(a));
  if (axes.some((i) => i < 0)) throw new CloudParseError(`${name}: no x, y, z fields`);
  const data = (header.DATA || [])[0];
  const out = new Float64Array(n * 3);
  // Column of each field in a row (fields with COUNT > 1 take several columns).
  const columns = [];
  let col = 0;
  for (let i = 0; i < fields.length; i++) {
    columns.push(col);
    col += counts[i] || 1;
  }
  if (data === "ascii") {
    const rows = decoder.decode(bytes.subarray(offset)).split(/\r?\n/).filter((l) => l.trim() !== "");
    if (rows.length < n) throw new CloudParseError(`${name}: ${n} points declared, ${rows.length} found`);
    for (let i = 0; i < n; i++) {
      const f = rows[i].trim().split(/\s+/);
      for (let k = 0; k < 3; k++) out[3 * i + k] = Number(f[columns[axes[k]]]);
    }
  } else if (data === "binary") {
    const view = new DataView(buffer);
    const byteOffsets = [];
    let stride = 0;
    for (let i = 0; i < fields.length; i++) {
      byteOffsets.push(stride);
      stride += sizes[i] * (counts[i] || 1);
    }
    if (offset + n * stride > buffer.byteLength) throw new CloudParseError(`${name}: file shorter than its header`);
    const getters = axes.map((a) => {
      const t = PCD_TYPES[`${types[a]}${sizes[a]}`];
      if (!t) throw new CloudParseError(`${name}: unsupported field type ${types[a]}${sizes[a]}`);
      return `get${t[0]}`;
    });
    for (let i = 0; i < n; i++) {
      const base = offset + i * stride;
      for (let k = 0; k < 3; k++) out[3 * i + k] = view[getters[k]](base + byteOffsets[axes[k]], true);
    }
  } else {
    throw new CloudParseError(`${name}: PCD DATA ${data} is not supported (use ascii or binary)`);
  }
  // Organized clouds mark missing points with NaN: drop them.
  const kept = [];
  for (let i = 0; i < n; i++) {
    const [x, y, z] = [out[3 * i], out[3 * i + 1], out[3 * i + 2]];
    if (Number.isFinite(x) && Number.isFinite(y) && Number.isFinite(z)) kept.push(x, y, z);
  }
  return finish(Float64Array.from(kept), name);
}

export function parseNPY(buffer, name = "NPY") {
  const bytes = new Uint8Array(buffer);
  if (bytes[0] !== 0x93 || decoder.decode(bytes.subarray(1, 6)) !== "NUMPY") {
    throw new CloudParseError(`${name}: not a .npy file`);
  }
  const view = new DataView(buffer);
  const major = bytes[6];
  const headerLen = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
  const start = major === 1 ? 10 : 12;
  const header = decoder.decode(bytes.subarray(start, start + headerLen));
  const descr = /'descr':\s*'([^']+)'/.exec(header)?.[1];
  const fortran = /'fortran_order':\s*True/.test(header);
  const shape = (/'shape':\s*\(([^)]*)\)/.exec(header)?.[1] || "").split(",").filter((s) => s.trim()).map(Number);
  if (fortran || shape.length !== 2 || shape[1] !== 3) {
    throw new CloudParseError(`${name}: expected a C-order (N, 3) array, got shape (${shape}) ${fortran ? "F" : "C"}`);
  }
  const types = { "<f4": ["Float32", 4], "<f8": ["Float64", 8], ">f4": ["Float32", 4], ">f8": ["Float64", 8] };
  const t = types[descr];
  if (!t) throw new CloudParseError(`${name}: unsupported dtype ${descr} (use float32 or float64)`);
  const little = descr[0] === "<";
  const n = shape[0] * 3;
  const offset = start + headerLen;
  if (offset + n * t[1] > buffer.byteLength) throw new CloudParseError(`${name}: file shorter than its header`);
  const out = new Float64Array(n);
  for (let i = 0; i < n; i++) out[i] = view[`get${t[0]}`](offset + i * t[1], little);
  return finish(out, name);
}

export const SUFFIXES = [".ply", ".pcd", ".xyz", ".txt", ".pts", ".npy"];

// File name + contents -> Float64Array of N*3 coordinates, by the file's suffix.
export function parseCloud(name, buffer) {
  const lower = name.toLowerCase();
  if (lower.endsWith(".ply")) return parsePLY(buffer, name);
  if (lower.endsWith(".pcd")) return parsePCD(buffer, name);
  if (lower.endsWith(".npy")) return parseNPY(buffer, name);
  if ([".xyz", ".txt", ".pts"].some((s) => lower.endsWith(s))) return parseXYZ(buffer, name);
  throw new CloudParseError(`${name}: unsupported file type; use one of ${SUFFIXES.join(", ")}`);
}

// N*3 coordinates -> the service's compact encoding: base64 of little-endian float32.
export function encodeCloud(values) {
  const bytes = new Uint8Array(values.length * 4);
  const view = new DataView(bytes.buffer);
  for (let i = 0; i < values.length; i++) view.setFloat32(4 * i, values[i], true);
  let binary = "";
  for (let i = 0; i < bytes.length; i += 0x8000) {
    binary += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  }
  return { encoding: "base64-float32-le", data: btoa(binary) };
}
