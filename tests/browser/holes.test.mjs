// Issue 40 on the web page: the fill_holes control. A hole cut here into spot (every face at
// one vertex removed) is sent with fill_holes; a size the server refuses names the field and
// the page highlights it; with `all` the job runs, its first frame is the filled mesh (more
// triangles than the upload), and the page draws that mesh.
import { after, before, test } from 'node:test';
import assert from 'node:assert/strict';
import { mkdirSync, readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { ARTIFACTS, URL_BASE, launch, paramsPart, sharedMesh, waitStats, watchedPage } from './support.mjs';

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

/** spot without the faces within two rings of one vertex: one hole, large enough that its
 * patch gets inner vertices. */
function holedSpot() {
  const lines = readFileSync(sharedMesh('spot_triangulated.obj'), 'utf8').split('\n');
  const corners = (line) => line.trim().split(/\s+/).slice(1).map((c) => c.split('/')[0]);
  const faces = lines.filter((l) => /^f\s/.test(l));
  const ring = new Set(faces.map(corners).filter((c) => c.includes('735')).flat());
  const touches = (line) => /^f\s/.test(line) && corners(line).some((v) => ring.has(v));
  const kept = lines.filter((l) => !touches(l));
  const removed = lines.length - kept.length;
  mkdirSync(ARTIFACTS, { recursive: true });
  const path = join(ARTIFACTS, 'spot-holed.obj');
  writeFileSync(path, kept.join('\n'));
  return { path, triangles: kept.filter((l) => /^f\s/.test(l)).length, removed };
}

test('fill_holes: a refused size names its field, `all` closes the hole and the page draws the filled mesh', async () => {
  const holed = holedSpot();
  assert.ok(holed.removed >= 12, `the cut removed ${holed.removed} faces`);
  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [holed.path]);
  await page.waitForFunction(() => /spot-holed\.obj/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  await page.selectOption('select[name=method]', 'conformal');
  await page.fill('[name="steps"]', '2');
  assert.equal(await page.locator('[name="fill_holes"]').getAttribute('placeholder'), 'none');
  const sent = [];
  const jobsUrl = (u) => u.pathname === '/v1/jobs';
  await page.route(jobsUrl, (route) => {
    if (route.request().method() === 'POST') sent.push(paramsPart(route.request().postDataBuffer()));
    return route.continue();
  });
  // A loop has at least 3 vertices: 2 is refused at submission, by field.
  await page.fill('[name="fill_holes"]', '2');
  await page.click('#submit');
  await page.locator('#form-error').filter({ hasText: 'fill_holes' }).waitFor();
  assert.ok(await page.locator('input[name="fill_holes"]').evaluate((el) => el.classList.contains('invalid')));
  assert.equal(sent[0].fill_holes, '2');
  await page.fill('[name="fill_holes"]', 'all');
  await page.click('#submit');
  // The job can finish before frame 0 (the filled mesh) is fetched and drawn: wait for both.
  const done = await waitStats(page, () => window.willowStats.state === 'succeeded' && window.willowStats.modelJobId === window.willowStats.jobId);
  assert.equal(sent[1].fill_holes, 'all');
  // The patch is refined to the surrounding edge length: more triangles than the cut took.
  assert.ok(
    done.triangleCount > holed.triangles + holed.removed / 2,
    `the page draws the filled mesh: ${done.triangleCount} triangles, the upload had ${holed.triangles}`,
  );
  await page.screenshot({ path: join(ARTIFACTS, 'holes-filled.png') });
  // Without fill_holes the field is not sent, and the upload's mesh is drawn again.
  await page.fill('[name="fill_holes"]', '');
  await page.click('#submit');
  const plain = await waitStats(page, (id) => window.willowStats.jobId !== id && window.willowStats.state === 'succeeded' && window.willowStats.modelJobId === window.willowStats.jobId, done.jobId);
  assert.equal(sent[2].fill_holes, undefined);
  assert.equal(plain.triangleCount, holed.triangles);
  await page.unroute(jobsUrl);
  problems.splice(0, problems.length, ...problems.filter((p) => !/status of 400/.test(p)));
  assert.deepEqual(problems, [], 'console errors or requests to other hosts');
});
