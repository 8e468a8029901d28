// Metric plots (uPlot), one point per step, growing live. Points are appended to plain arrays
// and the charts redrawn at most once per animation frame, however fast frames arrive.
import uPlot from 'uplot';

const SERIES = [
  // Both forms of W once frames carry the second (issue 26 item 4): the flow's own, signed
  // (H projected on the normal), and the whole mean-curvature vector's (|Δf|²/4A, libigl's).
  { el: 'plot-w', title: 'Willmore energy W', log: false,
    series: [
      { label: 'W', key: 'willmore_energy', stroke: '#2f6fd6' },
      { label: 'W vector |Δf|²/4A', key: 'willmore_energy_vector', stroke: '#ef6c00', optional: true },
    ] },
  { el: 'plot-q', title: 'quasi-conformal error Q', log: true,
    series: [
      { label: 'mean', key: 'q_mean', stroke: '#2e7d32' },
      { label: 'p95', key: 'q_p95', stroke: '#ef6c00' },
      { label: 'max', key: 'q_max', stroke: '#c62828' },
    ] },
  { el: 'plot-closure', title: 'closure residual', log: true,
    series: [{ label: 'closure', key: 'closure_residual', stroke: '#6a1b9a' }] },
  { el: 'plot-tau', title: 'τ used per step', log: false,
    series: [{ label: 'τ', key: 'tau', stroke: '#00838f', points: { show: true, size: 5 } }] },
  // Shown once a frame carries them (`measure_deviation`, `max_deviation`; `volume`).
  { el: 'plot-deviation', title: 'distance from the input', log: false, optional: true,
    series: [
      { label: 'max', key: 'deviation_max', stroke: '#c62828' },
      { label: 'mean', key: 'deviation_mean', stroke: '#2f6fd6' },
    ] },
  { el: 'plot-volume', title: 'enclosed volume', log: false, optional: true,
    series: [{ label: 'volume', key: 'volume', stroke: '#5d4037' }] },
  // Scale distortion against the input (issue 26 item 4): 0 for a similarity; Q, which sees
  // angles only, misses a triangle shrinking uniformly.
  { el: 'plot-scale', title: 'scale distortion ln(area share / input share)', log: false, optional: true,
    series: [
      { label: 'p1', key: 'log_area_ratio_p1', stroke: '#1565c0' },
      { label: 'p99', key: 'log_area_ratio_p99', stroke: '#c62828' },
    ] },
  { el: 'plot-collapsed', title: 'collapsed triangles', log: false, optional: true,
    series: [{ label: 'collapsed', key: 'collapsed_triangles', stroke: '#b71c1c', points: { show: true, size: 5 } }] },
  { el: 'plot-creases', title: 'crease edges kept', log: false, optional: true,
    series: [{ label: 'crease edges', key: 'crease_edges', stroke: '#6a1b9a', points: { show: true, size: 5 } }] },
];

/** Tick labels of a log axis: plain numbers from 0.01 up, powers of ten below (uPlot's default
 *  rounds 1e-4 to "0"). */
function logTicks(u, splits) {
  return splits.map((v) => {
    if (v == null) return '';
    return v >= 0.01 && v < 1e5 ? String(+v.toPrecision(3)) : v.toExponential(0);
  });
}

/** Show or hide the legend row of series `i` of chart `c` (an optional series has none until
 * its data arrives). uPlot's own CSS sets the rows' display, so `hidden` would not do. */
function showLegendRow(c, i, on) {
  // Found by label: without a live legend uPlot draws no row for the x series.
  const label = c.spec.series[i].label;
  const row = [...c.chart.root.querySelectorAll('.u-legend .u-series')].find((r) => r.textContent.trim() === label);
  if (row) row.style.display = on ? '' : 'none';
}

export class Plots {
  constructor() {
    this.charts = SERIES.map((spec) => {
      const el = document.getElementById(spec.el);
      const data = [[], ...spec.series.map(() => [])];
      const opts = {
        title: spec.title,
        width: Math.max(200, el.clientWidth),
        height: 170,
        scales: { x: { time: false }, y: spec.log ? { distr: 3 } : {} },
        axes: [{ label: 'step', size: 36 }, spec.log ? { size: 56, values: logTicks } : { size: 56 }],
        legend: { live: false },
        cursor: { drag: { x: false, y: false } },
        // An optional series stays hidden until a frame carries it.
        series: [{ label: 'step' }, ...spec.series.map((s) => ({ label: s.label, stroke: s.stroke, width: 1.5, points: s.points, show: !s.optional }))],
      };
      const chart = new uPlot(opts, data, el);
      const c = { spec, el, data, chart, shown: spec.series.map((s) => !s.optional) };
      spec.series.forEach((s, i) => { if (s.optional) showLegendRow(c, i, false); });
      return c;
    });
    this.pending = false;
    this.points = 0;
    new ResizeObserver(() => {
      for (const c of this.charts) c.chart.setSize({ width: Math.max(200, c.el.clientWidth), height: 170 });
    }).observe(document.getElementById('plots'));
  }

  clear() {
    for (const c of this.charts) {
      for (const a of c.data) a.length = 0;
      if (c.spec.optional) c.el.hidden = true;
      c.spec.series.forEach((s, i) => {
        if (s.optional && c.shown[i]) { c.shown[i] = false; c.chart.setSeries(i + 1, { show: false }); showLegendRow(c, i, false); }
      });
    }
    this.points = 0;
    this.redraw();
  }

  /** Add one step's metrics (steps arriving again after a reconnect are ignored). */
  add(m) {
    const steps = this.charts[0].data[0];
    if (steps.length && m.step <= steps[steps.length - 1]) return;
    for (const c of this.charts) {
      c.data[0].push(m.step);
      c.spec.series.forEach((s, i) => {
        let v = m[s.key];
        // Log scales cannot show 0 (step 0's residual, a flow without closure); τ is 0 at step 0.
        if (!(Number.isFinite(v)) || ((c.spec.log || s.key === 'tau') && v <= 0)) v = null;
        if (v !== null && c.el.hidden) { c.el.hidden = false; c.chart.setSize({ width: Math.max(200, c.el.clientWidth), height: 170 }); }
        if (v !== null && !c.shown[i]) { c.shown[i] = true; c.chart.setSeries(i + 1, { show: true }); showLegendRow(c, i, true); }
        c.data[i + 1].push(v);
      });
    }
    this.points++;
    if (!this.pending) {
      this.pending = true;
      requestAnimationFrame(() => this.redraw());
    }
  }

  redraw() {
    this.pending = false;
    for (const c of this.charts) c.chart.setData(c.data);
  }
}
