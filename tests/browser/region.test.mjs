// Issue 29 on the web page: a region picked on the 3D view by mouse (press on spot, drag out a
// radius), shown tinted, sent as a sphere region; the job runs it; everything outside stays
// where it was; the before/after toggle and the distance colours. Only `region` and `seam` are
// sent (the other new parameters stay unset, so nothing else is asked of the server).
import { after, before, test } from 'node:test';
import assert from 'node:assert/strict';
import { readFileSync } from 'node:fs';
import { join } from 'node:path';
import { ARTIFACTS, URL_BASE, launch, paramsPart, sharedMesh, stats, waitStats, watchedPage } from './support.mjs';

const spot = sharedMesh('spot_triangulated.obj');
const spotTexture = sharedMesh('spot_texture.png');

let browser;
let page;
let problems;

before(async () => {
  browser = await launch();
  ({ page, problems } = await watchedPage(browser.context, URL_BASE));
});

after(async () => {
  await browser?.close();
});

const shot = (name) => page.screenshot({ path: join(ARTIFACTS, `${name}.png`) });
/** A hash of what the view draws: rendered and read back in one task (the drawing buffer is
 * not kept between frames), so page layout and scrolling play no part. */
const canvasPixels = () => page.evaluate(() => {
  const v = window.willow.view;
  v.render();
  const gl = v.renderer.getContext();
  const px = new Uint8Array(gl.drawingBufferWidth * gl.drawingBufferHeight * 4);
  gl.readPixels(0, 0, gl.drawingBufferWidth, gl.drawingBufferHeight, gl.RGBA, gl.UNSIGNED_BYTE, px);
  let h = 0x811c9dc5; // FNV-1a
  for (let i = 0; i < px.length; i++) h = Math.imul(h ^ px[i], 0x01000193);
  return `${gl.drawingBufferWidth}x${gl.drawingBufferHeight}:${(h >>> 0).toString(16)}`;
});

/** The `v` lines of an OBJ, as numbers (the test's own reading, not the page's). */
function objVertices(text) {
  const out = [];
  for (const line of text.split('\n')) {
    if (/^v\s/.test(line)) out.push(line.trim().split(/\s+/).slice(1, 4).map(Number));
  }
  return out;
}

/** Distance from p to the triangle (a, b, c), the test's own way (not the page's): the plane's
 * foot if it falls inside, else the nearest of the three edges. */
function triangleDistance(p, a, b, c) {
  const sub = (u, v) => [u[0] - v[0], u[1] - v[1], u[2] - v[2]];
  const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  const cross = (u, v) => [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
  const segment = (u, v) => {
    const e = sub(v, u);
    const t = Math.min(1, Math.max(0, dot(sub(p, u), e) / dot(e, e)));
    return Math.hypot(...sub(p, [u[0] + t * e[0], u[1] + t * e[1], u[2] + t * e[2]]));
  };
  const n = cross(sub(b, a), sub(c, a));
  const h = dot(sub(p, a), n) / dot(n, n);
  const foot = [p[0] - h * n[0], p[1] - h * n[1], p[2] - h * n[2]];
  const inside = [[a, b], [b, c], [c, a]].every(([u, v]) => dot(cross(sub(v, u), sub(foot, u)), n) >= 0);
  return inside ? Math.abs(h) * Math.sqrt(dot(n, n)) : Math.min(segment(a, b), segment(b, c), segment(c, a));
}

/** The triangles of an OBJ (fan-split polygons), as 0-based `v` indices. */
function objTriangles(text) {
  const out = [];
  for (const line of text.split('\n')) {
    if (!/^f\s/.test(line)) continue;
    const t = line.trim().split(/\s+/).slice(1).map((w) => parseInt(w, 10) - 1);
    for (let k = 2; k < t.length; k++) out.push([t[0], t[k - 1], t[k]]);
  }
  return out;
}

test('a sphere region picked by mouse on the view moves only what it holds; before/after and distance colours', async () => {
  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  await page.fill('[name="steps"]', '4');

  // Pick: press at the middle of the canvas (spot's body faces the camera there) and drag
  // 70 px to the right.
  await page.click('#region-pick');
  const box = await page.locator('#canvas').boundingBox();
  const x = box.x + box.width / 2, y = box.y + box.height / 2;
  await page.mouse.move(x, y);
  await page.mouse.down();
  await page.mouse.move(x + 35, y, { steps: 4 });
  await page.mouse.move(x + 70, y, { steps: 4 });
  await page.mouse.up();
  assert.equal(await page.locator('[name="region"]').inputValue(), 'sphere');
  const center = (await page.locator('[name="region.sphere.center"]').inputValue()).split(',').map(Number);
  const radius = Number(await page.locator('[name="region.sphere.radius"]').inputValue());
  assert.equal(center.length, 3);
  assert.ok(center.every(Number.isFinite), `centre ${center}`);
  assert.ok(radius > 0, `radius ${radius}`);
  const input = objVertices(readFileSync(spot, 'utf8'));
  const inside = (p) => Math.hypot(p[0] - center[0], p[1] - center[1], p[2] - center[2]) <= radius;
  const insideCount = input.filter(inside).length;
  assert.ok(insideCount > 0 && insideCount < input.length, `the region holds ${insideCount} of ${input.length} vertices`);
  // The picked centre lies on the surface: within an edge or so of some input vertex.
  const nearest = Math.min(...input.map((p) => Math.hypot(p[0] - center[0], p[1] - center[1], p[2] - center[2])));
  assert.ok(nearest < 0.05, `the centre is ${nearest} from the nearest vertex`);
  // The page tints what the server will move: the same count as the test's own selection.
  assert.equal(Number(await page.locator('#region-info').getAttribute('data-inside')), insideCount);
  await shot('10-region-picked');

  // Submit: the request carries the sphere region as the form shows it, and nothing unset.
  // (Routed: chromium reports no body for a multipart upload a page merely sends.)
  let body = null;
  const jobsUrl = (u) => u.pathname === '/v1/jobs';
  await page.route(jobsUrl, (route) => {
    if (route.request().method() === 'POST') body = route.request().postDataBuffer();
    route.continue();
  });
  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  await page.unroute(jobsUrl);
  assert.ok(body, 'the page submitted the job');
  const params = paramsPart(body);
  assert.deepEqual(params.region, { sphere: { center, radius } });
  assert.equal(params.seam, 'smooth');
  for (const unset of ['preserve', 'max_deviation', 'until_willmore', 'feature_size', 'falloff', 'measure_deviation']) {
    assert.ok(!(unset in params), `\`${unset}\` was not set, so it is not sent`);
  }
  const id = await page.evaluate(() => location.hash.slice(5));
  const done = await waitStats(page, () => ['succeeded', 'failed', 'cancelled'].includes(window.willowStats.state));
  const job = await (await fetch(`${URL_BASE}/v1/jobs/${id}`)).json();
  assert.equal(done.state, 'succeeded', `the job ended ${done.state}: ${job.error}`);
  assert.equal(done.lastStep, 4);
  assert.deepEqual(job.params.region, [{ sphere: { center, radius } }], 'the server got the region');
  // The outcome, when the server reports one, is shown with its reason.
  if (job.outcome) {
    const shown = await page.locator('#outcome').textContent();
    assert.ok(shown.includes(job.outcome.replaceAll('_', ' ')), `outcome shown: ${shown}`);
    if (job.outcome_reason) assert.ok(shown.includes(job.outcome_reason));
  }
  // Wait until the page shows the last frame.
  await page.waitForFunction(() => /step 4\//.test(document.getElementById('frame-counter').textContent));
  await page.waitForTimeout(300);
  await shot('11-region-faired');
  // Metrics the frames do not carry are not plotted.
  const shownPlots = await page.evaluate(() => window.willow.plots.charts.filter((c) => !c.el.hidden).map((c) => c.el.id));
  const carried = (key) => job.metrics.latest && key in job.metrics.latest;
  assert.equal(shownPlots.includes('plot-deviation'), carried('deviation_max'));
  assert.equal(shownPlots.includes('plot-scale'), carried('log_area_ratio_p1'));
  const wLegend = await page.locator('#plot-w .u-legend .u-series:visible').allTextContents();
  assert.deepEqual(wLegend.map((t) => t.trim()), carried('willmore_energy_vector') ? ['W', 'W vector |Δf|²/4A'] : ['W']);

  // The final frame, as the server stores it: every vertex outside the region bit-identical to
  // the input file's, and the region itself moved.
  const res = await fetch(`${URL_BASE}/v1/jobs/${id}/frames/4?format=obj`);
  assert.equal(res.status, 200);
  const final = objVertices(await res.text());
  assert.equal(final.length, input.length);
  let moved = 0;
  for (let i = 0; i < input.length; i++) {
    if (inside(input[i])) {
      if (final[i].some((v, d) => v !== input[i][d])) moved++;
    } else {
      assert.deepEqual(final[i], input[i], `vertex ${i} lies outside the region and moved`);
    }
  }
  assert.ok(moved > insideCount / 2, `${moved} of the ${insideCount} vertices inside moved`);

  // The page shows that frame: its positions equal the stored frame's, outside vertices
  // equal the input's in the page's own float32 buffers too.
  const page4 = await page.evaluate(() => {
    const v = window.willow.view;
    return { current: Array.from(v.current), input: Array.from(v.model.filePositions), shown: v.lastPositions === v.current };
  });
  assert.ok(page4.shown, 'the current frame is on the canvas');
  for (let i = 0; i < input.length; i++) {
    for (let d = 0; d < 3; d++) {
      assert.equal(page4.current[3 * i + d], Math.fround(final[i][d]), `the page's step 4, vertex ${i}`);
    }
  }

  // Before/after: the toggle shows the input, then the current frame again.
  const after = await canvasPixels();
  await page.check('#show-input');
  await page.waitForTimeout(300);
  assert.ok(await page.evaluate(() => window.willow.view.lastPositions === window.willow.view.model.filePositions), 'the input is shown');
  const beforePixels = await canvasPixels();
  assert.notEqual(beforePixels, after, 'the canvas shows another surface with "show input"');
  await shot('12-region-before');
  await page.uncheck('#show-input');
  await page.waitForTimeout(300);
  assert.ok(await page.evaluate(() => window.willow.view.lastPositions === window.willow.view.current), 'the frame is back');
  const back = await canvasPixels();
  assert.equal(back, after, 'unchecking it shows the faired surface again');

  // Distance colours: 0 outside the region, and never more than a vertex's own displacement
  // (its input position is a point of the input surface).
  await page.selectOption('#colour', 'distance');
  await page.waitForTimeout(300);
  const dist = await page.evaluate(() => {
    const v = window.willow.view;
    const { rep, count } = v.weld;
    return { d: Array.from(v.distance.slice(0, count)), rep: Array.from(rep) };
  });
  // Every moved vertex (a few hundred) against a brute force over all input triangles.
  const triangles = objTriangles(readFileSync(spot, 'utf8'));
  let largest = 0;
  let compared = 0;
  for (let w = 0; w < dist.d.length; w++) {
    const i = dist.rep[w];
    if (!inside(input[i])) {
      assert.equal(dist.d[w], 0, `distance at vertex ${i}, outside the region`);
      continue;
    }
    const p = final[i].map(Math.fround);
    let truth = Infinity;
    for (const [a, b, c] of triangles) truth = Math.min(truth, triangleDistance(p, input[a], input[b], input[c]));
    assert.ok(Math.abs(dist.d[w] - truth) <= 1e-6 + 1e-4 * truth, `vertex ${i}: the page says ${dist.d[w]}, brute force ${truth}`);
    largest = Math.max(largest, truth);
    compared++;
  }
  assert.ok(compared > 0 && largest > 0, `some vertex is off the input surface (${compared} compared)`);
  assert.match(await page.locator('#legend').textContent(), /distance from the input/);
  await shot('13-region-distance');
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
});

test('the outcome and its reason are shown when the job ends; distance, volume, scale-distortion and W-vector plots appear once frames carry them', async () => {
  // Until the server reports them, its answers are given the fields of the API's contract
  // (job: `outcome`, `outcome_reason`; frames: `deviation_max`, `deviation_mean`, `volume`):
  // the job JSON, the stream's `done` event (the same JSON) and the frames' metrics.
  const id = await page.evaluate(() => location.hash.slice(5));
  assert.match(id, /^[0-9a-f-]{36}$/, 'the previous test left its job in the URL');
  const outcome = { outcome: 'max_deviation', outcome_reason: 'the next step would move the surface 0.03 from the input, beyond max_deviation 0.02' };
  const withOutcome = (job) => (job.id === id ? { ...job, ...outcome } : job);
  const routes = [
    [(u) => u.pathname === `/v1/jobs/${id}`, (body) => JSON.stringify(withOutcome(JSON.parse(body)))],
    [(u) => u.pathname === `/v1/jobs/${id}/events`, (body) => body.replace(/^(event: ?done\ndata: ?)(.*)$/m,
      (_, head, data) => head + JSON.stringify(withOutcome(JSON.parse(data))))],
    [(u) => u.pathname === `/v1/jobs/${id}/frames`, (body) => {
      const page1 = JSON.parse(body);
      for (const m of page1.frames) {
        Object.assign(m, {
          deviation_max: 0.01 * m.step, deviation_mean: 0.002 * m.step, volume: 0.5 + 0.001 * m.step,
          // Issue 26's metrics (the robust branch's names).
          willmore_energy_vector: 2 * m.willmore_energy, log_area_ratio_p1: -0.1 * m.step, log_area_ratio_p99: 0.2 * m.step,
          collapsed_triangles: m.step,
        });
      }
      return JSON.stringify(page1);
    }],
  ];
  for (const [match, rewrite] of routes) {
    await page.route(match, async (route) => {
      const res = await route.fetch();
      route.fulfill({ response: res, body: rewrite(await res.text()) });
    });
  }
  await page.reload();
  await waitStats(page, (id) => window.willowStats.jobId === id && window.willowStats.state === 'succeeded', id);
  const el = page.locator('#outcome');
  await el.filter({ hasText: 'max deviation' }).waitFor({ timeout: 30_000 });
  // The stream's `done` comes after the job JSON: the outcome is still there once it has.
  await page.waitForFunction(() => window.willowStats.framesApplied >= 1);
  await page.waitForTimeout(500);
  assert.equal(await el.getAttribute('data-outcome'), 'max_deviation');
  assert.equal(await el.textContent(), `ended: max deviation — ${outcome.outcome_reason}`);
  assert.ok(await page.locator('#plot-deviation').isVisible(), 'the distance plot appears');
  assert.ok(await page.locator('#plot-volume').isVisible(), 'the volume plot appears');
  assert.ok(await page.locator('#plot-scale').isVisible(), 'the scale distortion plot appears');
  assert.ok(await page.locator('#plot-collapsed').isVisible(), 'the collapsed triangles plot appears');
  const wSeries = await page.evaluate(() => window.willow.plots.charts[0].chart.series.map((s) => [s.label, s.show]));
  assert.deepEqual(wSeries.slice(1), [['W', true], ['W vector |Δf|²/4A', true]], 'both forms of W are plotted');
  assert.deepEqual((await page.locator('#plot-w .u-legend .u-series:visible').allTextContents()).map((t) => t.trim()), ['W', 'W vector |Δf|²/4A']);
  // The form shows the job's region again, tinted on the model it fetched back.
  assert.equal(await page.locator('[name="region"]').inputValue(), 'sphere');
  await page.waitForFunction(() => Number(document.getElementById('region-info').dataset.inside) > 0);
  await page.locator('#view-panel').scrollIntoViewIfNeeded();
  await shot('14-outcome');
  await page.locator('#plots').screenshot({ path: join(ARTIFACTS, '15-metric-plots.png') });
  await page.unrouteAll();
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
});

const duck = sharedMesh('Duck.glb');

test('a region picked on a glTF with a scaled node is in world space: the server moves what the page tints', async () => {
  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [duck]);
  await page.waitForFunction(() => /texture \(embedded\)/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  await page.fill('[name="steps"]', '3');
  await page.click('#region-pick');
  const box = await page.locator('#canvas').boundingBox();
  const x = box.x + box.width / 2, y = box.y + box.height / 2;
  await page.mouse.move(x, y);
  await page.mouse.down();
  await page.mouse.move(x + 50, y, { steps: 5 });
  await page.mouse.up();
  const center = (await page.locator('[name="region.sphere.center"]').inputValue()).split(',').map(Number);
  const radius = Number(await page.locator('[name="region.sphere.radius"]').inputValue());
  // The file's positions and each one's node matrix (Duck's node scales by 0.01): the test's
  // own world-space selection.
  const model = await page.evaluate(() => {
    const m = window.willow.view.model;
    const matrixOf = new Array(m.fileVertexCount).fill(null);
    for (const p of m.parts) for (const i of p.gather) matrixOf[i] = p.matrix;
    return { input: Array.from(m.filePositions), matrixOf };
  });
  assert.ok(model.matrixOf.some((m) => m && m[0] !== 1), 'Duck has a scaled node');
  const n = model.matrixOf.length;
  const world = (i) => {
    const m = model.matrixOf[i] || [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
    const [px, py, pz] = model.input.slice(3 * i, 3 * i + 3);
    return [0, 1, 2].map((d) => m[d] * px + m[4 + d] * py + m[8 + d] * pz + m[12 + d]);
  };
  const inside = [];
  for (let i = 0; i < n; i++) if (Math.hypot(...world(i).map((v, d) => v - center[d])) <= radius) inside.push(i);
  assert.ok(inside.length > 0 && inside.length < n, `${inside.length} of ${n} inside`);
  assert.equal(Number(await page.locator('#region-info').getAttribute('data-inside')), inside.length, 'the page tints the world-space selection');

  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  const done = await waitStats(page, () => ['succeeded', 'failed', 'cancelled'].includes(window.willowStats.state));
  assert.equal(done.state, 'succeeded', await page.locator('#view-error').textContent());
  await page.waitForFunction(() => /step 3\//.test(document.getElementById('frame-counter').textContent));
  const current = await page.evaluate(() => Array.from(window.willow.view.current));
  const isInside = new Set(inside);
  let moved = 0;
  for (let i = 0; i < n; i++) {
    const changed = [0, 1, 2].some((d) => current[3 * i + d] !== model.input[3 * i + d]);
    if (!isInside.has(i)) assert.ok(!changed, `vertex ${i} lies outside the region and moved`);
    else if (changed) moved++;
  }
  assert.ok(moved > inside.length / 2, `${moved} of the ${inside.length} vertices inside moved`);
  await page.locator('#view-panel').scrollIntoViewIfNeeded();
  await shot('16-duck-region');
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
});

test('shape and stopping controls: each is sent only once set, the detail size is a ring of that diameter, two regions go as a list, an error names its field, Clear drops the regions', async () => {
  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  // Typed, not picked: the numbers are the form's to edit.
  await page.selectOption('[name="region"]', 'sphere');
  await page.fill('[name="region.sphere.center"]', '0.1, 0.2, 0');
  await page.fill('[name="region.sphere.radius"]', '0.3');
  await page.selectOption('[name="seam"]', 'fixed');
  await page.fill('[name="falloff"]', '0.05');
  await page.fill('[name="feature_size"]', '0.125');
  await page.selectOption('[name="preserve"]', 'volume');
  await page.fill('[name="max_deviation"]', '0.02');
  await page.fill('[name="until_willmore"]', '13');
  await page.check('[name="measure_deviation"]');
  const outer = await page.evaluate(() => window.willow.regionControls.overlays.outlines
    .filter((o) => o.userData.falloff).map((o) => o.scale.x));
  assert.deepEqual(outer.map((r) => +r.toFixed(12)), [0.35], 'the falloff drawn as a sphere 0.05 wider');
  const ring = await page.evaluate(() => {
    const r = window.willow.regionControls.overlays.ring;
    return { visible: r.visible, scale: r.scale.x, at: r.position.toArray() };
  });
  assert.ok(ring.visible, 'the detail-size ring is shown');
  assert.ok(Math.abs(ring.scale - 0.125) < 1e-12, `ring diameter ${ring.scale}`);
  assert.deepEqual(ring.at.map((v) => +v.toFixed(6)), [0.1, 0.2, 0], 'the ring sits at the region\'s centre');
  assert.match(await page.locator('#ring-label').textContent(), /detail size 0\.125/);
  // A second region: the sphere is kept in the list, a box typed beside it; the job gets both
  // and the page tints their union.
  await page.click('#region-add');
  assert.equal(await page.locator('#region-list li').count(), 1);
  assert.equal(await page.locator('[name="region.sphere.center"]').inputValue(), '', 'the form is free for another region');
  await page.selectOption('[name="region"]', 'box');
  await page.fill('[name="region.box.min"]', '-0.3,-0.5,-0.6');
  await page.fill('[name="region.box.max"]', '0.3,-0.1,-0.2');
  const input = objVertices(readFileSync(spot, 'utf8'));
  const union = input.filter((p) => Math.hypot(p[0] - 0.1, p[1] - 0.2, p[2]) <= 0.3
    || (p[0] >= -0.3 && p[0] <= 0.3 && p[1] >= -0.5 && p[1] <= -0.1 && p[2] >= -0.6 && p[2] <= -0.2)).length;
  const sphereOnly = input.filter((p) => Math.hypot(p[0] - 0.1, p[1] - 0.2, p[2]) <= 0.3).length;
  assert.ok(union > sphereOnly, `the box adds vertices (${sphereOnly} → ${union})`);
  assert.equal(Number(await page.locator('#region-info').getAttribute('data-inside')), union);
  await page.locator('#view-panel').scrollIntoViewIfNeeded();
  await shot('17-shape-controls');

  // The server answers (here, as a server would that refuses one of them) with a problem
  // naming `max_deviation`: the request is kept to be read, not run.
  let body = null;
  const jobsUrl = (u) => u.pathname === '/v1/jobs';
  await page.route(jobsUrl, (route) => {
    if (route.request().method() !== 'POST') return route.continue();
    body = route.request().postDataBuffer();
    return route.fulfill({
      status: 400,
      contentType: 'application/problem+json',
      body: JSON.stringify({ type: 'about:blank', title: 'Bad Request', status: 400, code: 'invalid_parameter', field: 'max_deviation', detail: 'invalid parameter `max_deviation`: the test refuses it' }),
    });
  });
  await page.click('#submit');
  await page.locator('#form-error').filter({ hasText: 'max_deviation' }).waitFor();
  await page.unroute(jobsUrl);
  const params = paramsPart(body);
  assert.deepEqual(params.region, [
    { sphere: { center: [0.1, 0.2, 0], radius: 0.3 } },
    { box: { min: [-0.3, -0.5, -0.6], max: [0.3, -0.1, -0.2] } },
  ]);
  assert.equal(params.seam, 'fixed');
  assert.equal(params.falloff, 0.05);
  assert.equal(params.feature_size, 0.125);
  assert.equal(params.preserve, 'volume');
  assert.equal(params.max_deviation, 0.02);
  assert.equal(params.until_willmore, 13);
  assert.equal(params.measure_deviation, true);
  assert.ok(await page.locator('input[name="max_deviation"]').evaluate((el) => el.classList.contains('invalid')), 'the field is highlighted');

  // Emptied again: not sent. Clear: no region, no seam, nothing tinted.
  for (const name of ['falloff', 'feature_size', 'max_deviation', 'until_willmore']) await page.fill(`[name="${name}"]`, '');
  await page.selectOption('[name="preserve"]', '');
  await page.uncheck('[name="measure_deviation"]');
  // Removing the kept sphere leaves the box alone.
  await page.click('#region-list button[data-remove="0"]');
  assert.equal(await page.locator('#region-list li').count(), 0);
  assert.deepEqual(await page.evaluate(() => window.willow.regionControls.params().region), { box: { min: [-0.3, -0.5, -0.6], max: [0.3, -0.1, -0.2] } });
  await page.click('#region-clear');
  assert.equal(await page.locator('[name="region"]').inputValue(), '');
  assert.equal(await page.locator('#region-info').getAttribute('data-inside'), '');
  const cleared = await page.evaluate(() => window.willow.regionControls.params());
  assert.deepEqual(cleared, {}, 'nothing of these controls is sent');
  assert.equal(await page.evaluate(() => window.willow.regionControls.overlays.ring.visible), false);
  // The 400 above is the browser's console error, not the page's.
  problems.splice(0, problems.length, ...problems.filter((p) => !/status of 400/.test(p)));
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
});
