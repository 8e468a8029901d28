// Distance from a point to a triangle surface (the input), for the page's "distance from the
// input" colours (issue 29 item 3). Nearest point on the input's *triangles*, not the nearest
// input vertex nor the vertex's own displacement: a vertex that slid along the surface is at
// distance 0. Triangles are binned in a uniform grid over their bounding boxes; a query visits
// cells in growing shells around its own and stops once no unvisited cell can hold anything
// nearer than the best found. Pure JS, no three.js: the unit test runs it in node.

/**
 * Squared distance from p to the triangle (a, b, c): Ericson, "Real-Time Collision Detection"
 * §5.1.5 (closest point by Voronoi regions of the vertices, edges and face).
 */
export function pointTriangleDistance2(px, py, pz, P, a, b, c) {
  const ax = P[a], ay = P[a + 1], az = P[a + 2];
  const abx = P[b] - ax, aby = P[b + 1] - ay, abz = P[b + 2] - az;
  const acx = P[c] - ax, acy = P[c + 1] - ay, acz = P[c + 2] - az;
  const apx = px - ax, apy = py - ay, apz = pz - az;
  const d1 = abx * apx + aby * apy + abz * apz;
  const d2 = acx * apx + acy * apy + acz * apz;
  let qx, qy, qz;
  if (d1 <= 0 && d2 <= 0) return apx * apx + apy * apy + apz * apz; // vertex a
  const bpx = px - P[b], bpy = py - P[b + 1], bpz = pz - P[b + 2];
  const d3 = abx * bpx + aby * bpy + abz * bpz;
  const d4 = acx * bpx + acy * bpy + acz * bpz;
  if (d3 >= 0 && d4 <= d3) return bpx * bpx + bpy * bpy + bpz * bpz; // vertex b
  const vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) { // edge ab
    const v = d1 / (d1 - d3);
    qx = ax + v * abx; qy = ay + v * aby; qz = az + v * abz;
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2;
  }
  const cpx = px - P[c], cpy = py - P[c + 1], cpz = pz - P[c + 2];
  const d5 = abx * cpx + aby * cpy + abz * cpz;
  const d6 = acx * cpx + acy * cpy + acz * cpz;
  if (d6 >= 0 && d5 <= d6) return cpx * cpx + cpy * cpy + cpz * cpz; // vertex c
  const vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) { // edge ac
    const w = d2 / (d2 - d6);
    qx = ax + w * acx; qy = ay + w * acy; qz = az + w * acz;
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2;
  }
  const va = d3 * d6 - d5 * d4;
  if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) { // edge bc
    const w = (d4 - d3) / (d4 - d3 + (d5 - d6));
    qx = P[b] + w * (P[c] - P[b]); qy = P[b + 1] + w * (P[c + 1] - P[b + 1]); qz = P[b + 2] + w * (P[c + 2] - P[b + 2]);
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2;
  }
  const denom = 1 / (va + vb + vc); // inside the face
  const v = vb * denom, w = vc * denom;
  qx = ax + abx * v + acx * w; qy = ay + aby * v + acy * w; qz = az + abz * v + acz * w;
  return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2;
}

/** The input surface, ready for nearest-point queries. */
export class SurfaceDistance {
  /** `positions`: 3 numbers per vertex; `faces`: 3 vertex indices per triangle (copied). */
  constructor(positions, faces) {
    this.P = Float64Array.from(positions);
    this.faces = Uint32Array.from(faces);
    const P = this.P, F = this.faces, nf = F.length / 3;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    let edge = 0;
    for (let f = 0; f < F.length; f += 3) {
      for (let k = 0; k < 3; k++) {
        const s = 3 * F[f + k];
        for (let d = 0; d < 3; d++) { lo[d] = Math.min(lo[d], P[s + d]); hi[d] = Math.max(hi[d], P[s + d]); }
      }
      const a = 3 * F[f], b = 3 * F[f + 1];
      edge += Math.hypot(P[b] - P[a], P[b + 1] - P[a + 1], P[b + 2] - P[a + 2]);
    }
    if (nf === 0) throw new Error('no triangles to measure the distance to');
    // Cells about two mean edges wide: a few triangles each. The cell count is capped (4 per
    // triangle, at least 64) so a long thin mesh cannot ask for a huge grid.
    const ext = [0, 1, 2].map((d) => Math.max(hi[d] - lo[d], 1e-12));
    let cell = Math.max(2 * edge / nf, 1e-12);
    const cap = Math.max(64, 4 * nf);
    while (Math.ceil(ext[0] / cell) * Math.ceil(ext[1] / cell) * Math.ceil(ext[2] / cell) > cap) cell *= 1.25;
    this.cell = cell;
    this.lo = lo;
    this.n = ext.map((e) => Math.max(1, Math.ceil(e / cell)));
    const [nx, ny, nz] = this.n;
    // Two passes (count, fill): a compact cell → triangles table.
    const count = new Uint32Array(nx * ny * nz + 1);
    const range = new Int32Array(6);
    const visit = (f, fn) => {
      for (let d = 0; d < 3; d++) { range[d] = Infinity; range[d + 3] = -Infinity; }
      for (let k = 0; k < 3; k++) {
        const s = 3 * F[f + k];
        for (let d = 0; d < 3; d++) {
          const c = this.cellOf(P[s + d], d);
          if (c < range[d]) range[d] = c;
          if (c > range[d + 3]) range[d + 3] = c;
        }
      }
      for (let i = range[0]; i <= range[3]; i++)
        for (let j = range[1]; j <= range[4]; j++)
          for (let k = range[2]; k <= range[5]; k++) fn((k * ny + j) * nx + i);
    };
    for (let f = 0; f < F.length; f += 3) visit(f, (c) => count[c + 1]++);
    for (let c = 0; c < nx * ny * nz; c++) count[c + 1] += count[c];
    this.start = count;
    this.items = new Uint32Array(count[nx * ny * nz]);
    const fill = count.slice(0, nx * ny * nz);
    for (let f = 0; f < F.length; f += 3) visit(f, (c) => { this.items[fill[c]++] = f; });
    this.stamp = new Uint32Array(nf);
    this.query = 0;
  }

  cellOf(x, d) {
    const c = Math.floor((x - this.lo[d]) / this.cell);
    return c < 0 ? 0 : c >= this.n[d] ? this.n[d] - 1 : c;
  }

  /** Distance from (x, y, z) to the nearest point of the surface. */
  distance(x, y, z) {
    const { P, faces, items, start, stamp, cell, lo } = this;
    const [nx, ny, nz] = this.n;
    if (++this.query === 0xffffffff) { stamp.fill(0); this.query = 1; }
    const q = this.query;
    const ci = this.cellOf(x, 0), cj = this.cellOf(y, 1), ck = this.cellOf(z, 2);
    let best = Infinity;
    const rmax = Math.max(nx, ny, nz);
    for (let r = 0; r <= rmax; r++) {
      // Shell r: the cells at Chebyshev distance r from (ci, cj, ck).
      for (let k = ck - r; k <= ck + r; k++) {
        if (k < 0 || k >= nz) continue;
        for (let j = cj - r; j <= cj + r; j++) {
          if (j < 0 || j >= ny) continue;
          const onFace = k === ck - r || k === ck + r || j === cj - r || j === cj + r;
          for (let i = ci - r; i <= ci + r; i += onFace ? 1 : 2 * r || 1) {
            if (i < 0 || i >= nx) continue;
            const c = (k * ny + j) * nx + i;
            for (let t = start[c]; t < start[c + 1]; t++) {
              const f = items[t];
              if (stamp[f / 3] === q) continue;
              stamp[f / 3] = q;
              const d2 = pointTriangleDistance2(x, y, z, P, 3 * faces[f], 3 * faces[f + 1], 3 * faces[f + 2]);
              if (d2 < best) best = d2;
            }
          }
        }
      }
      if (best === Infinity) continue;
      // Everything not yet visited lies outside the block of cells [c−r, c+r]: at least as far
      // as the block's nearest face from the point (0 if the point is outside the block).
      let bound = Infinity;
      const p = [x, y, z], c0 = [ci, cj, ck];
      for (let d = 0; d < 3; d++) {
        const blo = lo[d] + (c0[d] - r) * cell, bhi = lo[d] + (c0[d] + r + 1) * cell;
        // A side at the grid's edge has nothing beyond it.
        const below = c0[d] - r <= 0 ? Infinity : p[d] - blo;
        const above = c0[d] + r >= this.n[d] - 1 ? Infinity : bhi - p[d];
        bound = Math.min(bound, below, above);
      }
      if (bound < 0) bound = 0;
      if (bound * bound >= best) break;
    }
    return Math.sqrt(best);
  }
}
