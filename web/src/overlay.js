// What the page draws over the surface (issue 29): the regions that will move, tinted on the
// model (the faces whose three corners they select, the server's rule on the input positions)
// with each sphere or box outlined, and the "detail size" as a ring of that diameter at the
// surface, facing the camera. Tints share the surface's own position buffers, so they follow every frame.
import {
  BoxGeometry, BufferAttribute, BufferGeometry, EdgesGeometry, Group, LineBasicMaterial, LineLoop,
  LineSegments, Mesh, MeshBasicMaterial, SphereGeometry,
} from 'three';

/** Is file vertex `i` of `P` (3 numbers per vertex, world space) inside `region`? As the server
 * decides it: a sphere holds its boundary, a box its faces, a vertex list names file vertices
 * (willow::flow::region). */
export function insideRegion(region, P, i) {
  if (region.kind === 'vertices' || region.kind === 'group') return !!region.set?.has(i);
  const x = P[3 * i], y = P[3 * i + 1], z = P[3 * i + 2];
  if (region.kind === 'sphere') {
    const [cx, cy, cz] = region.center;
    return (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2 <= region.radius ** 2;
  }
  const { min, max } = region;
  return x >= min[0] && x <= max[0] && y >= min[1] && y <= max[1] && z >= min[2] && z <= max[2];
}

export class Overlays {
  constructor(view) {
    this.view = view;
    this.group = new Group();
    view.scene.add(this.group);
    this.tintMaterial = new MeshBasicMaterial({
      color: 0xff2bd6, transparent: true, opacity: 0.45, depthWrite: false,
      polygonOffset: true, polygonOffsetFactor: -2, polygonOffsetUnits: -2,
    });
    this.tints = [];
    this.tinted = true;
    // The regions' shapes (world space): one outline each, from shared geometry; a sphere's
    // falloff (the width beyond it over which the motion blends to zero) as a fainter one.
    this.frame = new Group();
    this.group.add(this.frame);
    this.shapes = {
      sphere: new SphereGeometry(1, 32, 16),
      box: new EdgesGeometry(new BoxGeometry(1, 1, 1)),
      sphereMaterial: new MeshBasicMaterial({ color: 0xff8af0, wireframe: true, transparent: true, opacity: 0.18, depthWrite: false }),
      falloffMaterial: new MeshBasicMaterial({ color: 0xff8af0, wireframe: true, transparent: true, opacity: 0.07, depthWrite: false }),
      boxMaterial: new LineBasicMaterial({ color: 0xff8af0 }),
    };
    this.outlines = [];
    // The detail-size ring: a unit circle and one diameter across it, scaled to the length.
    const ring = [];
    for (let k = 0; k < 64; k++) ring.push(0.5 * Math.cos((2 * Math.PI * k) / 64), 0.5 * Math.sin((2 * Math.PI * k) / 64), 0);
    const ringGeometry = new BufferGeometry();
    ringGeometry.setAttribute('position', new BufferAttribute(new Float32Array(ring), 3));
    const barGeometry = new BufferGeometry();
    barGeometry.setAttribute('position', new BufferAttribute(new Float32Array([-0.5, 0, 0, 0.5, 0, 0]), 3));
    const cyan = new LineBasicMaterial({ color: 0x3ee6ff, depthTest: false, transparent: true });
    this.ring = new Group();
    this.ring.add(new LineLoop(ringGeometry, cyan), new LineSegments(barGeometry, cyan));
    this.ring.renderOrder = 2;
    for (const c of this.ring.children) c.renderOrder = 2;
    this.ring.visible = false;
    this.group.add(this.ring);
    this.regions = [];
    this.inside = null;
    view.onModel(() => { this.setRegions([]); this.setRing(null); });
    // The ring faces the camera as the view turns (drawn over the surface: depthTest off).
    view.controls.addEventListener('change', () => { if (this.ring.visible) this.ring.quaternion.copy(view.camera.quaternion); });
  }

  /**
   * Tint and outline `regions` (each {kind: 'sphere', center, radius} or {kind: 'box', min,
   * max}, in world space as the server reads regions; the job moves their union); a sphere's
   * `falloff` (> 0) is drawn as a fainter sphere that much wider. Returns how many file
   * vertices they select.
   */
  setRegions(regions, falloff = 0) {
    for (const t of this.tints) { this.view.scene.remove(t); t.geometry.dispose(); }
    this.tints = [];
    for (const o of this.outlines) this.frame.remove(o);
    this.outlines = [];
    this.regions = regions;
    const view = this.view;
    if (!regions.length || !view.model) { this.inside = null; view.requestRender(); return 0; }
    if (this.worldFor !== view.model) { this.world = view.toWorld(view.model.filePositions); this.worldFor = view.model; }
    const P = this.world;
    const n = view.model.fileVertexCount;
    const inside = new Uint8Array(n);
    let count = 0;
    for (let i = 0; i < n; i++) if ((inside[i] = regions.some((r) => insideRegion(r, P, i)) ? 1 : 0)) count++;
    this.inside = inside;
    for (const p of view.parts) {
      const g = p.part.gather, idx = p.part.index;
      const faces = [];
      for (let k = 0; k < idx.length; k += 3) {
        if (inside[g[idx[k]]] && inside[g[idx[k + 1]]] && inside[g[idx[k + 2]]]) faces.push(idx[k], idx[k + 1], idx[k + 2]);
      }
      if (!faces.length) continue;
      const geometry = new BufferGeometry();
      geometry.setAttribute('position', p.pos);
      geometry.setAttribute('normal', p.nor);
      geometry.setIndex(new BufferAttribute(Uint32Array.from(faces), 1));
      const tint = new Mesh(geometry, this.tintMaterial);
      tint.frustumCulled = false;
      tint.renderOrder = 1;
      tint.visible = this.tinted;
      if (p.part.matrix) { tint.matrixAutoUpdate = false; tint.matrix.fromArray(p.part.matrix); }
      view.scene.add(tint);
      this.tints.push(tint);
    }
    const sh = this.shapes;
    for (const region of regions) {
      if (region.kind === 'sphere') {
        const sphere = new Mesh(sh.sphere, sh.sphereMaterial);
        sphere.position.fromArray(region.center);
        sphere.scale.setScalar(Math.max(region.radius, 1e-9));
        this.outlines.push(sphere);
        if (falloff > 0) {
          const outer = new Mesh(sh.sphere, sh.falloffMaterial);
          outer.position.fromArray(region.center);
          outer.scale.setScalar(region.radius + falloff);
          outer.userData.falloff = true;
          this.outlines.push(outer);
        }
      } else if (region.kind === 'box') {
        // Vertex lists and groups have no outline: their tint shows them.
        const { min, max } = region;
        const box = new LineSegments(sh.box, sh.boxMaterial);
        box.position.set((min[0] + max[0]) / 2, (min[1] + max[1]) / 2, (min[2] + max[2]) / 2);
        box.scale.set(Math.max(max[0] - min[0], 1e-9), Math.max(max[1] - min[1], 1e-9), Math.max(max[2] - min[2], 1e-9));
        this.outlines.push(box);
      }
    }
    for (const o of this.outlines) this.frame.add(o);
    view.requestRender();
    return count;
  }

  /** Tint the region's faces (`false`: only its outline, so the surface's colours show). */
  setTinted(on) {
    this.tinted = on;
    for (const t of this.tints) t.visible = on;
    this.view.requestRender();
  }

  /** The detail-size ring: diameter `length` (world units), centred at `point` (world),
   * facing the camera; null hides it. */
  setRing(at) {
    this.ring.visible = !!at;
    if (at) {
      this.ring.position.copy(at.point);
      this.ring.scale.setScalar(at.length);
      this.ring.quaternion.copy(this.view.camera.quaternion);
    }
    this.view.requestRender();
  }
}
