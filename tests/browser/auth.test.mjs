// The web page against a server with authentication (`--auth keys`): its own `willow serve`
// (started here from the binary scripts/browser-test.sh built) with a key file made by
// `willow keys new`. Without a key the page asks for one; with it a job runs to the end with
// its frames streamed through a stream token, and the key itself never appears in a URL.
import { after, before, test } from 'node:test';
import assert from 'node:assert/strict';
import { mkdtempSync, readFileSync, rmSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { ARTIFACTS, launch, newKey, sharedMesh, startProxy, startServer, stats, waitStats, watchedPage } from './support.mjs';

const spot = sharedMesh('spot_triangulated.obj');
const spotTexture = sharedMesh('spot_texture.png');

const TOKEN_TTL_S = 12;
let server;
let proxy;
let BASE;
let browser;
let page;
let problems;
let key;
let keysDir;
/** Every request the page made: URL, method and whether it carried Authorization. */
const requests = [];
const pending = [];

before(async () => {
  const made = newKey('web', 'browser-test');
  key = made.key;
  assert.match(key, /^wlw_/, 'willow keys new prints the key on its first line');
  keysDir = mkdtempSync(join(tmpdir(), 'willow-keys-'));
  const keysFile = join(keysDir, 'api-keys');
  writeFileSync(keysFile, `# browser test\n${made.line}\n`);
  // Short-lived stream tokens, so the second test sees one near its expiry.
  server = await startServer(['--workers', '1', '--auth', 'keys', '--api-keys-file', keysFile,
    '--stream-token-ttl-secs', String(TOKEN_TTL_S)]);
  // The page is loaded through a proxy, so a test can drop its connections.
  proxy = await startProxy(server.url);
  BASE = proxy.url;
  browser = await launch();
  ({ page, problems } = await watchedPage(browser.context, BASE));
  page.on('request', (r) => {
    const entry = { url: r.url(), method: r.method(), auth: null };
    requests.push(entry); // in the order they were made
    pending.push(r.allHeaders().then((h) => { entry.auth = h.authorization || null; }).catch(() => {}));
  });
});

after(async () => {
  await browser?.close();
  await proxy?.close();
  await server?.stop();
  if (keysDir) rmSync(keysDir, { recursive: true, force: true });
});

const shot = (name) => page.screenshot({ path: join(ARTIFACTS, `${name}.png`) });
/** The browser's own console line for a refused request (the page shows its message instead). */
const drop401 = () => problems.splice(0, problems.length, ...problems.filter((p) => !/status of 401/.test(p)));

test('with --auth keys: the page asks for a key, then runs a job with streamed frames; the key never goes in a URL', async () => {
  // Before the key: the dashboard's 401 asks for it, and the key field has the focus.
  await page.goto(BASE + '/');
  const msg = page.locator('#auth-msg');
  await msg.filter({ hasText: 'needs an API key' }).waitFor();
  assert.equal(await page.evaluate(() => document.activeElement?.id), 'api-key', 'the key field is focused');
  assert.match(await page.locator('#jobs-error').textContent(), /API key/);
  await shot('10-auth-needs-key');
  drop401();
  assert.deepEqual(problems, [], 'only the refused requests\' own console lines');

  // A wrong key is refused with the server's reason.
  await page.fill('#api-key', 'wlw_not-a-key');
  await page.press('#api-key', 'Enter');
  await msg.filter({ hasText: 'refused (invalid_token)' }).waitFor();
  drop401();

  // The right key: kept for this tab only.
  await page.fill('#api-key', key);
  await page.press('#api-key', 'Enter');
  await page.waitForFunction(() => document.getElementById('auth-msg').textContent === '');
  await page.waitForFunction(() => document.getElementById('jobs-error').textContent === '' && /updated/.test(document.getElementById('jobs-updated').textContent));
  const storage = await page.evaluate(() => ({ session: sessionStorage.getItem('willow.apiKey'), local: JSON.stringify({ ...localStorage }) }));
  assert.equal(storage.session, key);
  assert.ok(!storage.local.includes(key), 'nothing in localStorage');

  // A job, submitted and streamed.
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  // These tests drive the conformal flow (the page's default method is `denoise`).
  await page.selectOption('select[name=method]', 'conformal');
  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  const id = await page.evaluate(() => location.hash.slice(5));
  await waitStats(page, () => window.willowStats.framesApplied >= 3);
  const done = await waitStats(page, () => window.willowStats.state === 'succeeded');
  assert.equal(done.lastStep, 20);
  assert.equal(done.plotPoints, 21);
  await shot('11-auth-job-done');

  // The dashboard lists it.
  await page.locator(`#jobs-table tr[data-job-id="${id}"][data-state="succeeded"]`).waitFor({ timeout: 10_000 });

  // The result downloads through fetch with the header (a plain link would be refused).
  const [download] = await Promise.all([page.waitForEvent('download'), page.click('#dl-glb')]);
  const file = join(ARTIFACTS, 'auth-spot-result.glb');
  await download.saveAs(file);
  assert.ok(download.suggestedFilename().startsWith(id) && download.suggestedFilename().endsWith('.glb'), download.suggestedFilename());
  const glb = readFileSync(file);
  assert.equal(glb.toString('latin1', 0, 4), 'glTF', 'GLB magic');
  assert.equal(glb.readUInt32LE(8), glb.length);

  // A reload keeps the key (this tab's sessionStorage): the job's input (frame 0), history and
  // stream come back.
  await page.reload();
  assert.equal(await page.inputValue('#api-key'), key);
  const back = await waitStats(page, (id) => window.willowStats.jobId === id && window.willowStats.state === 'succeeded' && window.willowStats.triangleCount === 5856 && window.willowStats.plotPoints === 21 && window.willowStats.lastStep === 20, id);
  assert.ok(back.framesReceived >= 1, 'the final frame came through the stream again');

  await Promise.all(pending);
  const api = requests.filter((r) => new URL(r.url).pathname.startsWith('/v1/'));
  // The key is in no URL; the only credentials in URLs are stream tokens, on the events route.
  for (const r of requests) assert.ok(!r.url.includes(key) && !r.url.includes(encodeURIComponent(key)), `the key is in ${r.url}`);
  const events = api.filter((r) => r.url.includes(`/v1/jobs/${id}/events`));
  assert.ok(events.length >= 2, `one stream per page load: ${events.map((r) => r.url)}`);
  for (const r of events) {
    const q = new URL(r.url).searchParams;
    assert.ok(q.get('access_token') && !q.get('access_token').includes(key), `stream token in ${r.url}`);
    assert.ok(q.has('from_step'));
  }
  for (const r of api.filter((r) => new URL(r.url).searchParams.has('access_token'))) {
    assert.match(new URL(r.url).pathname, /\/events$/, 'stream tokens only on event streams');
  }
  const mints = api.filter((r) => r.method === 'POST' && r.url.endsWith(`/v1/jobs/${id}/stream-token`));
  assert.equal(mints.length, events.length, 'one token minted per stream opened');
  // Every other API call carries the key in its header (the refused ones before it was given
  // carried none or the wrong one).
  const withKey = api.filter((r) => !r.url.includes('/events'));
  const last401 = withKey.findLastIndex((r) => r.auth !== `Bearer ${key}`);
  assert.ok(withKey.slice(last401 + 1).length > 5, 'calls after the key was given');
  assert.ok(withKey.slice(last401 + 1).every((r) => r.auth === `Bearer ${key}`));
  assert.ok(withKey.some((r) => /\/frames\/0\?/.test(r.url) && r.auth === `Bearer ${key}`), 'frame 0 fetched with the header');

  assert.deepEqual(problems, [], 'no console errors once the key was given');

  // Clear: the key is gone from the tab, and the page asks again.
  await page.click('#api-key-clear');
  assert.equal(await page.inputValue('#api-key'), '');
  assert.equal(await page.evaluate(() => sessionStorage.getItem('willow.apiKey')), null);
  await msg.filter({ hasText: 'needs an API key' }).waitFor();
  drop401();
  assert.deepEqual(problems, []);
});

// Waits (bounded) until `streams` holds `count` requests; the assertions after it say what
// they must be.
async function streamsReach(streams, count, timeoutMs) {
  for (const end = Date.now() + timeoutMs; streams.length < count && Date.now() < end;) {
    await new Promise((resolve) => setTimeout(resolve, 50));
  }
}

test('with --auth keys: a dropped stream resumes by itself while its token is fresh (Last-Event-ID), with a new token once it is about to expire, and asks for a key when refused', async () => {
  await page.fill('#api-key', key);
  await page.press('#api-key', 'Enter');
  await page.waitForFunction(() => document.getElementById('auth-msg').textContent === '');
  await page.setInputFiles('#files', [spot, spotTexture]);
  await page.waitForFunction(() => /texture spot_texture\.png/.test(document.getElementById('file-info').textContent));
  // Long enough to run through all of this on a fast machine too; cancelled at the end.
  await page.fill('[name="steps"]', '10000');
  await page.fill('[name="tau"]', '0.02');
  // Every step: a flow that has settled would otherwise end `converged` before the test acts.
  await page.check('[name=all_steps]');
  const streams = [];
  const onRequest = async (r) => {
    if (!r.url().includes('/events')) return;
    const entry = { url: r.url(), at: Date.now(), lastEventId: undefined };
    streams.push(entry);
    entry.lastEventId = (await r.allHeaders())['last-event-id'];
  };
  page.on('request', onRequest);
  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  const id = await page.evaluate(() => location.hash.slice(5));
  await waitStats(page, () => window.willowStats.framesApplied >= 3 && window.willowStats.state === 'running');
  assert.equal(streams.length, 1);
  assert.ok(streams[0].url.includes(`/v1/jobs/${id}/events?`));
  const token = (u) => new URL(u).searchParams.get('access_token');

  // Well before the token's expiry: the browser reconnects by itself, same URL, Last-Event-ID.
  const s0 = await stats(page);
  assert.ok(Date.now() - streams[0].at < TOKEN_TTL_S * 1000 / 3, 'the machine is too slow for this test\'s timing');
  proxy.dropAll();
  await page.waitForFunction(() => document.getElementById('state').textContent === 'running', null, { timeout: 15_000 });
  // Frames already on their way when the stream dropped still arrive: progress alone does not
  // show the reconnection, so wait for the new request itself first.
  await streamsReach(streams, 2, 15_000);
  await waitStats(page, (n) => window.willowStats.lastStep > n + 2, s0.lastStep);
  assert.equal(streams.length, 2, streams.map((s) => s.url).join('\n'));
  assert.equal(streams[1].url, streams[0].url, 'the browser\'s own reconnection');
  assert.ok(Number(streams[1].lastEventId) >= s0.lastStep, `Last-Event-ID ${streams[1].lastEventId}`);

  // In the token's last third (the page's margin): a drop re-mints and re-opens after the
  // last step seen, instead of reconnecting with a token about to expire.
  const wait = streams[0].at + (TOKEN_TTL_S * 2 / 3) * 1000 + 300 - Date.now();
  if (wait > 0) await page.waitForTimeout(wait);
  const s1 = await stats(page);
  proxy.dropAll();
  await streamsReach(streams, 3, 30_000);
  await waitStats(page, (n) => window.willowStats.lastStep > n + 2, s1.lastStep, 30_000);
  assert.equal(streams.length, 3, streams.map((s) => s.url).join('\n'));
  const reopened = new URL(streams[2].url);
  assert.notEqual(token(streams[2].url), token(streams[0].url), 'a new stream token');
  assert.ok(Number(reopened.searchParams.get('from_step')) > s1.lastStep - 1, `from_step ${reopened.searchParams.get('from_step')} after step ${s1.lastStep}`);
  assert.equal(streams[2].lastEventId, undefined, 'a new stream, not the browser\'s reconnection');

  // The key cleared mid-run, and the stream drops once its token is old: without a key the
  // page opens a plain stream, which the server refuses (401: the browser gives up, CLOSED);
  // after a few refusals the page asks the API why, stops and asks for a key. The key again:
  // the job is watched again, streamed with a new token.
  await page.click('#api-key-clear');
  const wait2 = streams[2].at + (TOKEN_TTL_S * 2 / 3) * 1000 + 300 - Date.now();
  if (wait2 > 0) await page.waitForTimeout(wait2);
  const before = streams.length;
  proxy.dropAll();
  await page.locator('#view-error').filter({ hasText: 'needs an API key' }).waitFor({ timeout: 20_000 });
  const refused = streams.slice(before);
  assert.ok(refused.length >= 3 && refused.every((s) => !token(s.url)), `plain streams, refused: ${refused.map((s) => s.url)}`);
  await page.waitForTimeout(2500);
  assert.equal(streams.length, before + refused.length, 'no more attempts once the page asked for a key');
  assert.match(await page.locator('#auth-msg').textContent(), /needs an API key/);
  problems.splice(0, problems.length, ...problems.filter((p) => !/status of 401|EventSource|ERR_INCOMPLETE_CHUNKED_ENCODING|ERR_EMPTY_RESPONSE|ERR_CONNECTION|Failed to fetch|network/.test(p)));
  const s2 = await stats(page);
  await page.fill('#api-key', key);
  await page.press('#api-key', 'Enter');
  await waitStats(page, (n) => window.willowStats.state === 'running' && window.willowStats.lastStep > n + 2, s2.lastStep, 30_000);
  assert.ok(token(streams[streams.length - 1].url), 'streamed with a token again');
  page.off('request', onRequest);

  await page.click('#cancel');
  await waitStats(page, () => window.willowStats.state === 'cancelled', null, 60_000);
  for (const s of streams) assert.ok(!s.url.includes(key));
  // Requests cut by the drops are the browser's console errors, not the page's.
  problems.splice(0, problems.length, ...problems.filter((p) => !/ERR_INCOMPLETE_CHUNKED_ENCODING|ERR_EMPTY_RESPONSE|ERR_CONNECTION|Failed to fetch|network/.test(p)));
  assert.deepEqual(problems, []);
});
