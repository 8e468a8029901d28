// Distance from a point to a triangle surface (the input), for the page's "distance from the
// input" colours (issue 29 item 3). Nearest point on the input's *triangles*, not the nearest
// input vertex nor the vertex's own displacement: a vertex that slid along the surface is at
// distance 0. The triangles sit in a bounding-volume hierarchy (median splits, a few triangles
// per leaf); a query descends nearer boxes first and skips any box no nearer than the best
// found, so points far from the surface (a flow that moved a lot) cost no more than near ones.
// Pure JS, no three.js: the unit test runs it in node.

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

/** Triangles per BVH leaf. */
const LEAF = 4;

/** The input surface, ready for nearest-point queries. */
export class SurfaceDistance {
  /** `positions`: 3 numbers per vertex; `faces`: 3 vertex indices per triangle (copied). */
  constructor(positions, faces) {
    this.P = Float64Array.from(positions);
    this.faces = Uint32Array.from(faces);
    const P = this.P, F = this.faces, nf = F.length / 3;
    if (nf === 0) throw new Error('no triangles to measure the distance to');
    const centroid = new Float64Array(3 * nf);
    const tbox = new Float64Array(6 * nf);
    for (let t = 0; t < nf; t++) {
      for (let d = 0; d < 3; d++) {
        const a = P[3 * F[3 * t] + d], b = P[3 * F[3 * t + 1] + d], c = P[3 * F[3 * t + 2] + d];
        centroid[3 * t + d] = (a + b + c) / 3;
        tbox[6 * t + d] = Math.min(a, b, c);
        tbox[6 * t + 3 + d] = Math.max(a, b, c);
      }
    }
    const order = new Uint32Array(nf);
    for (let t = 0; t < nf; t++) order[t] = t;
    // Nodes: box (6 numbers), then either children (left, right) or a leaf's range of `order`.
    const maxNodes = 2 * Math.ceil(nf / LEAF) * 2 + 1;
    const box = new Float64Array(6 * maxNodes);
    const child = new Int32Array(2 * maxNodes); // left, right; left = −1 − start for a leaf
    const count = new Uint32Array(maxNodes);
    let nodes = 0;
    const work = [[0, nf, nodes++]];
    while (work.length) {
      const [start, end, node] = work.pop();
      const b = 6 * node;
      for (let d = 0; d < 3; d++) { box[b + d] = Infinity; box[b + 3 + d] = -Infinity; }
      const clo = [Infinity, Infinity, Infinity], chi = [-Infinity, -Infinity, -Infinity];
      for (let k = start; k < end; k++) {
        const t = order[k];
        for (let d = 0; d < 3; d++) {
          box[b + d] = Math.min(box[b + d], tbox[6 * t + d]);
          box[b + 3 + d] = Math.max(box[b + 3 + d], tbox[6 * t + 3 + d]);
          clo[d] = Math.min(clo[d], centroid[3 * t + d]);
          chi[d] = Math.max(chi[d], centroid[3 * t + d]);
        }
      }
      if (end - start <= LEAF) {
        child[2 * node] = -1 - start;
        count[node] = end - start;
        continue;
      }
      // Split at the median centroid along the centroids' longest extent.
      const ext = [0, 1, 2].map((d) => chi[d] - clo[d]);
      const axis = ext[0] >= ext[1] && ext[0] >= ext[2] ? 0 : ext[1] >= ext[2] ? 1 : 2;
      const mid = (start + end) >> 1;
      select(order, start, end - 1, mid, (t) => centroid[3 * t + axis]);
      const left = nodes++, right = nodes++;
      child[2 * node] = left;
      child[2 * node + 1] = right;
      work.push([start, mid, left], [mid, end, right]);
    }
    this.order = order;
    this.box = box;
    this.child = child;
    this.count = count;
    this.stack = new Int32Array(128);
    this.near = new Float64Array(128);
  }

  /** Squared distance from (x, y, z) to node `n`'s box (0 inside it). */
  boxDistance2(n, x, y, z) {
    const b = this.box, o = 6 * n;
    const dx = Math.max(b[o] - x, 0, x - b[o + 3]);
    const dy = Math.max(b[o + 1] - y, 0, y - b[o + 4]);
    const dz = Math.max(b[o + 2] - z, 0, z - b[o + 5]);
    return dx * dx + dy * dy + dz * dz;
  }

  /**
   * Distance from (x, y, z) to the nearest point of the surface. `known2`, if given, is the
   * squared distance to some point known to lie on the surface (a moved vertex's own input
   * position): the search then only looks for something nearer, and a vertex that has not
   * moved costs nothing.
   */
  distance(x, y, z, known2 = Infinity) {
    if (known2 === 0) return 0;
    const { P, faces, order, child, count } = this;
    let stack = this.stack, near = this.near;
    let best = known2;
    let top = 0;
    stack[top] = 0;
    near[top++] = this.boxDistance2(0, x, y, z);
    while (top > 0) {
      const n = stack[--top];
      // Its box's distance, from when it was pushed: skipped if something nearer was found since.
      if (near[top] >= best) continue;
      const left = child[2 * n];
      if (left < 0) {
        const start = -1 - left;
        for (let k = start; k < start + count[n]; k++) {
          const t = 3 * order[k];
          const d2 = pointTriangleDistance2(x, y, z, P, 3 * faces[t], 3 * faces[t + 1], 3 * faces[t + 2]);
          if (d2 < best) best = d2;
        }
        continue;
      }
      const right = child[2 * n + 1];
      const dl = this.boxDistance2(left, x, y, z), dr = this.boxDistance2(right, x, y, z);
      if (top + 2 > stack.length) {
        const s2 = new Int32Array(2 * stack.length), n2 = new Float64Array(2 * stack.length);
        s2.set(stack); n2.set(near);
        stack = this.stack = s2; near = this.near = n2;
      }
      // The nearer child is searched first (pushed last).
      if (dl < dr) {
        if (dr < best) { stack[top] = right; near[top++] = dr; }
        if (dl < best) { stack[top] = left; near[top++] = dl; }
      } else {
        if (dl < best) { stack[top] = left; near[top++] = dl; }
        if (dr < best) { stack[top] = right; near[top++] = dr; }
      }
    }
    return Math.sqrt(best);
  }
}

/** Reorder `a[lo..=hi]` so that `a[k]` holds the element of rank k by `key`, smaller keys
 * before it and larger after (Hoare's selection). */
function select(a, lo, hi, k, key) {
  while (hi > lo) {
    const pivot = key(a[(lo + hi) >> 1]);
    let i = lo, j = hi;
    while (i <= j) {
      while (key(a[i]) < pivot) i++;
      while (key(a[j]) > pivot) j--;
      if (i <= j) { const t = a[i]; a[i] = a[j]; a[j] = t; i++; j--; }
    }
    if (k <= j) hi = j;
    else if (k >= i) lo = i;
    else return;
  }
}
