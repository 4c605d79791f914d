// Plots drawn with uPlot (vendored: static/vendor/uplot, loaded as the global uPlot).

const C = { meas: "#555", mean: "#c0392b", band: "rgba(52, 101, 164, 0.22)", edge: "rgba(52, 101, 164, 0.7)",
            pred: "#c0392b", measLoop: "#333" };

function width(el) {
  return Math.max(320, Math.floor(el.getBoundingClientRect().width || el.parentElement.clientWidth || 800));
}

// axis tick labels: 3 significant digits, no trailing zeros (1e-8, 0.00075, 150)
const ticks = (u, vs) => vs.map((v) => (v == null ? "" : String(Number(v.toPrecision(3)))));

const charts = new Map();

function mount(el, opts, data) {
  charts.get(el)?.destroy();
  el.replaceChildren();
  const chart = new uPlot({ width: width(el), ...opts }, data, el);
  charts.set(el, chart);
  return chart;
}

window.addEventListener("resize", () => {
  for (const [el, chart] of charts) chart.setSize({ width: width(el), height: chart.height });
});

function fmt(v) {
  if (v == null || !Number.isFinite(v)) return "-";
  if (Number.isInteger(v) && Math.abs(v) < 1e7) return String(v);
  const a = Math.abs(v);
  return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(3) : v.toPrecision(4);
}

/** Measured output (when given), predicted mean and its band over time; drag to zoom (x and y). */
export function timePlot(el, { t, y, mean, lower, upper, unit, bandLabel }) {
  const series = [{ label: "t [s]", value: (u, v) => fmt(v) }];
  const data = [t];
  if (y) {
    series.push({ label: "measured", stroke: C.meas, width: 1, points: { show: false }, value: (u, v) => fmt(v) });
    data.push(y);
  }
  const iUp = data.length;
  series.push({ label: `${bandLabel} upper`, stroke: C.edge, width: 0.5, value: (u, v) => fmt(v) });
  data.push(upper);
  series.push({ label: `${bandLabel} lower`, stroke: C.edge, width: 0.5, value: (u, v) => fmt(v) });
  data.push(lower);
  series.push({ label: "predicted mean", stroke: C.mean, width: 1.2, value: (u, v) => fmt(v) });
  data.push(mean);
  const chart = mount(el, {
    height: 340,
    scales: { x: { time: false } },
    axes: [{ label: "time [s]" }, { label: `output [${unit || "-"}]`, size: 70, values: ticks }],
    series,
    bands: [{ series: [iUp, iUp + 1], fill: C.band }],
    cursor: { drag: { x: true, y: true, uni: 40 } },
  }, data);
  el.dataset.samples = String(t.length);
  el.dataset.ready = "1";
  return chart;
}

/** Decades of power the PSD plot shows below its peak: a Welch estimate of a clean simulated record reaches
 * round-off, 15 or more decades down, which would squash every feature that matters into the top of the plot. */
export const PSD_DECADES = 7;

/** Axis limits of a log-power plot: from at least PSD_DECADES below the largest finite positive value to just
 * above it, both powers of ten (uPlot's log axis ticks need them); null when there is none. */
export function psdRange(...powers) {
  let peak = 0;
  for (const p of powers) if (p) for (const v of p) if (Number.isFinite(v) && v > peak) peak = v;
  if (!(peak > 0)) return null;
  const pow = (k) => Number(`1e${k}`);  // exactly the decimal power, as the axis's tick table holds it
  const top = Math.ceil(Math.log10(peak));
  return [pow(Math.floor(Math.log10(peak) - PSD_DECADES)), pow(top === Math.log10(peak) ? top + 1 : top)];
}

/** PSD of measured and predicted outputs (log power), the top PSD_DECADES decades below the peak. */
export function psdPlot(el, { f, measured, predicted, unit }) {
  const series = [{ label: "f [Hz]", value: (u, v) => fmt(v) }];
  const data = [f];
  const range = psdRange(measured, predicted);
  // values below the range are drawn at its floor rather than far below the plot
  const floor = (p) => Array.from(p, (v) => (v > 0 ? Math.max(v, range ? range[0] : v) : null));
  if (measured) {
    series.push({ label: "measured", stroke: C.meas, width: 1, value: (u, v) => fmt(v) });
    data.push(floor(measured));
  }
  series.push({ label: "predicted mean", stroke: C.mean, width: 1.2, value: (u, v) => fmt(v) });
  data.push(floor(predicted));
  const y = { distr: 3 };
  if (range) y.range = () => range;
  mount(el, {
    height: 300,
    scales: { x: { time: false }, y },
    axes: [{ label: "frequency [Hz]" }, { label: `PSD [${unit || "-"}²/Hz]`, size: 70, values: ticks }],
    series,
    cursor: { drag: { x: true, y: true, uni: 40 } },
  }, data);
  el.dataset.range = JSON.stringify(range);
  el.dataset.ready = "1";
}

// uPlot's built-in path builders decimate along x; a hysteresis loop goes back and forth in x,
// so its points are joined in order here.
function xyPath(u, seriesIdx) {
  const s = u.series[seriesIdx];
  const [xs, ys] = u.data[seriesIdx];
  const stroke = new Path2D();
  for (let i = 0; i < xs.length; i++) {
    const px = u.valToPos(xs[i], s.facets[0].scale, true);
    const py = u.valToPos(ys[i], s.facets[1].scale, true);
    if (i === 0) stroke.moveTo(px, py);
    else stroke.lineTo(px, py);
  }
  return { stroke, fill: null, clip: null, band: null, gaps: null, flags: 0 };
}

/** Restoring force against displacement: one x-y series per loop ({label, x, force, stroke, width}), joined
 * in time order. ``view`` ({x: [lo, hi], y: [lo, hi]}) sets the axes (a double-click fits every point). */
export function loopsPlot(el, loops, units, view) {
  const series = [{}];
  const data = [null];
  for (const l of loops) {
    series.push({ label: l.label, stroke: l.stroke, width: l.width, paths: xyPath, points: { show: false },
                  facets: [{ scale: "x", auto: true }, { scale: "y", auto: true }] });
    data.push([l.x, l.force]);
  }
  const chart = mount(el, {
    mode: 2,
    height: 300,
    legend: { live: false },
    scales: { x: { time: false } },
    axes: [{ label: `displacement [${units?.x || "m"}]`, values: ticks },
           { label: `restoring force [${units?.force || "N"}]`, size: 70, values: ticks }],
    series,
    cursor: { drag: { x: true, y: true, uni: 40 }, points: { show: false } },
  }, data);
  if (view) {
    chart.batch(() => {
      chart.setScale("x", { min: view.x[0], max: view.x[1] });
      chart.setScale("y", { min: view.y[0], max: view.y[1] });
    });
    el.dataset.view = JSON.stringify(view);
  }
  el.dataset.series = JSON.stringify(loops.map((l) => l.label));
  el.dataset.ready = "1";
}

export const LOOP_COLOURS = { pred: C.pred, edge: C.edge, meas: C.measLoop, raw: "rgba(90, 90, 90, 0.35)" };

const VERDICT_COLOURS = { healthy: "#1b7a3a", novel: "#b3261e", unjudged: "#c9a227" };

/** Novelty scores over time, one marker colour per verdict, and the threshold each was judged against
 * (log score axis: a changed structure scores decades above a healthy one). ``points``: the history's points. */
export function trendPlot(el, points) {
  const t = points.map((p) => Date.parse(p.time) / 1000);
  const pos = (v) => (v != null && v > 0 ? v : null);
  const series = [{ label: "time" },
    { label: "score", stroke: "rgba(80, 80, 80, 0.45)", width: 1, value: (u, v) => fmt(v), spanGaps: true,
      points: { show: false } }];
  const data = [t, points.map((p) => pos(p.score))];
  for (const v of ["healthy", "novel", "unjudged"]) {
    series.push({ label: v, stroke: VERDICT_COLOURS[v], fill: VERDICT_COLOURS[v], width: 0, paths: () => null,
                  points: { show: true, size: 8, stroke: VERDICT_COLOURS[v], fill: VERDICT_COLOURS[v] },
                  value: (u, x) => fmt(x) });
    data.push(points.map((p) => (p.verdict === v ? pos(p.score) : null)));
  }
  // a single verdict has no threshold line to draw: its threshold is drawn as a marker
  series.push({ label: "threshold", stroke: "#222", width: 1, dash: [6, 4], value: (u, v) => fmt(v),
                points: { show: points.length === 1, size: 10, stroke: "#222", fill: "#fff" }, spanGaps: true });
  data.push(points.map((p) => pos(p.threshold)));
  // the time axis spans the verdicts, widened 3 % (a minute each way around a single one)
  const [t0, t1] = [Math.min(...t), Math.max(...t)];
  const span = t1 > t0 ? [t0 - 0.03 * (t1 - t0), t1 + 0.03 * (t1 - t0)] : [t0 - 60, t1 + 60];
  const chart = mount(el, {
    height: 220,
    scales: { x: { time: true, range: () => span }, y: { distr: 3 } },
    axes: [{}, { label: "novelty score", size: 70, values: ticks }],
    series,
    cursor: { drag: { x: true, y: false } },
  }, data);
  chart.setScale("x", { min: span[0], max: span[1] });
  el.dataset.points = String(points.length);
  el.dataset.ready = "1";
}

export { fmt };
