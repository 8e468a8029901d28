// The region and shape controls of the form (issue 29 item 6): pick a region on the 3D view
// (press on the model, drag out a radius: a sphere, or a cube of that half-size in box mode),
// its numbers editable in the form; or a named group of the file's faces, picked from a list
// of the uploaded file's own `g`/`o` (glTF node and mesh) names; the detail size shown as a ring on the model; preserve,
// max_deviation, until_willmore, falloff, feature_angle, fill_holes. Each parameter is sent only when the user set it:
// leaving a field empty leaves the server's default (and a server that does not know the
// parameter is never asked about it).
import { Vector3 } from 'three';
import { Overlays } from './overlay.js';

/** Lengths and numbers sent only when typed in. */
const OPTIONAL_NUMBERS = ['falloff', 'feature_size', 'max_deviation', 'until_willmore', 'refine_edge'];

class FieldError extends Error {
  constructor(field, detail) { super(detail); this.problem = { field, detail }; }
}

/** A region as the API's JSON names it. */
function toWire(r) {
  if (r.kind === 'sphere') return { sphere: { center: r.center, radius: r.radius } };
  if (r.kind === 'box') return { box: { min: r.min, max: r.max } };
  if (r.kind === 'group') return { group: r.name };
  return { vertices: r.vertices };
}

/** A region of the API's JSON as the page holds it, or null for a kind it does not know. */
function fromWire(w) {
  if (w?.sphere) return { kind: 'sphere', center: w.sphere.center, radius: w.sphere.radius };
  if (w?.box) return { kind: 'box', min: w.box.min, max: w.box.max };
  if (Array.isArray(w?.vertices)) return { kind: 'vertices', vertices: w.vertices, set: new Set(w.vertices) };
  if (typeof w?.group === 'string') return { kind: 'group', name: w.group };
  return null;
}

function describe(r) {
  const v = (a) => a.map((x) => +x.toPrecision(4)).join(', ');
  if (r.kind === 'sphere') return `sphere at (${v(r.center)}), radius ${+r.radius.toPrecision(4)}`;
  if (r.kind === 'box') return `box (${v(r.min)}) – (${v(r.max)})`;
  if (r.kind === 'group') return `group ${r.name}`;
  return `${r.vertices.length} listed vertices`;
}

export class RegionControls {
  constructor(view, form) {
    this.view = view;
    this.form = form;
    this.overlays = new Overlays(view);
    // Where the region was picked on the surface (world space, as regions are).
    this.anchor = null; // { point: Vector3, normal: Vector3 }
    this.picking = false;
    this.drag = null;
    // Regions kept with "Add another": the job moves their union with the form's own.
    this.kept = [];
    this.list = document.getElementById('region-list');
    const $ = (id) => document.getElementById(id);
    this.info = $('region-info');
    this.pickButton = $('region-pick');
    this.pickButton.addEventListener('click', () => this.setPicking(!this.picking));
    $('region-clear').addEventListener('click', () => this.clear());
    $('region-add').addEventListener('click', () => this.keep());
    this.list.addEventListener('click', (e) => {
      const i = e.target.dataset?.remove;
      if (i === undefined) return;
      this.kept.splice(Number(i), 1);
      this.fromForm();
    });
    form.addEventListener('input', (e) => { if (this.owns(e.target)) this.fromForm(); });
    form.addEventListener('change', (e) => { if (this.owns(e.target)) this.fromForm(); });
    const canvas = view.canvas;
    canvas.addEventListener('pointerdown', (e) => this.down(e));
    canvas.addEventListener('pointermove', (e) => this.move(e));
    canvas.addEventListener('pointerup', (e) => this.up(e));
    canvas.addEventListener('pointercancel', (e) => this.up(e));
    window.addEventListener('keydown', (e) => { if (e.key === 'Escape' && this.picking && !this.drag) { this.setPicking(false); this.fromForm(); } });
    view.onModel(() => { this.anchor = null; this.setPicking(false); this.listGroups(); queueMicrotask(() => this.fromForm()); });
    this.fromForm();
  }

  owns(el) {
    return el.name === 'region' || el.name?.startsWith('region.') || el.name === 'feature_size' || el.name === 'falloff';
  }

  /** The model's group names as the choices of `region.group` (the one chosen kept when the
   * new model has it too); the `group` mode is offered only when the file names groups. */
  listGroups() {
    const e = this.form.elements;
    const chosen = e['region.group'].value;
    const names = [...(this.view.model?.groups?.keys() ?? [])];
    e['region.group'].replaceChildren(...names.map((name) => {
      const o = document.createElement('option');
      o.value = name;
      o.textContent = `${name} (${this.view.model.groups.get(name).size} vertices)`;
      return o;
    }));
    if (names.includes(chosen)) e['region.group'].value = chosen;
    e.region.querySelector('option[value="group"]').disabled = !names.length;
  }

  setPicking(on) {
    this.picking = on && !!this.view.model;
    this.view.controls.enabled = !this.picking;
    this.view.canvas.classList.toggle('picking', this.picking);
    this.pickButton.setAttribute('aria-pressed', String(this.picking));
    this.pickButton.classList.toggle('active', this.picking);
    if (this.picking && !['sphere', 'box'].includes(this.form.elements.region.value)) {
      this.form.elements.region.value = 'sphere';
      this.updateVisibility();
    }
    if (this.picking) this.info.textContent = 'press on the model at the centre and drag out the radius';
  }

  down(e) {
    if (!this.picking || e.button !== 0) return;
    const hit = this.view.pick(e.clientX, e.clientY);
    if (!hit) { this.info.textContent = 'that is not on the model: press on the surface'; return; }
    e.preventDefault();
    this.view.canvas.setPointerCapture(e.pointerId);
    this.anchor = { point: hit.point, normal: hit.normal };
    this.drag = { centre: hit.point.toArray(), radius: 0 };
    this.setShape(this.drag.centre, 0);
  }

  move(e) {
    if (!this.drag) return;
    const p = this.view.onViewPlane(e.clientX, e.clientY, this.anchor.point);
    if (!p) return;
    // The radius is measured in the view's plane through the centre: the circle dragged out on
    // the screen, in the model's (world) units.
    this.drag.radius = p.distanceTo(this.anchor.point);
    this.setShape(this.drag.centre, this.drag.radius);
  }

  up(e) {
    if (!this.drag) return;
    this.move(e);
    // A click without a drag: a small region (2% of the model) to start from.
    if (!(this.drag.radius > 0)) this.setShape(this.drag.centre, 0.02 * this.view.modelSize());
    this.drag = null;
    this.setPicking(false);
    this.fromForm();
  }

  /** A sphere of `radius` at `centre`, or in box mode the cube of half-size `radius`. */
  setShape(centre, radius) {
    const e = this.form.elements;
    const fmt = (v) => String(+v.toPrecision(7));
    if (e.region.value === 'box') {
      e['region.box.min'].value = centre.map((c) => fmt(c - radius)).join(',');
      e['region.box.max'].value = centre.map((c) => fmt(c + radius)).join(',');
    } else {
      e['region.sphere.center'].value = centre.map(fmt).join(',');
      e['region.sphere.radius'].value = fmt(radius);
    }
    this.fromForm();
  }

  /** Keep the form's region in the list and empty the form for another. */
  keep() {
    const region = this.region();
    if (!region) { this.info.textContent = 'pick or type a region first, then add another'; return; }
    this.kept.push(region);
    const e = this.form.elements;
    if (region.kind === 'group') e.region.value = '';
    for (const name of ['region.sphere.center', 'region.sphere.radius', 'region.box.min', 'region.box.max']) e[name].value = '';
    this.fromForm();
  }

  clear() {
    const e = this.form.elements;
    this.setPicking(false);
    this.kept = [];
    e.region.value = '';
    for (const name of ['region.sphere.center', 'region.sphere.radius', 'region.box.min', 'region.box.max']) e[name].value = '';
    this.anchor = null;
    this.fromForm();
  }

  updateVisibility() {
    const mode = this.form.elements.region.value;
    document.getElementById('region-sphere').hidden = mode !== 'sphere';
    document.getElementById('region-box').hidden = mode !== 'box';
    document.getElementById('region-group').hidden = mode !== 'group';
  }

  /** The region the form describes, or null (none, or not yet complete). */
  region() {
    const e = this.form.elements;
    const mode = e.region.value;
    const triple = (name) => {
      const t = e[name].value.split(',').map((s) => s.trim()).filter((s) => s !== '');
      const v = t.map(Number);
      return v.length === 3 && v.every(Number.isFinite) ? v : null;
    };
    if (mode === 'sphere') {
      const center = triple('region.sphere.center');
      const radius = e['region.sphere.radius'].value.trim() === '' ? NaN : Number(e['region.sphere.radius'].value);
      return center && Number.isFinite(radius) ? { kind: 'sphere', center, radius } : null;
    }
    if (mode === 'box') {
      const min = triple('region.box.min'), max = triple('region.box.max');
      return min && max ? { kind: 'box', min, max } : null;
    }
    if (mode === 'group') {
      const name = e['region.group'].value;
      return name ? { kind: 'group', name, set: this.view.model?.groups?.get(name) } : null;
    }
    return null;
  }

  /** The regions the job will get: those kept, then the form's own (if complete). */
  regions() {
    const current = this.region();
    // A group kept from a job's parameters learns its vertices from the model shown now.
    const kept = this.kept.map((r) => (r.kind === 'group' && !r.set ? { ...r, set: this.view.model?.groups?.get(r.name) } : r));
    return current ? [...kept, current] : kept;
  }

  /** Redraw the regions, their list and the ring from what the form says. */
  fromForm() {
    const e = this.form.elements;
    // With regions kept, the form edits one more of them, never "the whole surface".
    if (this.kept.length && e.region.value === '') e.region.value = this.kept[this.kept.length - 1].kind === 'box' ? 'box' : 'sphere';
    if (e.region.value === 'group' && e['region.group'].value === '' && e['region.group'].options.length) e['region.group'].selectedIndex = 0;
    this.updateVisibility();
    const regions = this.regions();
    const falloff = Number(e.falloff.value);
    const count = this.overlays.setRegions(regions, falloff > 0 ? falloff : 0);
    const n = this.view.model?.fileVertexCount || 0;
    if (!this.picking) {
      this.info.textContent = regions.length && n ? `${count} of ${n} vertices move; the rest stay exactly where they are` : '';
    }
    this.info.dataset.inside = regions.length ? String(count) : '';
    this.list.hidden = !this.kept.length;
    this.list.replaceChildren(...this.kept.map((r, i) => {
      const li = document.createElement('li');
      const x = document.createElement('button');
      x.type = 'button';
      x.dataset.remove = String(i);
      x.title = 'remove this region';
      x.textContent = '×';
      li.append(describe(r), x);
      return li;
    }));
    this.updateRing(regions[regions.length - 1] || null);
  }

  /** The detail size as a ring of that diameter on the model, facing the camera (so it reads
   * at its true length there): at the region's centre or, without a region, where the view's
   * centre meets the surface. Its caption gives the model's own size for scale. */
  updateRing(region) {
    const el = this.form.elements.feature_size;
    const caption = document.getElementById('ring-label');
    const length = Number(el.value);
    let point = null;
    if (el.value.trim() !== '' && length > 0 && this.view.model) {
      if (region && region === this.region() && this.anchor) {
        point = this.anchor.point;
      } else if (region && (region.kind === 'sphere' || region.kind === 'box')) {
        const c = region.kind === 'sphere' ? region.center : region.min.map((v, d) => (v + region.max[d]) / 2);
        point = new Vector3().fromArray(c);
      } else {
        const r = this.view.canvas.getBoundingClientRect();
        point = this.view.pick(r.left + r.width / 2, r.top + r.height / 2)?.point ?? null;
      }
    }
    caption.hidden = !point;
    if (!point) { this.overlays.setRing(null); return; }
    caption.textContent = `cyan ring: detail size ${length} (the model is ${this.view.modelSize().toPrecision(3)} across)`;
    this.overlays.setRing({ point, length });
  }

  /** The parameters these controls set, each only when set (added to the job's `params`). */
  params() {
    const e = this.form.elements;
    const out = {};
    const mode = e.region.value;
    if (mode && !this.region()) {
      // An empty form beside kept regions is fine; a half-typed region is not.
      if (mode === 'group') throw new FieldError('region.group', 'the group region needs a group: this file names none (OBJ g or o lines, glTF node or mesh names)');
      const fields = mode === 'sphere' ? ['region.sphere.center', 'region.sphere.radius'] : ['region.box.min', 'region.box.max'];
      if (!this.kept.length || fields.some((f) => e[f].value.trim() !== '')) {
        throw new FieldError(fields[0], `the ${mode} region needs its numbers: pick it on the view or type them (x,y,z)`);
      }
    }
    const regions = this.regions();
    if (regions.length) {
      out.region = regions.length === 1 ? toWire(regions[0]) : regions.map(toWire);
      out.seam = e.seam.value;
    }
    for (const name of OPTIONAL_NUMBERS) {
      const el = e[name];
      if (el.validity.badInput) throw new FieldError(name, `invalid parameter \`${name}\`: not a number`);
      if (el.value.trim() !== '') out[name] = Number(el.value);
    }
    const angle = e.feature_angle.value.trim();
    if (angle !== '') {
      // A number goes as one (the API takes both forms); `auto`/`none` as text.
      out.feature_angle = /^[0-9.]+$/.test(angle) && Number.isFinite(Number(angle)) ? Number(angle) : angle;
    }
    if (e.preserve.value) out.preserve = e.preserve.value;
    if (e.measure_deviation.checked) out.measure_deviation = true;
    if (e.all_steps.checked) out.until_converged = false;
    if (e.refine.checked) out.refine = true;
    const holes = e.fill_holes.value.trim();
    if (holes !== '') out.fill_holes = holes;
    return out;
  }

  /** Show a job's parameters (as the API reports them) in these controls. */
  fill(p) {
    const e = this.form.elements;
    const regions = (Array.isArray(p.region) ? p.region : p.region ? [p.region] : []).map(fromWire).filter(Boolean);
    // The first sphere or box goes in the form, the rest in the list.
    const at = regions.findIndex((r) => r.kind !== 'vertices');
    const first = at >= 0 ? toWire(regions[at]) : null;
    this.kept = regions.filter((_, i) => i !== at);
    this.anchor = null;
    for (const name of ['region.sphere.center', 'region.sphere.radius', 'region.box.min', 'region.box.max']) e[name].value = '';
    if (first?.sphere) {
      e.region.value = 'sphere';
      e['region.sphere.center'].value = first.sphere.center.join(',');
      e['region.sphere.radius'].value = first.sphere.radius;
    } else if (first?.box) {
      e.region.value = 'box';
      e['region.box.min'].value = first.box.min.join(',');
      e['region.box.max'].value = first.box.max.join(',');
    } else if (first?.group !== undefined) {
      // The job's model may not be here yet: offer its group by name until it is.
      const select = e['region.group'];
      if (![...select.options].some((o) => o.value === first.group)) select.add(new Option(first.group, first.group));
      select.value = first.group;
      e.region.querySelector('option[value="group"]').disabled = false;
      e.region.value = 'group';
    } else {
      e.region.value = '';
    }
    if (p.seam) e.seam.value = p.seam;
    for (const name of OPTIONAL_NUMBERS) e[name].value = p[name] ?? '';
    e.feature_angle.value = p.feature_angle === undefined || p.feature_angle === 'auto' ? '' : String(p.feature_angle);
    e.preserve.value = typeof p.preserve === 'string' ? p.preserve : '';
    e.measure_deviation.checked = p.measure_deviation === true;
    e.all_steps.checked = p.until_converged === false;
    e.refine.checked = p.refine === true;
    e.fill_holes.value = p.fill_holes === undefined || p.fill_holes === null ? '' : String(p.fill_holes);
    this.fromForm();
  }
}
