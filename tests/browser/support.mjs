// Shared by the browser tests and the timing script: launching Debian's chromium, a page that
// records console errors and requests to other hosts, and where the shared meshes are.
import { chromium } from 'playwright-core';
import { createServer, connect } from 'node:net';
import { execFileSync, spawn } from 'node:child_process';
import { existsSync, mkdtempSync, readFileSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';

const here = dirname(fileURLToPath(import.meta.url));

export const URL_BASE = process.env.WILLOW_URL || 'http://127.0.0.1:8080';
export const ARTIFACTS = process.env.WILLOW_ARTIFACTS || resolve(here, '../../target/browser-artifacts');

/** `$WILLOW_SHARED_MESHES`, else ../shared/meshes beside the checkout, else /work/shared/meshes
 * (as crates/willow/tests/mesh_support does). Throws when none has `name`: a test that needs
 * a shared mesh fails without it, it is never skipped (issue 41). */
export function sharedMesh(name) {
  const dirs = process.env.WILLOW_SHARED_MESHES
    ? [process.env.WILLOW_SHARED_MESHES]
    : [resolve(here, '../../../shared/meshes'), '/work/shared/meshes'];
  for (const d of dirs) if (existsSync(join(d, name))) return join(d, name);
  throw new Error(`${name} is needed by the browser tests and is not in ${dirs.join(', ')}; set WILLOW_SHARED_MESHES`);
}

/** Headless chromium from Debian with a fresh profile: software WebGL (SwiftShader), no
 * network of its own (no component updates, sync or background requests). */
export async function launch() {
  const profile = mkdtempSync(join(tmpdir(), 'willow-chromium-'));
  const context = await chromium.launchPersistentContext(profile, {
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    acceptDownloads: true,
    viewport: { width: 1400, height: 1000 },
    args: [
      '--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
      '--disable-background-networking', '--disable-component-update', '--disable-sync',
      '--enable-unsafe-swiftshader',
    ],
  });
  // A page bundle built by hand (`node web/build.mjs DIR`) served in place of the one in the
  // binary: trying a change to web/src without rebuilding the server.
  const dev = process.env.WILLOW_WEB_OUT;
  if (dev) {
    const types = { 'index.html': 'text/html', 'app.js': 'text/javascript', 'app.css': 'text/css' };
    await context.route(/\/(ui\/app\.(js|css))?$/, (route) => {
      const path = new URL(route.request().url()).pathname;
      const name = path === '/' ? 'index.html' : path.slice(4);
      route.fulfill({ contentType: types[name], body: readFileSync(join(dev, name)) });
    });
  }
  const close = async () => {
    await context.close();
    rmSync(profile, { recursive: true, force: true });
  };
  return { context, close };
}

/** A page that records what the tests forbid: console errors, uncaught exceptions and any
 * request to a host other than the server. */
export async function watchedPage(context, base = URL_BASE) {
  const page = context.pages()[0] || (await context.newPage());
  const problems = [];
  const origin = new URL(base).origin;
  page.on('console', (m) => { if (m.type() === 'error') problems.push(`console error: ${m.text()}`); });
  page.on('pageerror', (e) => problems.push(`uncaught: ${e.message}`));
  page.on('request', (r) => {
    const u = r.url();
    if (u.startsWith('data:') || u.startsWith('blob:')) return;
    if (new URL(u).origin !== origin) problems.push(`request to another host: ${u}`);
  });
  return { page, problems };
}

export const stats = (page) => page.evaluate(() => ({ ...window.willowStats }));

export async function waitStats(page, predicate, arg, timeout = 120_000) {
  try {
    await page.waitForFunction(predicate, arg, { timeout, polling: 100 });
  } catch (e) {
    const s = await stats(page).catch(() => null);
    throw new Error(`${e.message}\nwaiting for ${predicate}\nwillowStats: ${JSON.stringify({ ...s, applyMs: undefined, renderMs: undefined })}`);
  }
  return stats(page);
}

/** A TCP proxy on a free loopback port in front of the server, so a test can drop every open
 * connection (`dropAll`) as a network would. */
export async function startProxy(target = URL_BASE) {
  const { hostname, port } = new URL(target);
  const sockets = new Set();
  const server = createServer((client) => {
    const upstream = connect(Number(port), hostname);
    for (const [a, b] of [[client, upstream], [upstream, client]]) {
      sockets.add(a);
      a.on('error', () => b.destroy());
      a.on('close', () => { sockets.delete(a); b.destroy(); });
      a.pipe(b);
    }
  });
  await new Promise((r) => server.listen(0, '127.0.0.1', r));
  return {
    url: `http://127.0.0.1:${server.address().port}`,
    dropAll: () => { for (const s of sockets) s.destroy(); },
    close: () => new Promise((r) => { for (const s of sockets) s.destroy(); server.close(r); }),
  };
}

/** Another `willow serve` (the binary scripts/browser-test.sh built, `$WILLOW_BIN`) on a free
 * loopback port with its own temporary data dir and `args` added; `stop()` ends it and removes
 * the dir. */
export async function startServer(args = []) {
  const bin = process.env.WILLOW_BIN;
  if (!bin) throw new Error('WILLOW_BIN is not set (run scripts/browser-test.sh)');
  const dir = mkdtempSync(join(tmpdir(), 'willow-browser-'));
  const child = spawn(bin, ['serve', '--addr', '127.0.0.1:0', '--data-dir', join(dir, 'data'),
    '--log-format', 'text', ...args], { stdio: ['ignore', 'pipe', 'pipe'] });
  let out = '';
  let err = '';
  child.stderr.on('data', (d) => { err = (err + d).slice(-20_000); });
  const url = await new Promise((resolveUrl, reject) => {
    const timer = setTimeout(() => reject(new Error(`willow serve did not start: ${err}`)), 20_000);
    child.stdout.on('data', (d) => {
      out += d;
      const m = /^listening on (\S+)/m.exec(out);
      if (m) { clearTimeout(timer); resolveUrl(m[1]); }
    });
    child.on('exit', (code) => { clearTimeout(timer); reject(new Error(`willow serve exited (${code}): ${err}`)); });
  });
  const stop = async () => {
    if (child.exitCode === null) {
      const exited = new Promise((r) => child.once('exit', r));
      child.kill('SIGTERM');
      await exited;
    }
    rmSync(dir, { recursive: true, force: true });
  };
  return { url, dir, stop, log: () => err };
}

/** `willow keys new`: `{ key, line }` (the key, and its line for the key file). */
export function newKey(tenant, name) {
  const out = execFileSync(process.env.WILLOW_BIN, ['keys', 'new', '--tenant', tenant, '--name', name], { encoding: 'utf8', stdio: ['ignore', 'pipe', 'pipe'] });
  const [key, line] = out.split('\n');
  return { key: key.trim(), line: line.trim() };
}

/** The `params` part of a multipart job submission. */
export function paramsPart(body) {
  const text = body.toString('latin1');
  const at = text.indexOf('name="params"');
  if (at < 0) throw new Error('the submission has no params part');
  const start = text.indexOf('\r\n\r\n', at) + 4;
  const end = text.indexOf('\r\n--', start);
  return JSON.parse(Buffer.from(text.slice(start, end), 'latin1').toString('utf8'));
}
