// The page at `/`: upload a mesh, choose the job's parameters, watch the surface flow live
// (3D view + metric plots), cancel, download, and a dashboard of all jobs. Everything talks to
// the same server that served the page, through the public API only.
import { ApiError, api, apiKey, bytes, json, onUnauthorized, setApiKey } from './api.js';
import { MEDIA_TYPES, decodeBase64Into, formatOf, parseMesh, withOrigin } from './meshio.js';
import { Plots } from './plots.js';
import { RegionControls } from './region.js';
import { View } from './view.js';

/** Timings and counters, read by the browser tests and the 100k-triangle timing script. */
const stats = {
  jobId: null, modelJobId: null, state: null, framesReceived: 0, framesApplied: 0, lastStep: -1,
  lastApplyMs: 0, maxApplyMs: 0, applyMsTotal: 0, lastDecodeMs: 0,
  lastRenderMs: 0, maxRenderMs: 0, renderMsTotal: 0, renderCount: 0,
  plotPoints: 0, vertexCount: 0, triangleCount: 0, reconnects: 0,
  // The last 1000 per-frame times, for percentiles.
  applyMs: [], renderMs: [],
  // The timing script sets this to make each render wait until the frame is drawn.
  syncGpu: false,
};
window.willowStats = stats;

const $ = (id) => document.getElementById(id);
const form = $('params');
const view = new View($('canvas'), stats);
const plots = new Plots();
const regionControls = new RegionControls(view, form);
view.onModel(() => { $('show-input').checked = false; });
/** For the timing script, the browser tests and debugging in the console. */
window.willow = { view, plots, regionControls };

/** Positions of kept frames held in memory for the scrub slider, up to this many bytes. */
const FRAME_CACHE_BYTES = 256 << 20;
/** Dashboard poll period: the list is one small query, and a human reads it at this pace. */
const JOBS_POLL_MS = 2000;
const JOBS_PAGE_SIZE = 10;
/** Wait before re-opening an event stream the browser gave up on. */
const RECONNECT_MS = 1000;
/** A stream token this close to its expiry (or a third of its lifetime, if less) is not
 * trusted to cover the browser's own reconnection: a fresh one is minted instead. */
const TOKEN_MARGIN_S = 30;

let config = null;
let upload = null; // { file, format, texture: File|null, model }
let watch = null; // the job being watched (see startWatch)

// ---------------------------------------------------------------------------------------------
// Parameters: defaults and limits from the server's own rules (/ui/config.json, built from the
// same constants the API validates with) and help text from /openapi.json.

async function loadConfig() {
  const [cfg, openapi] = await Promise.all([json('/ui/config.json'), json('/openapi.json').catch(() => null)]);
  config = cfg;
  const method = form.elements.method;
  for (const m of cfg.methods) method.add(new Option(m, m));
  const d = cfg.defaults;
  for (const name of ['method', 'steps', 'tau', 'iterations', 'frame_interval']) form.elements[name].value = d[name];
  for (const name of ['include_positions', 'safeguard', 'exactness', 'mobius_balancing']) form.elements[name].checked = d[name];
  // Empty means the default, shown as the placeholder (iterations: `auto`, read off the mesh).
  for (const k of ['vertex_iterations', 'sigma_r', 'radius']) form.elements[`denoise.${k}`].placeholder = d.denoise[k];
  form.elements['denoise.guided'].checked = d.denoise.guided;
  const L = cfg.limits;
  setRange('steps', 1, L.max_steps);
  setRange('iterations', 1, L.max_iterations);
  setRange('frame_interval', 1, null);
  setRange('deadline_secs', null, L.max_deadline_secs);
  setRange('filter.k', 0, L.max_filter_k);
  setRange('boundary.prescribed.frame_angle', -L.max_frame_angle, L.max_frame_angle);
  form.elements.tau.min = 0;
  // Help text: the API's own parameter descriptions.
  const params = openapi?.paths?.['/v1/jobs']?.post?.parameters || [];
  for (const p of params) {
    const el = form.elements.namedItem(p.name);
    if (el && p.description && el.closest) el.closest('label').title = p.description;
  }
  updateFormVisibility();
}

/** Show a job's parameters (its `params`, every field reported) in the form. */
function fillForm(p) {
  const e = form.elements;
  for (const name of ['method', 'steps', 'tau', 'iterations', 'frame_interval']) e[name].value = p[name];
  e.deadline_secs.value = p.deadline_secs ?? '';
  for (const name of ['include_positions', 'safeguard', 'exactness', 'mobius_balancing']) e[name].checked = p[name];
  e.filter.checked = !!p.filter;
  if (p.filter) { e['filter.sigma'].value = p.filter.sigma; e['filter.k'].value = p.filter.k; }
  if (typeof p.boundary === 'string') {
    e.boundary.value = p.boundary;
  } else if (p.boundary?.prescribed) {
    const b = p.boundary.prescribed;
    e.boundary.value = 'prescribed';
    e['boundary.prescribed.frame_angle'].value = b.frame_angle;
    const fixed = b.axis && b.axis.fixed;
    e['boundary.prescribed.axis'].value = fixed ? 'fixed' : 'tangent';
    e['boundary.prescribed.axis.fixed'].value = fixed ? fixed.join(',') : '';
    const perLoop = b.angles && b.angles.per_loop;
    e['boundary.prescribed.angles'].value = perLoop ? 'per_loop' : 'uniform';
    e['boundary.prescribed.angles.per_loop'].value = perLoop ? perLoop.join(',') : '';
    e['boundary.prescribed.angles.uniform'].value = perLoop ? 0 : b.angles?.uniform ?? 0;
  }
  for (const k of ['iterations', 'vertex_iterations', 'sigma_r', 'radius']) {
    const v = p.denoise?.[k];
    e[`denoise.${k}`].value = v === undefined || v === null || v === config.defaults.denoise[k] ? '' : v;
  }
  e['denoise.guided'].checked = p.denoise?.guided ?? config.defaults.denoise.guided;
  regionControls.fill(p);
  updateFormVisibility();
}

function setRange(name, min, max) {
  const el = form.elements.namedItem(name);
  if (min !== null) el.min = min;
  if (max !== null) el.max = max;
  const hint = [min !== null ? `≥ ${min}` : '', max !== null ? `≤ ${max}` : ''].filter(Boolean).join(', ');
  if (hint) el.placeholder = el.placeholder || hint;
}

function updateFormVisibility() {
  const e = form.elements;
  $('prescribed').hidden = e.boundary.value !== 'prescribed';
  e['filter.sigma'].disabled = e['filter.k'].disabled = !e.filter.checked;
  e['boundary.prescribed.axis.fixed'].disabled = e['boundary.prescribed.axis'].value !== 'fixed';
  const perLoop = e['boundary.prescribed.angles'].value === 'per_loop';
  e['boundary.prescribed.angles.uniform'].disabled = perLoop;
  e['boundary.prescribed.angles.per_loop'].disabled = !perLoop;
  $('conformal-only').classList.toggle('muted', e.method.value !== 'conformal');
  $('denoise-only').classList.toggle('muted', e.method.value !== 'denoise');
}

class FieldError extends Error {
  constructor(field, detail) { super(detail); this.problem = { field, detail }; }
}

/** The `params` JSON part, in the shape of the API's JobParams. */
function readParams() {
  const e = form.elements;
  // Numbers go as typed: the API says what is wrong with them (a fraction for `steps`, …).
  const num = (name) => {
    const el = e[name];
    if (el.validity.badInput) throw new FieldError(name, `invalid parameter \`${name}\`: not a number`);
    if (el.value.trim() === '') return undefined;
    return Number(el.value);
  };
  const list = (name) => e[name].value.split(',').filter((t) => t.trim() !== '').map((t) => {
    const v = Number(t.trim());
    if (!Number.isFinite(v)) throw new FieldError(name, `invalid parameter \`${name}\`: \`${t.trim()}\` is not a number`);
    return v;
  });
  const p = {
    method: e.method.value,
    steps: num('steps'),
    tau: num('tau'),
    iterations: num('iterations'),
    frame_interval: num('frame_interval'),
    include_positions: e.include_positions.checked,
    deadline_secs: num('deadline_secs'),
    safeguard: e.safeguard.checked,
    exactness: e.exactness.checked,
    mobius_balancing: e.mobius_balancing.checked,
  };
  if (e.filter.checked) p.filter = { sigma: num('filter.sigma'), k: num('filter.k') };
  const b = e.boundary.value;
  if (b === 'prescribed') {
    const axis = e['boundary.prescribed.axis'].value === 'fixed' ? { fixed: list('boundary.prescribed.axis.fixed') } : 'tangent';
    const angles = e['boundary.prescribed.angles'].value === 'per_loop'
      ? { per_loop: list('boundary.prescribed.angles.per_loop') }
      : { uniform: num('boundary.prescribed.angles.uniform') ?? 0 };
    p.boundary = { prescribed: { frame_angle: num('boundary.prescribed.frame_angle') ?? 0, axis, angles } };
  } else {
    p.boundary = b;
  }
  // The denoising filter's knobs, under the method they belong to, each only once set.
  if (p.method === 'denoise') {
    const d = {};
    for (const k of ['iterations', 'vertex_iterations', 'sigma_r', 'radius']) d[k] = num(`denoise.${k}`);
    if (e['denoise.guided'].checked !== config.defaults.denoise.guided) d.guided = e['denoise.guided'].checked;
    for (const k of Object.keys(d)) if (d[k] === undefined) delete d[k];
    if (Object.keys(d).length > 0) p.denoise = d;
  }
  Object.assign(p, regionControls.params());
  for (const k of Object.keys(p)) if (p[k] === undefined) delete p[k];
  return p;
}

function clearErrors() {
  $('form-error').textContent = '';
  for (const el of form.querySelectorAll('.invalid')) el.classList.remove('invalid');
  for (const el of form.querySelectorAll('.field-error')) el.remove();
}

/** Show a problem as the API words it; highlight the field it names. */
function showProblem(problem) {
  const field = problem.field;
  let el = field ? form.elements.namedItem(field) : null;
  if (field && !el) el = [...form.elements].find((x) => x.name && x.name.startsWith(field + '.')) || null;
  if (el && el.classList) {
    el.classList.add('invalid');
    const note = document.createElement('span');
    note.className = 'field-error';
    note.textContent = problem.detail;
    el.closest('label').append(note);
    el.focus();
  }
  $('form-error').textContent = problem.detail + (problem.code ? ` (${problem.code})` : '');
}

// ---------------------------------------------------------------------------------------------
// Upload: the mesh is parsed here as well, so the input appears at once.

async function takeFiles(files) {
  const list = [...files];
  const mesh = list.find((f) => formatOf(f.name));
  const image = list.find((f) => f.type.startsWith('image/') || /\.(png|jpe?g|webp)$/i.test(f.name));
  clearErrors();
  $('view-error').textContent = '';
  try {
    if (mesh) {
      const format = formatOf(mesh.name);
      const model = parseMesh(await mesh.arrayBuffer(), format);
      upload = { file: mesh, format, texture: image || null, model };
      stopWatching();
      history.replaceState(null, '', location.pathname + location.search);
      plots.clear();
      resetJobUi();
    } else if (image && upload) {
      upload.texture = image;
    } else if (image) {
      throw new Error('choose the mesh (OBJ, glTF, GLB, STL, PLY or OFF) first, or together with its image');
    } else {
      throw new Error('no OBJ, glTF, GLB, STL, PLY or OFF file among the files given');
    }
    const bitmaps = await textureBitmaps(upload.model, upload.texture);
    view.setModel(upload.model, bitmaps);
    const textured = bitmaps.some(Boolean);
    $('colour').value = textured ? 'texture' : view.colour === 'curvature' ? 'curvature' : 'plain';
    view.setColour($('colour').value);
    const m = upload.model;
    $('file-info').textContent = `${upload.file.name}: ${m.fileVertexCount} vertices, ${stats.triangleCount} triangles` +
      (textured ? `, texture ${upload.texture ? upload.texture.name : '(embedded)'}` : '');
    $('submit').disabled = false;
  } catch (e) {
    $('form-error').textContent = `cannot read the file: ${e.message}`;
  }
}

async function textureBitmaps(model, imageFile) {
  if (model.uvFlipY) {
    // OBJ: the user's image; v runs up in OBJ, so the bitmap is flipped once here.
    return imageFile ? [await createImageBitmap(imageFile, { imageOrientation: 'flipY' })] : [];
  }
  return Promise.all(model.images.map((b) => (b ? createImageBitmap(b).catch(() => null) : null)));
}

async function submitJob(ev) {
  ev.preventDefault();
  clearErrors();
  if (!upload) return;
  let params;
  try {
    params = readParams();
  } catch (e) {
    showProblem(e.problem || { detail: e.message });
    return;
  }
  const body = new FormData();
  body.append('mesh', new Blob([upload.file], { type: MEDIA_TYPES[upload.format] }), upload.file.name);
  body.append('params', new Blob([JSON.stringify(params)], { type: 'application/json' }));
  $('submit').disabled = true;
  try {
    const job = await json('/v1/jobs', { method: 'POST', body });
    if (upload.texture && upload.model.uvFlipY) rememberTexture(job.id, upload.texture);
    upload.jobId = job.id;
    location.hash = `job=${job.id}`; // hashchange starts watching it (with the model we have)
  } catch (e) {
    showProblem(e instanceof ApiError ? e.problem : { detail: e.message });
  } finally {
    $('submit').disabled = false;
  }
}

/** The OBJ's image is not part of the job: keep it for this tab, so a reload still shows it. */
function rememberTexture(id, file) {
  if (file.size > 4 << 20) return;
  const r = new FileReader();
  r.onload = () => { try { sessionStorage.setItem(`willow.texture.${id}`, r.result); } catch { /* full */ } };
  r.readAsDataURL(file);
}

function rememberedTexture(id) {
  const url = sessionStorage.getItem(`willow.texture.${id}`);
  if (!url) return null;
  const comma = url.indexOf(',');
  const bin = atob(url.slice(comma + 1));
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return new Blob([out], { type: url.slice(5, url.indexOf(';')) });
}

// ---------------------------------------------------------------------------------------------
// Watching a job: SSE frames move the surface and grow the plots; a reload or a dropped
// connection resumes where it stopped.

function stopWatching() {
  if (watch) {
    watch.closed = true;
    watch.es?.close();
    clearTimeout(watch.retry);
  }
  watch = null;
}

function resetJobUi() {
  stats.framesReceived = stats.framesApplied = 0;
  stats.lastStep = -1;
  stats.state = stats.jobId = stats.modelJobId = null;
  $('job-title').textContent = 'no job';
  $('state').textContent = '';
  $('state').className = 'badge';
  $('cancel').disabled = true;
  $('downloads').classList.add('disabled');
  $('scrub').disabled = true;
  $('scrub-label').textContent = '';
  $('outcome').hidden = true;
  updateCounter();
}

async function startWatch(id) {
  stopWatching();
  resetJobUi();
  const w = {
    id, job: null, es: null, closed: false, retry: null, lastStep: -1, pending: null,
    modelReady: false, buffer: null, cache: new Map(), cacheBytes: 0, kept: new Set(), format: null,
  };
  watch = w;
  stats.jobId = id;
  $('job-title').textContent = `job ${id.slice(0, 8)}`;
  plots.clear();
  let job;
  try {
    job = await json(`/v1/jobs/${id}`);
  } catch (e) {
    $('view-error').textContent = e.message;
    return;
  }
  if (w.closed) return;
  w.format = job.input_format;
  updateJob(job);
  const fresh = !!upload && upload.jobId === id;
  const reshaped = job.params.refine || (job.params.fill_holes !== undefined && job.params.fill_holes !== null);
  if (fresh && !reshaped) {
    // Just submitted from this page: the job's input is the upload. A filled or refined job
    // before it may have left its own mesh on screen: draw the upload's again.
    if (view.model !== upload.model) {
      const bitmaps = await textureBitmaps(upload.model, upload.texture);
      if (w.closed) return;
      view.setModel(upload.model, bitmaps);
      view.setColour($('colour').value);
    }
    w.modelReady = true;
    stats.modelJobId = id;
  } else if (fresh) {
    // Refined or filled: the job runs on another mesh (its frames say connectivity_changed), so
    // the model on screen is frame 0's. The job computes that mesh after it starts, so it is
    // fetched when the stream delivers the first frame, not at once.
    w.modelDeferred = true;
  } else {
    upload = null;
    fillForm(job.params);
    $('submit').disabled = true;
    $('file-info').textContent = 'No mesh chosen.';
    // Frame 0 exists once the job has started: a queued job's model is fetched at its first
    // frame. Frames wait in `pending` until the model is ready.
    if (job.state === 'queued') w.modelDeferred = true;
    else loadModel(w);
  }
  // History first (cheap metrics), then the stream from the last kept frame at or before it.
  let from = 0;
  if (!fresh) {
    let next = 0;
    while (next !== undefined && !w.closed) {
      const page = await json(`/v1/jobs/${id}/frames?from_step=${next}&page_size=1000`);
      for (const m of page.frames) { plots.add(m); w.lastStep = Math.max(w.lastStep, m.step); noteKept(w, m.step); }
      next = page.next_from_step;
    }
    stats.plotPoints = plots.points;
    if (w.lastStep > 0) {
      const fi = job.params.frame_interval;
      const terminal = ['succeeded', 'failed', 'cancelled'].includes(job.state);
      from = terminal && job.progress.step === w.lastStep ? w.lastStep : Math.floor(w.lastStep / fi) * fi;
    }
  }
  if (!w.closed) openStream(w, from);
}

function noteKept(w, step) {
  const job = w.job;
  if (!job || !job.params.include_positions) return;
  if (step % job.params.frame_interval === 0 || step === job.progress.step) w.kept.add(step);
}

async function loadModel(w) {
  for (;;) {
    try {
      const model = parseMesh(await bytes(`/v1/jobs/${w.id}/frames/0?format=${w.format}`), w.format);
      if (w.closed) return;
      const tex = model.uvFlipY ? rememberedTexture(w.id) : null;
      const bitmaps = await textureBitmaps(model, tex);
      view.setModel(model, bitmaps);
      $('colour').value = bitmaps.some(Boolean) ? 'texture' : $('colour').value === 'texture' ? 'plain' : $('colour').value;
      view.setColour($('colour').value);
      w.modelReady = true;
      // Which job's mesh is on screen: tests wait for it, not only for the job's state.
      stats.modelJobId = w.id;
      schedule(w);
      return;
    } catch (e) {
      // Frame 0 not stored yet (the job was re-queued meanwhile): try again shortly.
      if (!(e instanceof ApiError && e.status === 404) || w.closed) {
        if (!w.closed) $('view-error').textContent = `cannot load the input: ${e.message}`;
        return;
      }
      await new Promise((r) => setTimeout(r, 1000));
      if (w.closed) return;
    }
  }
}

/** Open the job's event stream from step `from`. With an API key set, a stream token for this
 * job is minted first and goes in the URL (EventSource cannot send the Authorization header; the
 * key itself never goes in a URL). Without a key, no token: the URL as it always was. */
async function openStream(w, from) {
  let url = `/v1/jobs/${w.id}/events?from_step=${from}`;
  w.tokenExpires = null;
  if (apiKey()) {
    let t;
    try {
      t = await json(`/v1/jobs/${w.id}/stream-token`, { method: 'POST' });
    } catch (e) {
      if (w.closed) return;
      if (e instanceof ApiError && e.status === 401) {
        $('view-error').textContent = e.message; // and the key field asks for a key
        return;
      }
      // The server is away for a moment (restarting): try again, as for a stream it dropped.
      stats.reconnects++;
      $('state').textContent = 'reconnecting…';
      w.retry = setTimeout(() => { if (!w.closed) openStream(w, from); }, RECONNECT_MS);
      return;
    }
    if (w.closed) return;
    url += `&access_token=${encodeURIComponent(t.token)}`;
    const margin = Math.min(TOKEN_MARGIN_S, t.expires_in / 3);
    w.tokenExpires = Date.now() + (t.expires_in - margin) * 1000;
  }
  const es = new EventSource(url);
  w.es = es;
  es.addEventListener('state', (ev) => updateJob(JSON.parse(ev.data)));
  es.addEventListener('frame', (ev) => onFrame(w, JSON.parse(ev.data)));
  es.addEventListener('done', (ev) => {
    es.close();
    updateJob(JSON.parse(ev.data));
    finishRun(w);
  });
  es.onerror = () => {
    if (w.closed || isTerminal(w.job)) return;
    // CONNECTING: the browser retries by itself and sends Last-Event-ID. CLOSED: it gave up
    // (e.g. the server answered an error while restarting); re-open after the last step seen.
    stats.reconnects++;
    $('state').textContent = 'reconnecting…';
    if (es.readyState === EventSource.CLOSED) {
      w.refused = (w.refused || 0) + 1;
      w.retry = setTimeout(async () => {
        if (w.closed) return;
        if (w.refused >= 3) {
          // Refused again and again: ask the API why. A 401 (the key was cleared or revoked)
          // stops here and asks for a key; a new one watches the job again.
          try {
            updateJob(await json(`/v1/jobs/${w.id}`));
          } catch (e) {
            if (e instanceof ApiError && e.status === 401) { $('view-error').textContent = e.message; return; }
          }
          if (w.closed || isTerminal(w.job)) return;
        }
        openStream(w, w.lastStep + 1);
      }, RECONNECT_MS);
    } else if (w.tokenExpires !== null && Date.now() >= w.tokenExpires) {
      // The browser would reconnect with a token about to expire (its URL cannot change): a
      // fresh token and a new stream from the last step seen instead. An open stream is never
      // cut when its token expires; the token is checked when a connection opens.
      es.close();
      w.retry = setTimeout(() => { if (!w.closed) openStream(w, w.lastStep + 1); }, 0);
    }
  };
  es.onopen = () => { w.refused = 0; if (w.job) updateJob(w.job); };
}

function onFrame(w, f) {
  if (w.closed) return;
  stats.framesReceived++;
  if (w.modelDeferred) {
    w.modelDeferred = false;
    loadModel(w);
  }
  w.lastStep = Math.max(w.lastStep, f.step);
  stats.lastStep = w.lastStep;
  plots.add(f.metrics);
  stats.plotPoints = plots.points;
  if (w.job) {
    w.job.progress.step = Math.max(w.job.progress.step, f.step);
    w.job.metrics.latest = f.metrics;
  }
  if (f.positions_b64) {
    w.kept.add(f.step);
    w.pending = { step: f.step, b64: f.positions_b64, origin: f.origin };
    schedule(w);
  }
  updateCounter();
}

/** Apply the newest pending frame once per animation frame: frames that arrive faster than the
 * screen refreshes are skipped, not queued. */
function schedule(w) {
  if (w.scheduled) return;
  w.scheduled = true;
  requestAnimationFrame(() => {
    w.scheduled = false;
    if (w.closed || !w.pending || !w.modelReady || !view.model) return;
    const { step, b64, origin } = w.pending;
    w.pending = null;
    const t0 = performance.now();
    const n = view.model.fileVertexCount * 12;
    if (!w.buffer || w.buffer.byteLength !== n) w.buffer = new Uint8Array(n);
    const got = decodeBase64Into(b64, w.buffer);
    if (got !== n) {
      $('view-error').textContent = `frame ${step} has ${got} bytes of positions, expected ${n}`;
      return;
    }
    const positions = withOrigin(new Float32Array(w.buffer.buffer, 0, n / 4), origin);
    stats.lastDecodeMs = performance.now() - t0;
    if (w.cacheBytes + n <= FRAME_CACHE_BYTES && !w.cache.has(step)) {
      w.cache.set(step, positions.slice());
      w.cacheBytes += n;
    }
    view.applyPositions(positions);
    const ms = performance.now() - t0;
    stats.lastApplyMs = ms;
    stats.maxApplyMs = Math.max(stats.maxApplyMs, ms);
    stats.applyMsTotal += ms;
    record(stats.applyMs, ms);
    stats.framesApplied++;
    w.shownStep = step;
    updateCounter();
  });
}

function record(list, ms) {
  list.push(ms);
  if (list.length > 1000) list.shift();
}

function updateCounter() {
  const el = $('frame-counter');
  const total = watch?.job?.progress.total_steps;
  el.textContent = `frames ${stats.framesApplied}` + (watch?.shownStep !== undefined ? ` · step ${watch.shownStep}${total ? '/' + total : ''}` : '');
  el.dataset.framesApplied = stats.framesApplied;
}

const isTerminal = (job) => !!job && ['succeeded', 'failed', 'cancelled'].includes(job.state);

function updateJob(job) {
  if (!watch || job.id !== watch.id) return;
  // A terminal state is final: a response that left the server before it (the cancel call's
  // own "running", answered just before the stream's `done`) must not undo it.
  if (isTerminal(watch.job) && !isTerminal(job)) return;
  watch.job = job;
  stats.state = job.state;
  const badge = $('state');
  badge.textContent = job.state + (job.error_code && job.error_code !== job.state ? `: ${job.error_code}` : '');
  badge.title = job.error || '';
  badge.className = `badge s-${job.state}`;
  $('cancel').disabled = isTerminal(job);
  const ok = job.state === 'succeeded';
  $('downloads').classList.toggle('disabled', !ok);
  for (const f of ['glb', 'gltf', 'obj', 'stl', 'ply', 'off']) {
    const a = $(`dl-${f}`);
    if (ok) a.href = `${job.links.result}?format=${f}`; else a.removeAttribute('href');
  }
  if (job.error && job.state !== 'succeeded') $('view-error').textContent = job.error;
  showOutcome(job);
  updateCounter();
}

/** How the job ended and why (`outcome`, `outcome_reason`), once it has: absent fields (a
 * server without them) show the state alone, or nothing. */
function showOutcome(job) {
  const el = $('outcome');
  const outcome = isTerminal(job) ? job.outcome || (job.state === 'succeeded' ? null : job.state) : null;
  el.hidden = !outcome;
  el.dataset.outcome = outcome || '';
  if (!outcome) return;
  const b = document.createElement('b');
  b.textContent = `ended: ${outcome.replaceAll('_', ' ')}`;
  const why = job.outcome_reason || (job.outcome ? '' : job.error) || '';
  el.replaceChildren(b, why ? ` — ${why}` : '');
}

/** A result download link, clicked. Without a key it is the plain link, as ever; with one the
 * file is fetched with the Authorization header and handed to the browser as a blob URL. */
async function downloadResult(ev) {
  const a = ev.currentTarget;
  const href = a.getAttribute('href');
  if (!href || !apiKey()) return;
  ev.preventDefault();
  try {
    const res = await api(href);
    const blob = await res.blob();
    const m = /filename="([^"]+)"/.exec(res.headers.get('content-disposition') || '');
    const name = m ? m[1] : `${watch?.id || 'willow'}-result.${new URL(href, location.href).searchParams.get('format')}`;
    const url = URL.createObjectURL(blob);
    const tmp = document.createElement('a');
    tmp.href = url;
    tmp.download = name;
    document.body.append(tmp);
    tmp.click();
    tmp.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60_000);
  } catch (e) {
    $('view-error').textContent = `cannot download the result: ${e.message}`;
  }
}

function finishRun(w) {
  if (w.closed) return;
  for (let s = 0; s <= w.lastStep; s++) noteKept(w, s);
  const steps = [...w.kept].sort((a, b) => a - b);
  w.keptSteps = steps;
  const scrub = $('scrub');
  scrub.max = Math.max(0, steps.length - 1);
  scrub.value = scrub.max;
  scrub.disabled = steps.length < 2;
  $('scrub-label').textContent = steps.length ? `step ${steps[steps.length - 1]} (${steps.length} kept)` : 'no kept frames';
}

async function scrubTo(index) {
  const w = watch;
  if (!w || !w.keptSteps) return;
  const step = w.keptSteps[index];
  $('scrub-label').textContent = `step ${step} (${w.keptSteps.length} kept)`;
  let positions = w.cache.get(step);
  if (!positions) {
    try {
      const model = parseMesh(await bytes(`/v1/jobs/${w.id}/frames/${step}?format=${w.format}`), w.format);
      positions = model.filePositions;
      w.cache.set(step, positions);
    } catch (e) {
      $('view-error').textContent = e.message;
      return;
    }
  }
  if (watch !== w || w.keptSteps[+$('scrub').value] !== step) return; // the slider moved on
  view.applyPositions(positions);
  w.shownStep = step;
  updateCounter();
}

async function cancelJob() {
  if (!watch) return;
  try {
    updateJob(await json(`/v1/jobs/${watch.id}/cancel`, { method: 'POST' }));
  } catch (e) {
    $('view-error').textContent = e.message;
  }
}

// ---------------------------------------------------------------------------------------------
// Jobs dashboard: a paged list, polled.

const dash = { tokens: [null], page: 0, timer: null };

async function refreshJobs() {
  clearTimeout(dash.timer);
  const state = $('jobs-state').value;
  const q = new URLSearchParams({ page_size: JOBS_PAGE_SIZE });
  if (state) q.set('state', state);
  const token = dash.tokens[dash.page];
  if (token) q.set('page_token', token);
  try {
    const list = await json(`/v1/jobs?${q}`);
    renderJobs(list.jobs);
    dash.tokens[dash.page + 1] = list.next_page_token || null;
    $('jobs-next').disabled = !list.next_page_token;
    $('jobs-prev').disabled = dash.page === 0;
    $('jobs-updated').textContent = `updated ${new Date().toLocaleTimeString()}`;
    $('jobs-error').textContent = '';
  } catch (e) {
    $('jobs-error').textContent = e.message;
    // No (valid) key: polling again would only repeat the 401; a new key refreshes the list.
    if (e instanceof ApiError && e.status === 401) return;
  }
  dash.timer = setTimeout(refreshJobs, JOBS_POLL_MS);
}

function renderJobs(jobs) {
  const body = $('jobs-table').tBodies[0];
  const rows = jobs.map((j) => {
    const tr = document.createElement('tr');
    tr.dataset.jobId = j.id;
    tr.dataset.state = j.state;
    if (watch && watch.id === j.id) tr.className = 'current';
    const m = j.metrics.latest;
    const ran = j.started_time ? duration(j.started_time, j.finished_time) : '';
    const cells = [
      `<a href="#job=${j.id}"><code>${j.id.slice(0, 8)}</code></a>`,
      `<span class="badge s-${j.state}" title="${escapeHtml(j.error || '')}">${j.state}${j.error_code && j.error_code !== j.state ? ': ' + j.error_code : ''}</span>`,
      `<progress max="${j.progress.total_steps}" value="${j.progress.step}"></progress> ${j.progress.step}/${j.progress.total_steps}`,
      m ? m.willmore_energy.toPrecision(5) : '',
      m ? m.q_mean.toFixed(4) : '',
      escapeHtml(`${j.input_format} · ${j.face_count} tris · ${j.params.method}`),
      new Date(j.created_time).toLocaleTimeString(),
      ran,
      isTerminal(j) ? '' : `<button type="button" data-cancel="${j.id}">cancel</button>`,
    ];
    tr.innerHTML = cells.map((c) => `<td>${c}</td>`).join('');
    return tr;
  });
  body.replaceChildren(...rows);
}

function duration(from, to) {
  const s = ((to ? Date.parse(to) : Date.now()) - Date.parse(from)) / 1000;
  return s < 60 ? `${s.toFixed(1)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

const escapeHtml = (s) => s.replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);

// ---------------------------------------------------------------------------------------------
// API key: typed into the header's field, kept in sessionStorage (api.js). A 401 anywhere asks
// for one there; a new key re-runs what the 401 stopped.

let authFailed = false;

onUnauthorized((e) => {
  const msg = $('auth-msg');
  const first = !authFailed || msg.textContent !== e.message;
  authFailed = true;
  msg.textContent = e.message;
  // Focus once per message, not on every call that fails the same way (the user may be typing
  // elsewhere).
  if (first) $('api-key').focus();
});

function useKey(key) {
  key = key.trim();
  const changed = key !== apiKey();
  if (!changed && !authFailed) return;
  setApiKey(key);
  $('api-key').value = key;
  $('auth-msg').textContent = '';
  const retry = authFailed;
  authFailed = false;
  if (retry || changed) {
    $('jobs-error').textContent = '';
    dash.tokens = [null];
    dash.page = 0;
    refreshJobs();
    if ($('form-error').textContent.includes('API key')) $('form-error').textContent = '';
    // The watched job stopped at a 401 (its details, input or stream): watch it again.
    if (retry && watch) {
      $('view-error').textContent = '';
      startWatch(watch.id);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Wiring

function onHash() {
  const m = /^#job=([0-9a-f-]+)$/i.exec(location.hash);
  if (m && (!watch || watch.id !== m[1])) startWatch(m[1]);
  if (location.hash === '#jobs') $('jobs').scrollIntoView();
}

function wire() {
  $('api-key').value = apiKey();
  $('auth').addEventListener('submit', (e) => { e.preventDefault(); useKey($('api-key').value); });
  // Leaving the field with a new key uses it too (Enter or "Use" already did, if unchanged).
  $('api-key').addEventListener('change', (e) => { if (e.target.value.trim() !== apiKey()) useKey(e.target.value); });
  $('api-key-clear').addEventListener('click', () => useKey(''));
  for (const f of ['glb', 'gltf', 'obj', 'stl', 'ply', 'off']) $(`dl-${f}`).addEventListener('click', downloadResult);
  const drop = $('drop');
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => { e.preventDefault(); drop.classList.remove('over'); takeFiles(e.dataTransfer.files); });
  $('files').addEventListener('change', (e) => { takeFiles(e.target.files); e.target.value = ''; });
  form.addEventListener('submit', submitJob);
  form.addEventListener('change', updateFormVisibility);
  form.addEventListener('input', (e) => {
    e.target.classList?.remove('invalid');
    e.target.closest('label')?.querySelector('.field-error')?.remove();
  });
  $('colour').addEventListener('change', (e) => {
    view.setColour(e.target.value);
    // The distance colours are the point there: the region keeps its outline, not its tint.
    regionControls.overlays.setTinted(e.target.value !== 'distance');
  });
  $('wireframe').addEventListener('change', (e) => view.setWireframe(e.target.checked));
  $('show-input').addEventListener('change', (e) => view.setShowInput(e.target.checked));
  $('cancel').addEventListener('click', cancelJob);
  $('scrub').addEventListener('input', (e) => scrubTo(+e.target.value));
  $('jobs-state').addEventListener('change', () => { dash.tokens = [null]; dash.page = 0; refreshJobs(); });
  $('jobs-next').addEventListener('click', () => { dash.page++; refreshJobs(); });
  $('jobs-prev').addEventListener('click', () => { dash.page = Math.max(0, dash.page - 1); refreshJobs(); });
  $('jobs-table').addEventListener('click', async (e) => {
    const id = e.target.dataset?.cancel;
    if (!id) return;
    try {
      const job = await json(`/v1/jobs/${id}/cancel`, { method: 'POST' });
      updateJob(job);
    } catch (err) {
      $('jobs-error').textContent = err.message;
    }
    refreshJobs();
  });
  window.addEventListener('hashchange', onHash);
}

wire();
refreshJobs();
// A job in the URL is watched once the form exists: it shows that job's parameters.
loadConfig()
  .catch((e) => { $('form-error').textContent = `cannot load the parameters: ${e.message}`; })
  .then(onHash);
