// Issue 29 on the web page: a region named by a group of the file. The page lists the uploaded
// OBJ's own `g`/`o` names, tints the chosen group's vertices, sends `{"group": name}`, and the
// job moves those vertices only. A file without groups offers no group mode.
import { after, before, test } from 'node:test';
import assert from 'node:assert/strict';
import { mkdtempSync, readFileSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { ARTIFACTS, URL_BASE, launch, paramsPart, sharedMesh, waitStats, watchedPage } from './support.mjs';

const spot = sharedMesh('spot_triangulated.obj');

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

/** Spot's right ear (as tests/service_region_acceptance finds it). */
const EAR = { center: [0.40, 0.72, -0.20], radius: 0.15 };

/** spot as `o spot`, then `g ear` over the faces with every corner in the ear sphere and `g
 * body` over the rest; and the test's own count of each group's vertices (its faces' corners). */
function spotWithGroups(text) {
  const v = [];
  let head = 'o spot\n', ear = '', body = '';
  const earVertices = new Set(), bodyVertices = new Set();
  for (const line of text.split('\n')) {
    if (/^v\s/.test(line)) v.push(line.trim().split(/\s+/).slice(1, 4).map(Number));
    if (/^f\s/.test(line)) {
      const corners = line.trim().split(/\s+/).slice(1).map((w) => parseInt(w, 10) - 1);
      const inEar = corners.every((k) => Math.hypot(...v[k].map((x, d) => x - EAR.center[d])) <= EAR.radius);
      if (inEar) { ear += line + '\n'; corners.forEach((k) => earVertices.add(k)); } else { body += line + '\n'; corners.forEach((k) => bodyVertices.add(k)); }
    } else if (line !== '') {
      head += line + '\n';
    }
  }
  return { text: `${head}g ear\n${ear}g body\n${body}`, earVertices, bodyVertices, vertexCount: v.length };
}

function objVertices(text) {
  return text.split('\n').filter((l) => /^v\s/.test(l)).map((l) => l.trim().split(/\s+/).slice(1, 4).map(Number));
}

test('a group of the uploaded OBJ is picked from its names, tinted, sent as {group} and only it moves', async () => {
  const grouped = spotWithGroups(readFileSync(spot, 'utf8'));
  const dir = mkdtempSync(join(tmpdir(), 'willow-groups-'));
  const file = join(dir, 'spot_groups.obj');
  writeFileSync(file, grouped.text);

  // A file without groups first: the group mode is not offered.
  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [spot]);
  await page.waitForFunction(() => /spot_triangulated\.obj/.test(document.getElementById('file-info').textContent));
  assert.equal(await page.locator('[name="region"] option[value="group"]').isDisabled(), true);

  await page.setInputFiles('#files', [file]);
  await page.waitForFunction(() => /spot_groups\.obj/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  await page.fill('[name="steps"]', '3');
  assert.equal(await page.locator('[name="region"] option[value="group"]').isDisabled(), false);
  await page.selectOption('[name="region"]', 'group');
  assert.equal(await page.locator('#region-group').isVisible(), true);
  // The file's names in file order, each with its vertex count (the test's own count).
  const options = await page.locator('[name="region.group"] option').evaluateAll((os) => os.map((o) => [o.value, o.textContent]));
  assert.deepEqual(options.map(([v]) => v), ['spot', 'ear', 'body']);
  assert.equal(options[1][1], `ear (${grouped.earVertices.size} vertices)`);
  assert.equal(options[2][1], `body (${grouped.bodyVertices.size} vertices)`);
  await page.selectOption('[name="region.group"]', 'ear');
  assert.equal(Number(await page.locator('#region-info').getAttribute('data-inside')), grouped.earVertices.size);
  assert.ok(grouped.earVertices.size > 20 && grouped.earVertices.size < grouped.vertexCount / 10);
  await page.screenshot({ path: join(ARTIFACTS, '20-region-group.png') });

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
  assert.deepEqual(params.region, { group: 'ear' });
  assert.equal(params.seam, 'smooth');
  const id = await page.evaluate(() => location.hash.slice(5));
  const done = await waitStats(page, () => ['succeeded', 'failed', 'cancelled'].includes(window.willowStats.state));
  const job = await (await fetch(`${URL_BASE}/v1/jobs/${id}`)).json();
  assert.equal(done.state, 'succeeded', `the job ended ${done.state}: ${job.error}`);
  assert.deepEqual(job.params.region, [{ group: 'ear' }], 'the server got the group');

  // The result: every vertex outside the group bit-identical (as text numbers) to the file's,
  // and the group's own vertices moved.
  const input = objVertices(grouped.text);
  const res = await fetch(`${URL_BASE}/v1/jobs/${id}/result?format=obj`);
  assert.equal(res.status, 200);
  const result = objVertices(await res.text());
  assert.equal(result.length, input.length);
  let moved = 0;
  for (let i = 0; i < input.length; i++) {
    if (grouped.earVertices.has(i)) {
      if (result[i].some((x, d) => x !== input[i][d])) moved++;
    } else {
      assert.deepEqual(result[i], input[i], `vertex ${i} is outside the group and moved`);
    }
  }
  assert.ok(moved > grouped.earVertices.size / 2, `${moved} of the ${grouped.earVertices.size} ear vertices moved`);

  // The job's page shows the group again, chosen in the form and tinted on the model.
  await page.waitForTimeout(300);
  assert.equal(await page.locator('[name="region"]').inputValue(), 'group');
  assert.equal(await page.locator('[name="region.group"]').inputValue(), 'ear');
  await page.waitForFunction((n) => Number(document.getElementById('region-info').dataset.inside) === n, grouped.earVertices.size);
  await page.screenshot({ path: join(ARTIFACTS, '21-region-group-faired.png') });
  assert.deepEqual(problems, [], 'no console errors or outside requests');
});

const duck = sharedMesh('Duck.glb');

test('a glTF offers its node and mesh names as groups, each with the vertices of its triangles', async () => {
  // The test's own reading of the GLB: the JSON chunk, then the index accessor in the BIN chunk.
  const bytes = readFileSync(duck);
  const jsonLength = bytes.readUInt32LE(12);
  const json = JSON.parse(bytes.subarray(20, 20 + jsonLength).toString('utf8'));
  const bin = bytes.subarray(20 + jsonLength + 8);
  const names = [];
  const visit = (i) => {
    const node = json.nodes[i];
    if (node.mesh !== undefined) {
      for (const name of [node.name, json.meshes[node.mesh].name]) if (typeof name === 'string' && !names.includes(name)) names.push(name);
    }
    (node.children || []).forEach(visit);
  };
  json.scenes[json.scene ?? 0].nodes.forEach(visit);
  assert.deepEqual(names, ['LOD3spShape'], 'Duck has one named node with a mesh');
  const indices = json.accessors[json.meshes[0].primitives[0].indices];
  const view = json.bufferViews[indices.bufferView];
  assert.equal(indices.componentType, 5123, 'u16 indices');
  const used = new Set();
  for (let k = 0; k < indices.count; k++) used.add(bin.readUInt16LE((view.byteOffset || 0) + (indices.byteOffset || 0) + 2 * k));

  await page.goto(URL_BASE + '/');
  await page.setInputFiles('#files', [duck]);
  await page.waitForFunction(() => /Duck\.glb/.test(document.getElementById('file-info').textContent));
  await page.selectOption('[name="region"]', 'group');
  const options = await page.locator('[name="region.group"] option').evaluateAll((os) => os.map((o) => [o.value, o.textContent]));
  assert.deepEqual(options, [['LOD3spShape', `LOD3spShape (${used.size} vertices)`]]);
  assert.equal(Number(await page.locator('#region-info').getAttribute('data-inside')), used.size);
  assert.deepEqual(problems, [], 'no console errors or outside requests');
});
