// The web page in a real browser (issue 13), against the real server started by
// scripts/browser-test.sh. The tests run in order and share one browser and page.
import { after, before, test } from 'node:test';
import assert from 'node:assert/strict';
import { existsSync, readFileSync } from 'node:fs';
import { createRequire } from 'node:module';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';
import { ARTIFACTS, URL_BASE, launch, paramsPart, sharedMesh, startProxy, stats, waitStats, watchedPage } from './support.mjs';

const here = dirname(fileURLToPath(import.meta.url));
const spot = sharedMesh('spot_triangulated.obj');
const spotTexture = sharedMesh('spot_texture.png');
const duck = sharedMesh('Duck.glb');

let browser;
let page;
let problems;
let firstJob;
// The page is loaded through a proxy, so a test can drop its connections.
let proxy;
let BASE;

before(async () => {
  proxy = await startProxy(URL_BASE);
  BASE = proxy.url;
  browser = await launch();
  ({ page, problems } = await watchedPage(browser.context, BASE));
});

after(async () => {
  await browser?.close();
  await proxy?.close();
});

/** Nothing forbidden happened so far (checked at the end of every test). */
function assertClean() {
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
}

const shot = (name) => page.screenshot({ path: join(ARTIFACTS, `${name}.png`) });
const canvasPixels = () => page.locator('#canvas').screenshot();
const counter = async () => Number(await page.locator('#frame-counter').getAttribute('data-frames-applied'));

async function uploadSpot(params = {}) {
  await page.goto(BASE + '/');
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  // The parameters' defaults come from the server before the form is used.
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  for (const [name, value] of Object.entries(params)) await page.fill(`[name="${name}"]`, String(value));
}

test('upload spot with its texture: at least 3 frames render, the canvas changes, the plots grow', async () => {
  await uploadSpot();
  assert.equal(await page.locator('#colour').inputValue(), 'texture');
  const s0 = await stats(page);
  assert.equal(s0.triangleCount, 5856, 'the input is shown at once, parsed in the page');
  const before = await canvasPixels();
  const plotBefore = await page.locator('#plot-w canvas').screenshot();
  await shot('01-spot-input');

  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  firstJob = await page.evaluate(() => location.hash.slice(5));
  const s = await waitStats(page, () => window.willowStats.framesApplied >= 3);
  assert.ok((await counter()) >= 3, 'the visible frame counter shows 3 frames');
  assert.match(await page.locator('#frame-counter').textContent(), /frames \d+ · step \d+\/20/);
  assert.ok(s.plotPoints >= 3, `plots have ${s.plotPoints} points`);
  const during = await canvasPixels();
  assert.ok(!during.equals(before), 'the canvas pixels change as frames arrive');
  await shot('02-spot-running');

  const done = await waitStats(page, () => window.willowStats.state === 'succeeded');
  assert.equal(done.lastStep, 20);
  assert.equal(done.plotPoints, 21, 'one plot point per step, step 0 included');
  const plotAfter = await page.locator('#plot-w canvas').screenshot();
  assert.ok(!plotAfter.equals(plotBefore), 'the Willmore plot was drawn');
  await shot('03-spot-done');

  // Scrub back to the input: the kept frame 0 comes back on the canvas.
  const final = await canvasPixels();
  await page.locator('#scrub').evaluate((el) => { el.value = '0'; el.dispatchEvent(new Event('input')); });
  await page.waitForFunction(() => /step 0\//.test(document.getElementById('frame-counter').textContent));
  await page.waitForTimeout(300);
  assert.ok(!(await canvasPixels()).equals(final), 'scrubbing to step 0 shows another surface');
  await shot('04-spot-scrubbed-to-step0');

  // Wireframe and curvature colours render without errors.
  await page.check('#wireframe');
  await page.selectOption('#colour', 'curvature');
  await page.waitForTimeout(300);
  await shot('05-spot-curvature-wireframe');
  await page.uncheck('#wireframe');
  assertClean();
});

test('the result downloads as a valid GLB', async () => {
  const [download] = await Promise.all([page.waitForEvent('download'), page.click('#dl-glb')]);
  const file = join(ARTIFACTS, 'spot-result.glb');
  await download.saveAs(file);
  const glb = readFileSync(file);
  assert.equal(glb.toString('latin1', 0, 4), 'glTF', 'GLB magic');
  assert.equal(glb.readUInt32LE(4), 2, 'glTF version 2');
  assert.equal(glb.readUInt32LE(8), glb.length, 'header length is the file length');
  const jsonLength = glb.readUInt32LE(12);
  assert.equal(glb.readUInt32LE(16), 0x4e4f534a, 'the first chunk is JSON');
  const doc = JSON.parse(glb.toString('utf8', 20, 20 + jsonLength));
  assert.equal(doc.asset.version, '2.0');
  assert.ok(doc.meshes.length > 0);
  // The Khronos validator, when scripts/test.sh has installed it.
  const validator = resolve(here, '../tools/node_modules/gltf-validator');
  if (existsSync(validator)) {
    const v = createRequire(import.meta.url)(validator);
    const report = await v.validateBytes(new Uint8Array(glb), { uri: 'spot-result.glb' });
    assert.equal(report.issues.numErrors, 0, JSON.stringify(report.issues.messages.slice(0, 5)));
  } else {
    console.log('note: tests/tools/node_modules/gltf-validator missing; structural checks only');
  }
  assertClean();
});

test('the API\'s error is shown, its field highlighted', async () => {
  await uploadSpot({ tau: 1.5 });
  await page.click('#submit');
  const error = page.locator('#form-error');
  await error.filter({ hasText: 'tau' }).waitFor();
  assert.match(await error.textContent(), /invalid parameter `tau`: must be < 1 for the conformal flow \(paper §4\), got 1\.5 \(invalid_parameter\)/);
  assert.ok(await page.locator('input[name=tau]').evaluate((el) => el.classList.contains('invalid')));
  // A nested field: the spectral filter's order.
  await page.fill('[name="tau"]', '0.5');
  await page.check('[name="filter"]');
  await page.fill('[name="filter.k"]', '7');
  await page.click('#submit');
  await error.filter({ hasText: 'filter.k' }).waitFor();
  assert.ok(await page.locator('input[name="filter.k"]').evaluate((el) => el.classList.contains('invalid')));
  await shot('06-parameter-error');
  // Errors are console-free: the page shows them, it does not throw.
  problems.splice(0, problems.length, ...problems.filter((p) => !/status of 400/.test(p)));
  assertClean();
});

test('denoising options: the defaults as placeholders, each sent only once set, a bad one names its field, the job runs with them', async () => {
  await page.goto(BASE + '/');
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  assert.equal(await page.locator('select[name=method]').inputValue(), 'denoise', 'the default method');
  assert.equal(await page.locator('[name="denoise.sigma_r"]').getAttribute('placeholder'), '0.35');
  assert.equal(await page.locator('[name="denoise.iterations"]').getAttribute('placeholder'), 'auto');
  assert.ok(await page.locator('[name="denoise.guided"]').isChecked(), 'guided by default');
  // Every POST's params part, as sent.
  const sent = [];
  const jobsUrl = (u) => u.pathname === '/v1/jobs';
  await page.route(jobsUrl, (route) => {
    if (route.request().method() === 'POST') sent.push(paramsPart(route.request().postDataBuffer()));
    return route.continue();
  });
  // Out of range: the server's problem names the nested field and the page highlights it.
  await page.fill('[name="denoise.radius"]', '9');
  await page.click('#submit');
  await page.locator('#form-error').filter({ hasText: 'denoise.radius' }).waitFor();
  assert.ok(await page.locator('input[name="denoise.radius"]').evaluate((el) => el.classList.contains('invalid')));
  assert.deepEqual(sent[0].denoise, { radius: 9 }, 'only the field that was set');
  // Two forced iterations (one step: the flow takes two a step), a smaller disc, the
  // bilateral filter: spot has no noise, so without them it would end already_fair.
  await page.fill('[name="denoise.radius"]', '1.5');
  await page.fill('[name="denoise.iterations"]', '2');
  await page.uncheck('[name="denoise.guided"]');
  await page.click('#submit');
  const done = await waitStats(page, () => window.willowStats.state === 'succeeded');
  assert.equal(done.lastStep, 1);
  assert.deepEqual(sent[1].denoise, { iterations: 2, radius: 1.5, guided: false });
  assert.equal(sent[1].method, 'denoise');
  // Under another method nothing of the filter is sent.
  await page.selectOption('select[name=method]', 'conformal');
  await page.fill('[name="steps"]', '1');
  await page.click('#submit');
  await waitStats(page, (id) => window.willowStats.jobId !== id && window.willowStats.state === 'succeeded', done.jobId);
  assert.equal(sent[2].denoise, undefined);
  await page.unroute(jobsUrl);
  problems.splice(0, problems.length, ...problems.filter((p) => !/status of 400/.test(p)));
  assertClean();
});

test('a dropped connection and a reload mid-run resume the stream; cancel the job; the dashboard shows the states', async () => {
  // Long enough to reload and cancel while it runs: small steps.
  await uploadSpot({ steps: 2000, tau: 0.02 });
  // Every step: a flow that has settled would otherwise end `converged` before the test acts.
  await page.check('[name=all_steps]');
  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  const id = await page.evaluate(() => location.hash.slice(5));
  assert.notEqual(id, firstJob);
  const s0 = await waitStats(page, () => window.willowStats.framesApplied >= 3 && window.willowStats.state === 'running');

  // A dropped connection: the browser reconnects by itself and resumes after Last-Event-ID.
  const resumes = [];
  const onResume = async (r) => {
    if (!r.url().includes(`/v1/jobs/${id}/events`)) return;
    const h = await r.allHeaders();
    if (h['last-event-id'] !== undefined) resumes.push(Number(h['last-event-id']));
  };
  page.on('request', onResume);
  proxy.dropAll();
  const dropped = await waitStats(page, () => window.willowStats.reconnects > 0, null, 10_000);
  await page.waitForFunction(() => document.getElementById('state').textContent === 'running', null, { timeout: 30_000 });
  page.off('request', onResume);
  assert.equal(resumes.length, 1, 'one reconnection, with Last-Event-ID');
  assert.ok(resumes[0] >= s0.lastStep, `resumed after step ${resumes[0]}, the last seen before the drop`);
  const s1 = await waitStats(page, (step) => window.willowStats.lastStep > step + 2, dropped.lastStep);
  // Requests cut by the drop (a dashboard poll) are the browser's console errors, not the page's.
  problems.splice(0, problems.length, ...problems.filter((p) => !/ERR_INCOMPLETE_CHUNKED_ENCODING|ERR_EMPTY_RESPONSE|ERR_CONNECTION|Failed to fetch|network/.test(p)));

  const streams = [];
  const onRequest = (r) => { if (r.url().includes(`/v1/jobs/${id}/events`)) streams.push(r.url()); };
  page.on('request', onRequest);
  await page.reload();
  const s2 = await waitStats(page, ([id, step]) => window.willowStats.jobId === id && window.willowStats.lastStep > step && window.willowStats.framesApplied >= 2, [id, s1.lastStep]);
  page.off('request', onRequest);
  assert.equal(streams.length, 1);
  const from = Number(new URL(streams[0]).searchParams.get('from_step'));
  assert.ok(from >= s1.lastStep, `the stream resumed at step ${from}, not from the start (had ${s1.lastStep})`);
  assert.ok(s2.plotPoints > s1.lastStep, 'the plots were refilled from the job\'s history');
  assert.equal(s2.triangleCount, 5856, 'the input was fetched back (frame 0) after the reload');
  assert.equal(await page.locator('#colour').inputValue(), 'texture', 'the OBJ\'s texture is kept for this tab');
  assert.equal(await page.locator('[name=steps]').inputValue(), '2000', 'the form shows the job\'s parameters');
  await shot('07-reloaded-running');

  // Dashboard: this job running, the first one succeeded.
  const row = page.locator(`#jobs-table tr[data-job-id="${id}"]`);
  await row.waitFor();
  assert.equal(await row.getAttribute('data-state'), 'running');
  assert.equal(await page.locator(`#jobs-table tr[data-job-id="${firstJob}"]`).getAttribute('data-state'), 'succeeded');

  await page.click('#cancel');
  try {
    await waitStats(page, () => window.willowStats.state === 'cancelled', null, 60_000);
  } catch (e) {
    const job = await (await fetch(`${URL_BASE}/v1/jobs/${id}`)).text();
    throw new Error(`${e.message}\nthe API says: ${job}`);
  }
  await page.locator(`#jobs-table tr[data-job-id="${id}"][data-state="cancelled"]`).waitFor({ timeout: 10_000 });
  // Scrub to step 0, which came before the reload: fetched from the frames endpoint.
  await page.waitForFunction(() => !document.getElementById('scrub').disabled);
  await page.locator('#scrub').evaluate((el) => { el.value = '0'; el.dispatchEvent(new Event('input')); });
  await page.waitForFunction(() => /step 0\//.test(document.getElementById('frame-counter').textContent));
  // Filtered by state: only cancelled jobs.
  await page.selectOption('#jobs-state', 'cancelled');
  await page.waitForFunction((first) => !document.querySelector(`#jobs-table tr[data-job-id="${first}"]`), firstJob);
  const states = await page.locator('#jobs-table tbody tr').evaluateAll((rows) => rows.map((r) => r.dataset.state));
  assert.ok(states.length >= 1 && states.every((s) => s === 'cancelled'), `filtered rows: ${states}`);
  await page.locator('#jobs').scrollIntoViewIfNeeded();
  await shot('08-dashboard-cancelled');
  assertClean();
});

test('a textured GLB shows its embedded texture and flows', async () => {
  await page.goto(BASE + '/');
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // The conformal flow's frames (the default method leaves the clean duck alone).
  await page.selectOption('select[name=method]', 'conformal');
  await page.setInputFiles('#files', [duck]);
  await page.waitForFunction(() => /texture \(embedded\)/.test(document.getElementById('file-info').textContent));
  const s = await stats(page);
  assert.equal(s.triangleCount, 4212);
  assert.equal(await page.locator('#colour').inputValue(), 'texture');
  // Its frames (glTF accessor vertices, in accessor-local space) land on the same buffers.
  await page.fill('[name="steps"]', '4');
  await page.click('#submit');
  const done = await waitStats(page, () => window.willowStats.state === 'succeeded' && window.willowStats.framesApplied >= 2);
  assert.equal(await page.locator('#view-error').textContent(), '');
  assert.equal(done.triangleCount, 4212);
  await page.waitForTimeout(300);
  await shot('09-duck-glb-faired');
  assertClean();
});
