// The 100k-triangle case (issue 13): how long the page takes to apply a frame (decode the
// base64 positions, gather them into the GPU buffer, normals, curvature colours) and to render
// it, per frame, on nefertiti (99 938 triangles), and the distance colours' cost. Prints figures; not a pass/fail test.
// Run by `scripts/browser-test.sh --timing` (which starts the server).
//
// The flow is Taubin smoothing: explicit and cheap, so frames arrive as fast as the server
// streams them and the page is what is measured. Each render waits until the frame is drawn
// (a 1-pixel readPixels), which in headless chromium is SwiftShader, a CPU rasterizer: a real
// GPU draws 100k triangles in a fraction of that.
import { ARTIFACTS, URL_BASE, launch, sharedMesh, waitStats, watchedPage } from './support.mjs';
import { join } from 'node:path';

const mesh = sharedMesh('nefertiti.obj');
if (!mesh) process.exit(0);
const STEPS = 60;

const { context, close } = await launch();
const { page, problems } = await watchedPage(context);
await page.goto(URL_BASE + '/');
await page.evaluate(() => {
  window.longTasks = [];
  new PerformanceObserver((l) => { for (const e of l.getEntries()) window.longTasks.push(e.duration); })
    .observe({ type: 'longtask', buffered: false });
});
await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
const t0 = Date.now();
await page.setInputFiles('#files', [mesh]);
await page.waitForFunction(() => /nefertiti/.test(document.getElementById('file-info').textContent), null, { timeout: 60_000 });
const loadMs = Date.now() - t0;
await page.selectOption('[name=method]', 'taubin');
await page.fill('[name=steps]', String(STEPS));
await page.fill('[name=tau]', '0.5');
await page.evaluate(() => { window.willowStats.syncGpu = true; });

const reset = () => page.evaluate(() => {
  const s = window.willowStats;
  s.applyMs.length = 0; s.renderMs.length = 0; window.longTasks.length = 0;
  s.framesAppliedAtReset = s.framesApplied; s.framesReceivedAtReset = s.framesReceived;
});
const snapshot = () => page.evaluate(() => ({
  ...window.willowStats, longTasks: [...window.longTasks],
}));
const summary = (name, s) => {
  const q = (a, p) => { const b = [...a].sort((x, y) => x - y); return b.length ? b[Math.min(b.length - 1, Math.floor(p * b.length))] : NaN; };
  const f = (a) => `median ${q(a, 0.5).toFixed(1)} ms, p95 ${q(a, 0.95).toFixed(1)} ms, max ${Math.max(...a).toFixed(1)} ms`;
  console.log(`${name}: ${s.framesApplied - s.framesAppliedAtReset} frames applied of ${s.framesReceived - s.framesReceivedAtReset} received`);
  console.log(`  apply (decode + gather + normals${name.includes('curvature') ? ' + curvature' : ''}): ${f(s.applyMs)}`);
  console.log(`  render (until drawn: a 1-pixel readPixels): ${f(s.renderMs)}`);
  console.log(`  long tasks (> 50 ms) on the main thread: ${s.longTasks.length}${s.longTasks.length ? ', longest ' + Math.max(...s.longTasks).toFixed(0) + ' ms' : ''}`);
};

await reset();
await page.click('#submit');
const half = await waitStats(page, () => window.willowStats.framesApplied >= 25, null, 300_000);
const a = await snapshot();
await page.screenshot({ path: join(ARTIFACTS, 'timing-100k-texture.png') });
await page.selectOption('#colour', 'curvature');
await reset();
await waitStats(page, () => ['succeeded', 'failed', 'cancelled'].includes(window.willowStats.state), null, 300_000);
const b = await snapshot();
await page.screenshot({ path: join(ARTIFACTS, 'timing-100k-curvature.png') });

// The distance-from-the-input colours on the last frame: building the input's BVH once, then
// one colouring pass (nearest input triangle for every vertex), each timed alone.
await page.selectOption('#colour', 'distance');
const distance = await page.evaluate(() => {
  const v = window.willow.view;
  const time = () => { v.distanceIdleAt = 0; const t = performance.now(); v.updateDistance(); return performance.now() - t; };
  v.inputSurface = null;
  const first = time();
  const passes = [time(), time(), time()].sort((x, y) => x - y);
  return { first, pass: passes[1], max: v.stats.distanceMax };
});
await page.screenshot({ path: join(ARTIFACTS, 'timing-100k-distance.png') });

console.log(`nefertiti.obj: ${half.vertexCount} vertices, ${half.triangleCount} triangles; read and shown in ${loadMs} ms (file chosen to first render)`);
summary('plain shading', a);
summary('mean-curvature colours', b);
console.log(`distance colours after ${STEPS} steps: BVH build + first pass ${distance.first.toFixed(0)} ms, a pass ${distance.pass.toFixed(0)} ms (median of 3; largest distance ${distance.max.toPrecision(3)})`);
if (problems.length) console.log('problems:', problems);
await close();
