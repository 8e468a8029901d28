// The page's frame reader (web/src/meshio.js `withOrigin`), checked in node without a browser:
// a frame without `origin` is its f32 values as they are; with one, origin + offset is added in
// double precision before the single rounding to f32, so a vertex at map-grid coordinates is
// the f32 nearest its true position (as if the f32 coordinates had been sent, but without
// losing the offsets' own precision first).
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { withOrigin } from '../../web/src/meshio.js';

test('a frame without an origin is left as it is', () => {
  const f = new Float32Array([0.1, -2.5, 3]);
  const same = withOrigin(f, undefined);
  assert.equal(same, f);
  assert.deepEqual([...same], [...new Float32Array([0.1, -2.5, 3])]);
});

test('origin + offset in double precision, then one rounding to f32', () => {
  const origin = [5e6, -5e6, 2.5e6];
  // Offsets that are exact in f32, so the true positions are known exactly.
  const offsets = [0.75, -0.125, 0.5, -0.375, 0.25, 0.875];
  const f = withOrigin(new Float32Array(offsets), origin);
  for (let i = 0; i < offsets.length; i++) {
    const truth = origin[i % 3] + offsets[i];
    assert.equal(f[i], Math.fround(truth), `coordinate ${i}`);
  }
});
