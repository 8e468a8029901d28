// The 3D view: one BufferGeometry per model part, built once. A frame moves file vertices; it
// is gathered into the SAME position attribute (`needsUpdate`), normals (and the curvature
// colours when shown) are recomputed in place. Index and UVs are never touched again.
import {
  BufferAttribute, BufferGeometry, Color, DirectionalLight, HemisphereLight, Matrix4, Mesh,
  MeshLambertMaterial, PerspectiveCamera, Plane, Raycaster, Scene, SRGBColorSpace, Texture, Vector2,
  Vector3, WebGLRenderer,
} from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { SurfaceDistance } from './distance.js';

export class View {
  constructor(canvas, stats) {
    this.stats = stats;
    this.canvas = canvas;
    // No MSAA: where WebGL is software (SwiftShader: headless, no GPU) it triples the cost of
    // a 100k-triangle frame (122 ms against 41 ms measured); a device pixel ratio up to 2
    // smooths edges on the screens that have one.
    this.renderer = new WebGLRenderer({ canvas, antialias: false });
    this.pixel = new Uint8Array(4);
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.scene = new Scene();
    this.scene.background = new Color(0x20242c);
    this.camera = new PerspectiveCamera(40, 1, 0.01, 100);
    this.scene.add(new HemisphereLight(0xffffff, 0x444455, 1.2));
    const head = new DirectionalLight(0xffffff, 1.4);
    head.position.set(0.3, 0.5, 1);
    this.camera.add(head);
    this.scene.add(this.camera);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener('change', () => this.requestRender());
    this.materials = {
      plain: new MeshLambertMaterial({ color: 0xd8c9a8 }),
      curvature: new MeshLambertMaterial({ vertexColors: true }),
    };
    this.textures = [];
    this.meshes = [];
    this.model = null;
    this.colour = 'texture';
    this.wireframe = false;
    // Before/after: `current` is the last frame given; while `showingInput` the input is drawn
    // instead (frames still arrive and are kept in `current`).
    this.current = null;
    this.showingInput = false;
    this.raycaster = new Raycaster();
    this.modelListeners = [];
    this.dirty = false;
    new ResizeObserver(() => this.resize()).observe(canvas.parentElement);
    this.resize();
  }

  resize() {
    const el = this.canvas.parentElement;
    const w = el.clientWidth, h = el.clientHeight;
    if (w === 0 || h === 0) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  requestRender() {
    if (this.dirty) return;
    this.dirty = true;
    requestAnimationFrame(() => this.render());
  }

  render() {
    this.dirty = false;
    const t0 = performance.now();
    this.renderer.render(this.scene, this.camera);
    if (this.stats.syncGpu) {
      // Timing only: reading one pixel waits until the frame is drawn (gl.finish() does not,
      // through chromium's command buffer).
      const gl = this.renderer.getContext();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.pixel);
    }
    const ms = performance.now() - t0;
    this.stats.lastRenderMs = ms;
    this.stats.renderCount++;
    this.stats.renderMsTotal += ms;
    this.stats.maxRenderMs = Math.max(this.stats.maxRenderMs, ms);
    this.stats.renderMs.push(ms);
    if (this.stats.renderMs.length > 1000) this.stats.renderMs.shift();
  }

  /** Show `model` (from meshio.js) with its input positions; `textureImages` are ImageBitmaps. */
  setModel(model, textureImages) {
    for (const m of this.meshes) { this.scene.remove(m); m.geometry.dispose(); }
    for (const t of this.textures) t.dispose();
    this.meshes = [];
    this.textures = (textureImages || []).map((img) => {
      if (!img) return null;
      const t = new Texture(img);
      t.flipY = false; // ImageBitmaps come flipped already where the format needs it
      t.colorSpace = SRGBColorSpace;
      t.needsUpdate = true;
      return t;
    });
    this.model = model;
    // Weld file vertices by exact position (as the server does): normals and curvature are
    // those of the surface, without seams where UVs split a vertex.
    const n = model.fileVertexCount;
    const weldOf = new Uint32Array(n);
    const seen = new Map();
    const p = model.filePositions;
    let nw = 0;
    for (let i = 0; i < n; i++) {
      const key = p[3 * i] + ',' + p[3 * i + 1] + ',' + p[3 * i + 2];
      let w = seen.get(key);
      if (w === undefined) { w = nw++; seen.set(key, w); }
      weldOf[i] = w;
    }
    const rep = new Uint32Array(nw); // a file vertex of each welded vertex
    for (let i = n - 1; i >= 0; i--) rep[weldOf[i]] = i;
    let faceCount = 0;
    for (const part of model.parts) faceCount += part.index.length / 3;
    const faces = new Uint32Array(faceCount * 3);
    let f = 0;
    this.parts = model.parts.map((part) => {
      const nr = part.gather.length;
      const g = new BufferGeometry();
      const pos = new BufferAttribute(new Float32Array(nr * 3), 3);
      const nor = new BufferAttribute(new Float32Array(nr * 3), 3);
      const col = new BufferAttribute(new Float32Array(nr * 3), 3);
      g.setAttribute('position', pos);
      g.setAttribute('normal', nor);
      g.setAttribute('color', col);
      if (part.uv) g.setAttribute('uv', new BufferAttribute(part.uv, 2));
      g.setIndex(new BufferAttribute(part.index, 1));
      const welded = new Uint32Array(nr);
      for (let r = 0; r < nr; r++) welded[r] = weldOf[part.gather[r]];
      for (let k = 0; k < part.index.length; k++) faces[f++] = welded[part.index[k]];
      const tex = part.uv && part.image !== null ? this.textures[part.image] : part.uv ? this.textures[0] : null;
      const textured = tex ? new MeshLambertMaterial({ map: tex }) : null;
      const mesh = new Mesh(g, this.materials.plain);
      // Positions move every frame: a bounding sphere from step 0 could cull the surface.
      mesh.frustumCulled = false;
      if (part.matrix) { mesh.matrixAutoUpdate = false; mesh.matrix.fromArray(part.matrix); }
      this.scene.add(mesh);
      this.meshes.push(mesh);
      return { part, geometry: g, pos, nor, col, welded, textured, mesh };
    });
    this.weld = { count: nw, rep, faces };
    // Each file vertex's local→world matrix (glTF nodes; null for OBJ): regions and distances
    // are in world space, as the server reads them (willow::mesh::io, "spheres and boxes in its
    // world space").
    this.matrixOf = new Array(n).fill(null);
    for (const part of model.parts) if (part.matrix) for (const i of part.gather) this.matrixOf[i] = part.matrix;
    this.scratch = {
      wpos: new Float32Array(nw * 3), normal: new Float32Array(nw * 3),
      lap: new Float32Array(nw * 3), area: new Float32Array(nw), h: new Float32Array(nw),
    };
    this.curvatureRange = null;
    // The input surface for the distance colours, built when first shown.
    this.inputSurface = null;
    this.distanceScale = 0;
    this.distance = new Float32Array(nw);
    this.distanceIdleAt = 0;
    this.stats.vertexCount = n;
    this.stats.triangleCount = faceCount;
    this.showingInput = false;
    this.applyPositions(model.filePositions);
    this.fitCamera();
    this.setColour(this.colour);
    for (const fn of this.modelListeners) fn(model);
  }

  /** `fn(model)` after every new model. */
  onModel(fn) { this.modelListeners.push(fn); }

  hasTexture() { return this.parts?.some((p) => p.textured); }

  setColour(mode) {
    this.colour = mode;
    const vertexColours = mode === 'curvature' || mode === 'distance';
    for (const p of this.parts || []) {
      p.mesh.material = vertexColours ? this.materials.curvature
        : mode === 'texture' && p.textured ? p.textured : this.materials.plain;
      p.mesh.material.wireframe = this.wireframe;
    }
    const legend = document.getElementById('legend');
    if (legend) {
      legend.hidden = !vertexColours;
      legend.className = mode;
      legend.innerHTML = '';
    }
    if (mode === 'curvature' && this.lastPositions) { this.curvatureLegend(); this.updateColours(); }
    if (mode === 'distance' && this.lastPositions) this.updateDistance();
    this.requestRender();
  }

  /** Show the input (`true`) or the last frame given (`false`). */
  setShowInput(on) {
    if (!this.model) return;
    this.showingInput = on;
    this.draw(on ? this.model.filePositions : this.current);
  }

  setWireframe(on) {
    this.wireframe = on;
    for (const m of [this.materials.plain, this.materials.curvature, ...(this.parts || []).map((p) => p.textured)]) {
      if (m) m.wireframe = on;
    }
    this.requestRender();
  }

  fitCamera() {
    const min = new Vector3(Infinity, Infinity, Infinity), max = new Vector3(-Infinity, -Infinity, -Infinity);
    const v = new Vector3();
    for (const p of this.parts) {
      const a = p.pos.array;
      const m = p.part.matrix ? new Matrix4().fromArray(p.part.matrix) : null;
      for (let i = 0; i < a.length; i += 3) {
        v.set(a[i], a[i + 1], a[i + 2]);
        if (m) v.applyMatrix4(m);
        min.min(v); max.max(v);
      }
    }
    const centre = min.clone().add(max).multiplyScalar(0.5);
    const radius = Math.max(max.distanceTo(min) / 2, 1e-6);
    const dist = radius / Math.sin((this.camera.fov * Math.PI) / 360) * 1.05;
    this.camera.near = dist / 100;
    this.camera.far = dist * 100;
    this.camera.position.copy(centre).add(new Vector3(0.35, 0.25, 1).normalize().multiplyScalar(dist));
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
  }

  /** A new frame: `filePositions` (3 floats per file vertex), drawn unless the input is shown. */
  applyPositions(filePositions) {
    this.current = filePositions;
    if (this.showingInput) return 0;
    return this.draw(filePositions);
  }

  /** Move the surface to `filePositions`. */
  draw(filePositions) {
    const t0 = performance.now();
    this.lastPositions = filePositions;
    for (const p of this.parts) {
      const g = p.part.gather, a = p.pos.array;
      for (let r = 0, o = 0; r < g.length; r++, o += 3) {
        const s = 3 * g[r];
        a[o] = filePositions[s]; a[o + 1] = filePositions[s + 1]; a[o + 2] = filePositions[s + 2];
      }
      p.pos.needsUpdate = true;
    }
    this.updateNormals();
    if (this.colour === 'curvature') this.updateColours();
    if (this.colour === 'distance') this.updateDistance();
    const ms = performance.now() - t0;
    this.stats.lastApplyMs = ms;
    this.requestRender();
    return ms;
  }

  /** Area-weighted vertex normals of the welded surface, scattered to every render vertex. */
  updateNormals() {
    const { count, rep, faces } = this.weld;
    const { wpos, normal } = this.scratch;
    const fp = this.lastPositions;
    for (let w = 0; w < count; w++) {
      const s = 3 * rep[w];
      wpos[3 * w] = fp[s]; wpos[3 * w + 1] = fp[s + 1]; wpos[3 * w + 2] = fp[s + 2];
    }
    normal.fill(0);
    for (let f = 0; f < faces.length; f += 3) {
      const a = 3 * faces[f], b = 3 * faces[f + 1], c = 3 * faces[f + 2];
      const ux = wpos[b] - wpos[a], uy = wpos[b + 1] - wpos[a + 1], uz = wpos[b + 2] - wpos[a + 2];
      const vx = wpos[c] - wpos[a], vy = wpos[c + 1] - wpos[a + 1], vz = wpos[c + 2] - wpos[a + 2];
      const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      normal[a] += nx; normal[a + 1] += ny; normal[a + 2] += nz;
      normal[b] += nx; normal[b + 1] += ny; normal[b + 2] += nz;
      normal[c] += nx; normal[c + 1] += ny; normal[c + 2] += nz;
    }
    for (let w = 0; w < 3 * count; w += 3) {
      const l = Math.hypot(normal[w], normal[w + 1], normal[w + 2]) || 1;
      normal[w] /= l; normal[w + 1] /= l; normal[w + 2] /= l;
    }
    for (const p of this.parts) {
      const a = p.nor.array, wd = p.welded;
      for (let r = 0, o = 0; r < wd.length; r++, o += 3) {
        const s = 3 * wd[r];
        a[o] = normal[s]; a[o + 1] = normal[s + 1]; a[o + 2] = normal[s + 2];
      }
      p.nor.needsUpdate = true;
    }
  }

  curvatureLegend() {
    const legend = document.getElementById('legend');
    if (!legend || !this.curvatureRange) return;
    const [lo, hi] = this.curvatureRange;
    legend.innerHTML = `H ${lo.toPrecision(3)}<i></i>${hi.toPrecision(3)}`;
  }

  /**
   * Distance of each vertex of the shown surface to the input *surface* (nearest point on its
   * triangles, distance.js), in world units. Coloured from 0 to the 98th percentile (the
   * largest seen so far: the scale only grows, so a colour means the same distance in every
   * frame); beyond it, the top colour.
   */
  updateDistance() {
    // At most a fifth of the time goes here while frames stream (a 100k-triangle surface takes
    // a few hundred ms); the latest surface is coloured once the pause is over.
    const t0 = performance.now();
    if (t0 < this.distanceIdleAt) {
      this.distanceTimer ??= setTimeout(() => {
        this.distanceTimer = null;
        if (this.colour === 'distance' && this.lastPositions) { this.updateDistance(); this.requestRender(); }
      }, this.distanceIdleAt - t0);
      return;
    }
    const { count, rep, faces } = this.weld;
    if (!this.inputSurface) {
      const fp = this.toWorld(this.model.filePositions);
      const input = new Float64Array(3 * count);
      for (let w = 0; w < count; w++) {
        const s = 3 * rep[w];
        input[3 * w] = fp[s]; input[3 * w + 1] = fp[s + 1]; input[3 * w + 2] = fp[s + 2];
      }
      this.inputSurface = new SurfaceDistance(input, faces);
      this.inputWelded = input;
    }
    const { wpos } = this.scratch;
    const d = this.distance, input = this.inputWelded;
    let max = 0, sum = 0;
    for (let w = 0; w < count; w++) {
      let x = wpos[3 * w], y = wpos[3 * w + 1], z = wpos[3 * w + 2];
      const m = this.matrixOf[rep[w]];
      if (m) {
        [x, y, z] = [m[0] * x + m[4] * y + m[8] * z + m[12], m[1] * x + m[5] * y + m[9] * z + m[13], m[2] * x + m[6] * y + m[10] * z + m[14]];
      }
      // The vertex's own input position is a point of the input surface: a bound to beat (0
      // for a vertex that did not move, outside a region).
      const own = (x - input[3 * w]) ** 2 + (y - input[3 * w + 1]) ** 2 + (z - input[3 * w + 2]) ** 2;
      const v = this.inputSurface.distance(x, y, z, own);
      d[w] = v;
      sum += v;
      if (v > max) max = v;
    }
    // The top of the scale: the 98th percentile (a few outlying vertices would otherwise
    // leave everything else dark), and it only grows, so colours mean the same in every frame.
    const sample = [];
    const stride = Math.max(1, Math.floor(count / 4000));
    for (let w = 0; w < count; w += stride) sample.push(d[w]);
    sample.sort((a, b) => a - b);
    this.distanceScale = Math.max(this.distanceScale, sample[Math.floor(0.98 * (sample.length - 1))] || 0);
    const inv = this.distanceScale > 0 ? 1 / this.distanceScale : 0;
    for (const p of this.parts) {
      const a = p.col.array, wd = p.welded;
      for (let r = 0, o = 0; r < wd.length; r++, o += 3) rampSequential(Math.min(1, d[wd[r]] * inv), a, o);
      p.col.needsUpdate = true;
    }
    this.stats.distanceMax = max;
    this.stats.distanceMean = count ? sum / count : 0;
    const legend = document.getElementById('legend');
    if (legend) {
      legend.innerHTML = `distance from the input 0<i></i>≥ ${this.distanceScale.toPrecision(3)}` +
        `<br><span>this surface: max ${max.toPrecision(3)}, mean ${(sum / Math.max(count, 1)).toPrecision(3)}</span>`;
    }
    this.distanceIdleAt = performance.now() + 4 * (performance.now() - t0);
  }

  /** Point the raycaster through the client position (x, y) of the canvas. */
  rayAt(x, y) {
    const r = this.canvas.getBoundingClientRect();
    const ndc = new Vector2(((x - r.left) / r.width) * 2 - 1, -((y - r.top) / r.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    return this.raycaster.ray;
  }

  /** The surface under the client position (x, y), as shown: `{ point, normal }` in world
   * space; null where the ray misses. */
  pick(x, y) {
    if (!this.parts) return null;
    this.rayAt(x, y);
    this.scene.updateMatrixWorld();
    // The surface moves: bounds from an earlier frame would make the ray miss it.
    for (const p of this.parts) { p.geometry.boundingSphere = null; p.geometry.boundingBox = null; }
    const hit = this.raycaster.intersectObjects(this.meshes, false)[0];
    if (!hit) return null;
    const normal = hit.face ? hit.face.normal.clone().transformDirection(hit.object.matrixWorld) : new Vector3(0, 0, 1);
    return { point: hit.point.clone(), normal };
  }

  /** Where the ray through (x, y) meets the plane through `point` (world) facing the camera. */
  onViewPlane(x, y, point) {
    const ray = this.rayAt(x, y);
    const n = this.camera.getWorldDirection(new Vector3());
    return ray.intersectPlane(new Plane().setFromNormalAndCoplanarPoint(n, point), new Vector3());
  }

  /** `filePositions` (3 per file vertex) in world space, as a new Float64Array. */
  toWorld(filePositions) {
    const out = Float64Array.from(filePositions);
    for (let i = 0; i < this.matrixOf.length; i++) if (this.matrixOf[i]) worldInPlace(out, 3 * i, this.matrixOf[i]);
    return out;
  }

  /** The model's size: the diagonal of its bounding box (world space). */
  modelSize() {
    if (!this.model) return 0;
    const p = this.toWorld(this.model.filePositions);
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < p.length; i += 3) {
      for (let d = 0; d < 3; d++) { lo[d] = Math.min(lo[d], p[i + d]); hi[d] = Math.max(hi[d], p[i + d]); }
    }
    return Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  }

  /**
   * Mean curvature per welded vertex, `H_i = −⟨(L f)_i, N_i⟩ / 2A_i` (cotan Laplacian
   * `(L f)_i = ½ Σ_j (cot α + cot β)(f_j − f_i)`, barycentric areas; docs/conventions.md's convention,
   * 1/r on a sphere), coloured on a fixed scale: the 5th–95th percentile of the first surface
   * shown, so colours mean the same curvature in every frame.
   */
  updateColours() {
    const { count, faces } = this.weld;
    const { wpos, normal, lap, area, h } = this.scratch;
    lap.fill(0);
    area.fill(0);
    for (let f = 0; f < faces.length; f += 3) {
      const i = 3 * faces[f], j = 3 * faces[f + 1], k = 3 * faces[f + 2];
      const eix = wpos[k] - wpos[j], eiy = wpos[k + 1] - wpos[j + 1], eiz = wpos[k + 2] - wpos[j + 2]; // opposite i
      const ejx = wpos[i] - wpos[k], ejy = wpos[i + 1] - wpos[k + 1], ejz = wpos[i + 2] - wpos[k + 2]; // opposite j
      const ekx = wpos[j] - wpos[i], eky = wpos[j + 1] - wpos[i + 1], ekz = wpos[j + 2] - wpos[i + 2]; // opposite k
      const cx = eky * ejz - ekz * ejy, cy = ekz * ejx - ekx * ejz, cz = ekx * ejy - eky * ejx;
      const dbl = Math.hypot(cx, cy, cz); // twice the area
      if (!(dbl > 1e-30)) continue;
      // cot at corner i = −(e_k · e_j) / |e_k × e_j|, and likewise.
      const coti = -(ekx * ejx + eky * ejy + ekz * ejz) / dbl;
      const cotj = -(eix * ekx + eiy * eky + eiz * ekz) / dbl;
      const cotk = -(ejx * eix + ejy * eiy + ejz * eiz) / dbl;
      // Edge (j,k) weighted by cot i, etc.: L f gains ½ cot (f_other − f_self) at both ends.
      lap[j] += 0.5 * coti * eix; lap[j + 1] += 0.5 * coti * eiy; lap[j + 2] += 0.5 * coti * eiz;
      lap[k] -= 0.5 * coti * eix; lap[k + 1] -= 0.5 * coti * eiy; lap[k + 2] -= 0.5 * coti * eiz;
      lap[k] += 0.5 * cotj * ejx; lap[k + 1] += 0.5 * cotj * ejy; lap[k + 2] += 0.5 * cotj * ejz;
      lap[i] -= 0.5 * cotj * ejx; lap[i + 1] -= 0.5 * cotj * ejy; lap[i + 2] -= 0.5 * cotj * ejz;
      lap[i] += 0.5 * cotk * ekx; lap[i + 1] += 0.5 * cotk * eky; lap[i + 2] += 0.5 * cotk * ekz;
      lap[j] -= 0.5 * cotk * ekx; lap[j + 1] -= 0.5 * cotk * eky; lap[j + 2] -= 0.5 * cotk * ekz;
      const third = dbl / 6;
      area[i / 3] += third; area[j / 3] += third; area[k / 3] += third;
    }
    for (let w = 0; w < count; w++) {
      const s = 3 * w;
      h[w] = area[w] > 0 ? -(lap[s] * normal[s] + lap[s + 1] * normal[s + 1] + lap[s + 2] * normal[s + 2]) / (2 * area[w]) : 0;
    }
    if (!this.curvatureRange) {
      const sample = [];
      const stride = Math.max(1, Math.floor(count / 4000));
      for (let w = 0; w < count; w += stride) if (Number.isFinite(h[w])) sample.push(h[w]);
      sample.sort((a, b) => a - b);
      const lo = sample[Math.floor(0.05 * (sample.length - 1))] ?? -1;
      let hi = sample[Math.floor(0.95 * (sample.length - 1))] ?? 1;
      if (!(hi > lo)) hi = lo + 1;
      this.curvatureRange = [lo, hi];
      this.curvatureLegend();
    }
    const [lo, hi] = this.curvatureRange;
    const inv = 1 / (hi - lo);
    for (const p of this.parts) {
      const a = p.col.array, wd = p.welded;
      for (let r = 0, o = 0; r < wd.length; r++, o += 3) {
        let t = (h[wd[r]] - lo) * inv;
        t = t < 0 ? 0 : t > 1 ? 1 : t || 0;
        ramp(t, a, o);
      }
      p.col.needsUpdate = true;
    }
  }
}

// Moreland's cool–warm diverging map, 5 stops (linear colours, as three expects).
const STOPS = [[59, 76, 192], [141, 176, 254], [242, 242, 242], [244, 154, 123], [180, 4, 38]].map((c) =>
  c.map((v) => Math.pow(v / 255, 2.2)),
);
function ramp(t, out, o) {
  const x = t * 4;
  const i = Math.min(3, Math.floor(x));
  const f = x - i;
  const a = STOPS[i], b = STOPS[i + 1];
  out[o] = a[0] + (b[0] - a[0]) * f;
  out[o + 1] = a[1] + (b[1] - a[1]) * f;
  out[o + 2] = a[2] + (b[2] - a[2]) * f;
}

// A sequential map for distances (viridis, 5 stops): dark is 0, yellow the scale's top.
const SEQ = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]].map((c) =>
  c.map((v) => Math.pow(v / 255, 2.2)),
);
function rampSequential(t, out, o) {
  const x = (t || 0) * 4;
  const i = Math.min(3, Math.floor(x));
  const f = x - i;
  const a = SEQ[i], b = SEQ[i + 1];
  out[o] = a[0] + (b[0] - a[0]) * f;
  out[o + 1] = a[1] + (b[1] - a[1]) * f;
  out[o + 2] = a[2] + (b[2] - a[2]) * f;
}

/** p[o..o+3] ← m·p (m: a column-major 4×4 affine matrix, as glTF stores it). */
function worldInPlace(p, o, m) {
  const x = p[o], y = p[o + 1], z = p[o + 2];
  p[o] = m[0] * x + m[4] * y + m[8] * z + m[12];
  p[o + 1] = m[1] * x + m[5] * y + m[9] * z + m[13];
  p[o + 2] = m[2] * x + m[6] * y + m[10] * z + m[14];
}
