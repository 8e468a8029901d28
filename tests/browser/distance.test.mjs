// The page's distance-from-the-input colours (web/src/distance.js), checked in node without a
// browser: analytic cases on a flat square, and a brute force over every triangle of a bumpy
// sphere for points off the surface, far outside and inside it.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { SurfaceDistance, pointTriangleDistance2 } from '../../web/src/distance.js';

test('point-to-triangle distance: the face, an edge and a vertex of a right triangle', () => {
  const P = [0, 0, 0, 1, 0, 0, 0, 1, 0];
  const d = (x, y, z) => Math.sqrt(pointTriangleDistance2(x, y, z, P, 0, 3, 6));
  assert.equal(d(0.25, 0.25, 0.5), 0.5); // above the face
  assert.ok(Math.abs(d(1, 1, 0) - Math.SQRT1_2) < 1e-12); // beyond the hypotenuse, nearest at (½, ½)
  assert.ok(Math.abs(d(-3, -4, 0) - 5) < 1e-12); // beyond vertex a
  assert.ok(Math.abs(d(0.5, -2, 2) - Math.hypot(2, 2)) < 1e-12); // beyond edge ab
  assert.ok(Math.abs(d(2, 0, 0) - 1) < 1e-12); // beyond vertex b
});

/** A UV sphere of radius 1 with radial bumps: 3 numbers per vertex, 3 indices per triangle. */
function bumpySphere(rings, segments) {
  const P = [];
  const F = [];
  for (let i = 0; i <= rings; i++) {
    const th = (Math.PI * i) / rings;
    for (let j = 0; j < segments; j++) {
      const ph = (2 * Math.PI * j) / segments;
      const r = 1 + 0.05 * Math.sin(7 * th) * Math.cos(5 * ph);
      P.push(r * Math.sin(th) * Math.cos(ph), r * Math.sin(th) * Math.sin(ph), r * Math.cos(th));
    }
  }
  const v = (i, j) => i * segments + (j % segments);
  for (let i = 0; i < rings; i++) {
    for (let j = 0; j < segments; j++) {
      F.push(v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j), v(i + 1, j + 1), v(i, j + 1));
    }
  }
  return { P, F };
}

test('BVH distance equals the brute-force minimum over every triangle', () => {
  const { P, F } = bumpySphere(24, 32);
  const bvh = new SurfaceDistance(P, F);
  let seed = 12345;
  const rand = () => ((seed = (seed * 1103515245 + 12345) % 2 ** 31) / 2 ** 31);
  let checked = 0;
  for (let n = 0; n < 400; n++) {
    // Radii from well inside to well outside the surface (which spans about ±1.05).
    const r = 0.1 + 2.4 * rand();
    const th = Math.acos(2 * rand() - 1), ph = 2 * Math.PI * rand();
    const x = r * Math.sin(th) * Math.cos(ph), y = r * Math.sin(th) * Math.sin(ph), z = r * Math.cos(th);
    let brute = Infinity;
    for (let f = 0; f < F.length; f += 3) {
      brute = Math.min(brute, pointTriangleDistance2(x, y, z, P, 3 * F[f], 3 * F[f + 1], 3 * F[f + 2]));
    }
    const got = bvh.distance(x, y, z);
    assert.ok(Math.abs(got - Math.sqrt(brute)) <= 1e-12, `at (${x}, ${y}, ${z}): BVH ${got}, brute force ${Math.sqrt(brute)}`);
    checked++;
  }
  assert.equal(checked, 400);
  // A vertex of the surface itself is at distance 0, and so is a point inside a triangle.
  assert.equal(bvh.distance(P[300], P[301], P[302]), 0);
  const [a, b, c] = [F[600], F[601], F[602]];
  const mid = [0, 1, 2].map((d) => (P[3 * a + d] + P[3 * b + d] + P[3 * c + d]) / 3);
  assert.ok(bvh.distance(...mid) < 1e-12);
});
