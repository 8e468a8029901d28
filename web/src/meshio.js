// Mesh files in the browser, read the way the server numbers vertices (docs/formats.md, "Files
// keep the user's numbering"): frames carry positions per *file vertex*, so every model here says how
// its render vertices map to file vertices.
//
// A model is
//   { fileVertexCount, filePositions: Float32Array (3 per file vertex, as read),
//     parts: [{ gather: Uint32Array (render vertex -> file vertex), index: Uint32Array,
//               uv: Float32Array | null, matrix: number[16] | null (column-major, world) ,
//               image: number | null (index into images) }],
//     images: [Blob], uvFlipY: bool (OBJ: v runs up, the image must be flipped),
//     groups: Map(name -> Set of file vertices) }: the file's named groups of faces as the
//     server reads them for `{"group": name}` regions (OBJ `g`/`o` names, glTF node and mesh
//     names), each the corners of its faces, in order of first appearance; names without a
//     face are left out, as the server leaves them out.
// Connectivity and UVs never change during a flow: frames only move file vertices.

/** Parse OBJ text: `v` lines in order are the file vertices, (v, vt) pairs the render vertices. */
export function parseObj(text) {
  const filePos = [];
  const uvs = [];
  const corners = []; // v, vt (-1: none), per triangle corner
  // The groups the next faces go to: those of the last `g` line and of the last `o` line.
  const groups = new Map();
  let currentG = [];
  let currentO = null;
  let line = 0;
  let start = 0;
  const n = text.length;
  while (start < n) {
    let end = text.indexOf('\n', start);
    if (end < 0) end = n;
    line++;
    const c0 = text.charCodeAt(start);
    const c1 = text.charCodeAt(start + 1);
    if (c0 === 118 /* v */ && (c1 === 32 || c1 === 9)) {
      const t = text.slice(start + 2, end).trim().split(/\s+/);
      const x = +t[0], y = +t[1], z = +t[2];
      if (!(Number.isFinite(x) && Number.isFinite(y) && Number.isFinite(z))) {
        throw new Error(`OBJ line ${line}: a \`v\` line needs three numbers`);
      }
      filePos.push(x, y, z);
    } else if (c0 === 118 && c1 === 116 /* vt */) {
      const t = text.slice(start + 3, end).trim().split(/\s+/);
      uvs.push(+t[0] || 0, +t[1] || 0);
    } else if (c0 === 102 /* f */ && (c1 === 32 || c1 === 9)) {
      const t = text.slice(start + 2, end).trim().split(/\s+/);
      const nv = filePos.length / 3;
      const nt = uvs.length / 2;
      const vs = [];
      for (const w of t) {
        if (!w) continue;
        const parts = w.split('/');
        let v = parseInt(parts[0], 10);
        let vt = parts.length > 1 && parts[1] !== '' ? parseInt(parts[1], 10) : 0;
        v = v < 0 ? nv + v : v - 1;
        vt = vt < 0 ? nt + vt : vt - 1;
        if (!(v >= 0 && v < nv)) throw new Error(`OBJ line ${line}: face index out of range`);
        vs.push(v, vt >= 0 && vt < nt ? vt : -1);
      }
      // Fan triangulation of polygons (the server's own reading of faces decides validity).
      for (let k = 2; k < vs.length / 2; k++) {
        corners.push(vs[0], vs[1], vs[2 * k - 2], vs[2 * k - 1], vs[2 * k], vs[2 * k + 1]);
      }
      if (vs.length >= 6) {
        for (const name of currentO === null ? currentG : [...currentG, currentO]) {
          const set = groups.get(name);
          for (let k = 0; k < vs.length; k += 2) set.add(vs[k]);
        }
      }
    } else if (c0 === 103 /* g */ && (c1 === 32 || c1 === 9 || c1 === 13 || start + 1 === end)) {
      // `g a b`: the faces that follow belong to a and b (a bare `g`: to no group). Names are
      // listed in the order their lines first appear, as the server lists them.
      currentG = text.slice(start + 1, end).trim().split(/\s+/).filter((w) => w !== '');
      for (const name of currentG) if (!groups.has(name)) groups.set(name, new Set());
    } else if (c0 === 111 /* o */ && (c1 === 32 || c1 === 9 || c1 === 13 || start + 1 === end)) {
      const name = text.slice(start + 1, end).trim();
      currentO = name === '' ? null : name;
      if (currentO !== null && !groups.has(name)) groups.set(name, new Set());
    }
    start = end + 1;
  }
  if (corners.length === 0) throw new Error('the OBJ file has no faces');
  for (const [name, set] of groups) if (set.size === 0) groups.delete(name);
  const nt = uvs.length / 2;
  const keyOf = new Map();
  const gather = [];
  const uv = [];
  const index = new Uint32Array(corners.length / 2);
  let hasUv = false;
  for (let c = 0; c < corners.length; c += 2) {
    const v = corners[c], t = corners[c + 1];
    const key = v * (nt + 1) + (t + 1);
    let r = keyOf.get(key);
    if (r === undefined) {
      r = gather.length;
      keyOf.set(key, r);
      gather.push(v);
      if (t >= 0) { uv.push(uvs[2 * t], uvs[2 * t + 1]); hasUv = true; } else uv.push(0, 0);
    }
    index[c / 2] = r;
  }
  return {
    fileVertexCount: filePos.length / 3,
    filePositions: new Float32Array(filePos),
    parts: [{ gather: Uint32Array.from(gather), index, uv: hasUv ? new Float32Array(uv) : null, matrix: null, image: null }],
    images: [],
    uvFlipY: true,
    groups,
  };
}

const GLB_MAGIC = 0x46546c67; // "glTF"
const CHUNK_JSON = 0x4e4f534a;
const CHUNK_BIN = 0x004e4942;

/** Parse a GLB (ArrayBuffer) or glTF JSON (text with data: URIs). */
export function parseGltf(data) {
  let json;
  let bin = null;
  if (data instanceof ArrayBuffer) {
    const dv = new DataView(data);
    if (dv.byteLength >= 12 && dv.getUint32(0, true) === GLB_MAGIC) {
      const version = dv.getUint32(4, true);
      if (version !== 2) throw new Error(`GLB version ${version}: only glTF 2.0 is read`);
      let off = 12;
      while (off + 8 <= dv.byteLength) {
        const len = dv.getUint32(off, true);
        const type = dv.getUint32(off + 4, true);
        const body = new Uint8Array(data, off + 8, len);
        if (type === CHUNK_JSON) json = JSON.parse(new TextDecoder().decode(body));
        else if (type === CHUNK_BIN && bin === null) bin = body;
        off += 8 + len + ((4 - (len % 4)) % 4);
      }
      if (!json) throw new Error('the GLB file has no JSON chunk');
    } else {
      json = JSON.parse(new TextDecoder().decode(data));
    }
  } else {
    json = JSON.parse(data);
  }
  const buffers = (json.buffers || []).map((b, i) => {
    if (b.uri === undefined) {
      if (!bin) throw new Error(`buffer ${i} refers to a GLB binary chunk that is missing`);
      return bin;
    }
    if (b.uri.startsWith('data:')) return dataUri(b.uri);
    throw new Error(`buffer ${i} is an external file (${b.uri}): upload a GLB or a glTF with embedded data`);
  });
  const viewBytes = (vi) => {
    const v = json.bufferViews[vi];
    const buf = buffers[v.buffer];
    return { bytes: new Uint8Array(buf.buffer, buf.byteOffset + (v.byteOffset || 0), v.byteLength), stride: v.byteStride || 0 };
  };
  const COMPS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };
  const readAccessor = (ai, asFloat) => {
    const a = json.accessors[ai];
    const comps = COMPS[a.type];
    const out = asFloat ? new Float32Array(a.count * comps) : new Uint32Array(a.count * comps);
    if (a.bufferView === undefined) return out; // all zeros (sparse accessors are not read)
    const { bytes, stride } = viewBytes(a.bufferView);
    const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const size = { 5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4 }[a.componentType];
    const step = stride || size * comps;
    const base = a.byteOffset || 0;
    const get = {
      5120: (o) => dv.getInt8(o), 5121: (o) => dv.getUint8(o), 5122: (o) => dv.getInt16(o, true),
      5123: (o) => dv.getUint16(o, true), 5125: (o) => dv.getUint32(o, true), 5126: (o) => dv.getFloat32(o, true),
    }[a.componentType];
    const scale = asFloat && a.normalized ? { 5120: 127, 5121: 255, 5122: 32767, 5123: 65535 }[a.componentType] || 1 : 1;
    for (let i = 0; i < a.count; i++) {
      const o = base + i * step;
      for (let c = 0; c < comps; c++) out[i * comps + c] = get(o + c * size) / scale;
    }
    return out;
  };

  // Nodes depth first from the scene's roots; accessors numbered by first use (docs/formats.md).
  const scene = (json.scenes || [])[json.scene || 0];
  const roots = scene ? scene.nodes || [] : (json.nodes || []).map((_, i) => i);
  const offsets = new Map();
  const filePos = [];
  let fileVertexCount = 0;
  const parts = [];
  const groups = new Map();
  const visit = (ni, parent) => {
    const node = json.nodes[ni];
    const world = mul(parent, localMatrix(node));
    if (node.mesh !== undefined) {
      for (const prim of json.meshes[node.mesh].primitives) {
        if ((prim.mode ?? 4) !== 4 || prim.attributes.POSITION === undefined) continue;
        const pa = prim.attributes.POSITION;
        if (!offsets.has(pa)) {
          const p = readAccessor(pa, true);
          offsets.set(pa, fileVertexCount);
          fileVertexCount += p.length / 3;
          for (let i = 0; i < p.length; i++) filePos.push(p[i]);
        }
        const off = offsets.get(pa);
        const count = json.accessors[pa].count;
        const gather = new Uint32Array(count);
        for (let i = 0; i < count; i++) gather[i] = off + i;
        let index;
        if (prim.indices !== undefined) index = readAccessor(prim.indices, false);
        else { index = new Uint32Array(count); for (let i = 0; i < count; i++) index[i] = i; }
        const uvA = prim.attributes.TEXCOORD_0;
        const mat = prim.material !== undefined ? json.materials[prim.material] : null;
        const tex = mat?.pbrMetallicRoughness?.baseColorTexture;
        const image = tex && json.textures?.[tex.index]?.source !== undefined ? json.textures[tex.index].source : null;
        parts.push({ gather, index, uv: uvA !== undefined ? readAccessor(uvA, true) : null, matrix: world, image });
        // The node's name and its mesh's name each name the node's faces (a group region).
        for (const name of [node.name, json.meshes[node.mesh].name]) {
          if (typeof name !== 'string' || index.length < 3) continue;
          if (!groups.has(name)) groups.set(name, new Set());
          const set = groups.get(name);
          for (let k = 0; k < index.length; k++) set.add(gather[index[k]]);
        }
      }
    }
    for (const c of node.children || []) visit(c, world);
  };
  for (const r of roots) visit(r, IDENTITY);
  if (parts.length === 0) throw new Error('the glTF scene has no triangle primitives');
  const images = (json.images || []).map((im) => {
    if (im.bufferView !== undefined) {
      const { bytes } = viewBytes(im.bufferView);
      return new Blob([bytes.slice()], { type: im.mimeType || 'image/png' });
    }
    if (im.uri && im.uri.startsWith('data:')) {
      return new Blob([dataUri(im.uri)], { type: im.uri.slice(5, im.uri.indexOf(';')) });
    }
    return null; // external image: not available
  });
  return { fileVertexCount, filePositions: new Float32Array(filePos), parts, images, uvFlipY: false, groups };
}

/** A model from a mesh file by format (`obj`, `glb`, `gltf`, `stl`, `ply`, `off`). */
export function parseMesh(buffer, format) {
  if (format === 'obj') return parseObj(new TextDecoder().decode(buffer));
  if (format === 'stl') return parseStl(buffer);
  if (format === 'ply') return parsePly(buffer);
  if (format === 'off') return parseOff(new TextDecoder().decode(buffer));
  return parseGltf(buffer);
}

export function formatOf(name) {
  const ext = name.toLowerCase().split('.').pop();
  return ['obj', 'glb', 'gltf', 'stl', 'ply', 'off'].includes(ext) ? ext : null;
}

// PLY and OFF have no registered media type: these are the server's (docs/http.md, `POST /v1/jobs`).
export const MEDIA_TYPES = {
  obj: 'model/obj', glb: 'model/gltf-binary', gltf: 'model/gltf+json',
  stl: 'model/stl', ply: 'model/x-ply', off: 'model/x-off',
};

/** A model whose file vertices are its render vertices (STL, PLY, OFF). */
function indexedModel(filePos, index, uv) {
  const n = filePos.length / 3;
  if (index.length === 0) throw new Error('the file has no faces');
  for (const i of index) if (!(i >= 0 && i < n)) throw new Error('face index out of range');
  const gather = new Uint32Array(n);
  for (let i = 0; i < n; i++) gather[i] = i;
  return {
    fileVertexCount: n,
    filePositions: new Float32Array(filePos),
    parts: [{ gather, index: Uint32Array.from(index), uv: uv ? new Float32Array(uv) : null, matrix: null, image: null }],
    images: [],
    uvFlipY: true,
    groups: new Map(),
  };
}

/** Fan-triangulates polygon `vs` into `index`, as the server does. */
function fan(vs, index) {
  for (let k = 1; k + 1 < vs.length; k++) index.push(vs[0], vs[k], vs[k + 1]);
}

/** STL, binary (told by its exact length) or ASCII: corners joined by position in order of
 * first appearance, which is how the server numbers STL's file vertices. */
export function parseStl(buffer) {
  const bytes = new Uint8Array(buffer);
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const corners = [];
  if (bytes.length >= 84 && 84 + 50 * dv.getUint32(80, true) === bytes.length) {
    const n = dv.getUint32(80, true);
    for (let t = 0; t < n; t++) {
      for (let k = 0; k < 9; k++) corners.push(dv.getFloat32(84 + 50 * t + 12 + 4 * k, true));
    }
  } else {
    const words = new TextDecoder().decode(bytes).split(/\s+/);
    for (let i = 0; i < words.length; i++) {
      if (words[i] === 'vertex') corners.push(+words[i + 1], +words[i + 2], +words[i + 3]);
    }
  }
  const ids = new Map();
  const filePos = [];
  const index = [];
  for (let c = 0; c < corners.length; c += 3) {
    // `+ 0` joins -0 and +0, as the server does.
    const key = `${corners[c] + 0} ${corners[c + 1] + 0} ${corners[c + 2] + 0}`;
    let id = ids.get(key);
    if (id === undefined) {
      id = filePos.length / 3;
      ids.set(key, id);
      filePos.push(corners[c], corners[c + 1], corners[c + 2]);
    }
    index.push(id);
  }
  return indexedModel(filePos, index, null);
}

/** OFF (with the ST/C/N variants): vertex lines in order are the file vertices. */
export function parseOff(text) {
  const lines = text.split(/\r\n|\r|\n/).map((l) => l.split('#')[0].trim()).filter((l) => l);
  const head = (lines.shift() || '').split(/\s+/);
  if (!/^(ST)?C?N?OFF$/.test(head[0])) throw new Error('not an OFF file');
  const hasNormals = head[0].includes('N');
  const hasUv = head[0].startsWith('ST');
  const counts = (head.length > 1 ? head.slice(1) : (lines.shift() || '').split(/\s+/)).map(Number);
  const [nv, nf] = counts;
  const filePos = [];
  const uv = hasUv ? [] : null;
  for (let i = 0; i < nv; i++) {
    const w = (lines[i] || '').split(/\s+/).map(Number);
    filePos.push(w[0], w[1], w[2]);
    if (uv) uv.push(w[w.length - 2], w[w.length - 1]);
  }
  void hasNormals;
  const index = [];
  for (let f = 0; f < nf; f++) {
    const w = (lines[nv + f] || '').split(/\s+/).map(Number);
    fan(w.slice(1, 1 + w[0]), index);
  }
  return indexedModel(filePos, index, uv);
}

const PLY_TYPES = {
  char: ['Int8', 1], int8: ['Int8', 1], uchar: ['Uint8', 1], uint8: ['Uint8', 1],
  short: ['Int16', 2], int16: ['Int16', 2], ushort: ['Uint16', 2], uint16: ['Uint16', 2],
  int: ['Int32', 4], int32: ['Int32', 4], uint: ['Uint32', 4], uint32: ['Uint32', 4],
  float: ['Float32', 4], float32: ['Float32', 4], double: ['Float64', 8], float64: ['Float64', 8],
};

/** PLY, ASCII or binary either endianness: the vertex element's records are the file vertices. */
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const head = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const end = head.indexOf('end_header');
  if (!head.startsWith('ply') || end < 0) throw new Error('not a PLY file');
  let bodyAt = head.indexOf('\n', end) + 1;
  const elements = [];
  let format = 'ascii';
  for (const line of head.slice(0, end).split('\n')) {
    const w = line.trim().split(/\s+/);
    if (w[0] === 'format') format = w[1];
    else if (w[0] === 'element') elements.push({ name: w[1], count: +w[2], props: [] });
    else if (w[0] === 'property' && elements.length) {
      const props = elements[elements.length - 1].props;
      if (w[1] === 'list') props.push({ name: w[4], count: PLY_TYPES[w[2]], item: PLY_TYPES[w[3]] });
      else props.push({ name: w[2], type: PLY_TYPES[w[1]] });
    }
  }
  // Header bytes are ASCII, so the character offset is the byte offset.
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const little = format === 'binary_little_endian';
  let words = null;
  let wi = 0;
  if (format === 'ascii') words = new TextDecoder().decode(bytes.subarray(bodyAt)).trim().split(/\s+/);
  const read = (t) => {
    if (words) return +words[wi++];
    const x = dv[`get${t[0]}`](bodyAt, little);
    bodyAt += t[1];
    return x;
  };
  const filePos = [];
  const index = [];
  let uv = null;
  for (const el of elements) {
    const names = el.props.map((p) => p.name);
    const uvNames = [['s', 't'], ['u', 'v'], ['texture_u', 'texture_v'], ['texture_s', 'texture_t']]
      .find(([a, b]) => names.includes(a) && names.includes(b));
    if (el.name === 'vertex' && uvNames) uv = [];
    for (let r = 0; r < el.count; r++) {
      const rec = {};
      for (const p of el.props) {
        if (p.count) {
          const n = read(p.count);
          const list = [];
          for (let k = 0; k < n; k++) list.push(read(p.item));
          rec[p.name] = list;
        } else rec[p.name] = read(p.type);
      }
      if (el.name === 'vertex') {
        filePos.push(rec.x, rec.y, rec.z);
        if (uv) uv.push(rec[uvNames[0]], rec[uvNames[1]]);
      } else if (el.name === 'face') fan(rec.vertex_indices || rec.vertex_index || [], index);
    }
  }
  return indexedModel(filePos, index, uv);
}

function dataUri(uri) {
  const comma = uri.indexOf(',');
  const bin = atob(uri.slice(comma + 1));
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

const IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];

function localMatrix(node) {
  if (node.matrix) return node.matrix;
  const [tx, ty, tz] = node.translation || [0, 0, 0];
  const [x, y, z, w] = node.rotation || [0, 0, 0, 1];
  const [sx, sy, sz] = node.scale || [1, 1, 1];
  const x2 = x + x, y2 = y + y, z2 = z + z;
  const xx = x * x2, xy = x * y2, xz = x * z2, yy = y * y2, yz = y * z2, zz = z * z2;
  const wx = w * x2, wy = w * y2, wz = w * z2;
  return [
    (1 - (yy + zz)) * sx, (xy + wz) * sx, (xz - wy) * sx, 0,
    (xy - wz) * sy, (1 - (xx + zz)) * sy, (yz + wx) * sy, 0,
    (xz + wy) * sz, (yz - wx) * sz, (1 - (xx + yy)) * sz, 0,
    tx, ty, tz, 1,
  ];
}

function mul(a, b) {
  const o = new Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      o[c * 4 + r] = a[r] * b[c * 4] + a[4 + r] * b[c * 4 + 1] + a[8 + r] * b[c * 4 + 2] + a[12 + r] * b[c * 4 + 3];
    }
  }
  return o;
}

// ---------------------------------------------------------------------------------------------
// Frames: `positions_b64` is little-endian f32 xyz per file vertex, relative to the frame's
// `origin` when it has one (a model far from the origin: see `withOrigin`).

/**
 * A frame's positions as the viewer holds them (f32 xyz per file vertex, like the file it
 * read): `relative` itself when the frame has no `origin` (a model around the origin), else
 * origin + offset, added in double precision before the one rounding to f32. Writes into
 * `relative` (the frame's own buffer) and returns it.
 */
export function withOrigin(relative, origin) {
  if (!origin) return relative;
  for (let i = 0; i < relative.length; i += 3) {
    relative[i] = origin[0] + relative[i];
    relative[i + 1] = origin[1] + relative[i + 1];
    relative[i + 2] = origin[2] + relative[i + 2];
  }
  return relative;
}

const B64 = new Uint8Array(128);
{
  const abc = 'ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/';
  for (let i = 0; i < abc.length; i++) B64[abc.charCodeAt(i)] = i;
}

/**
 * Decode base64 into `out` (a Uint8Array that is reused frame after frame), without building a
 * binary string. Returns the byte count. Uses Uint8Array.prototype.setFromBase64 where the
 * browser has it.
 */
export function decodeBase64Into(s, out) {
  if (typeof out.setFromBase64 === 'function') return out.setFromBase64(s).written;
  let n = s.length;
  while (n > 0 && s.charCodeAt(n - 1) === 61 /* = */) n--;
  let o = 0;
  let i = 0;
  for (; i + 4 <= n; i += 4) {
    const v = (B64[s.charCodeAt(i)] << 18) | (B64[s.charCodeAt(i + 1)] << 12) | (B64[s.charCodeAt(i + 2)] << 6) | B64[s.charCodeAt(i + 3)];
    out[o++] = v >> 16; out[o++] = (v >> 8) & 255; out[o++] = v & 255;
  }
  const rest = n - i;
  if (rest >= 2) {
    const v = (B64[s.charCodeAt(i)] << 18) | (B64[s.charCodeAt(i + 1)] << 12) | (rest > 2 ? B64[s.charCodeAt(i + 2)] << 6 : 0);
    out[o++] = v >> 16;
    if (rest > 2) out[o++] = (v >> 8) & 255;
  }
  return o;
}
