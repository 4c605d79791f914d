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

/** PSD of measured and predicted outputs (log power). */
export function psdPlot(el, { f, measured, predicted, unit }) {
  const series = [{ label: "f [Hz]", value: (u, v) => fmt(v) }];
  const data = [f];
  const floor = (p) => Array.from(p, (v) => (v > 0 ? v : null));
  if (measured) {
    series.push({ label: "measured", stroke: C.meas, width: 1, value: (u, v) => fmt(v) });
    data.push(floor(measured));
  }
  series.push({ label: "predicted mean", stroke: C.mean, width: 1.2, value: (u, v) => fmt(v) });
  data.push(floor(predicted));
  mount(el, {
    height: 300,
    scales: { x: { time: false }, y: { distr: 3 } },
    axes: [{ label: "frequency [Hz]" }, { label: `PSD [${unit || "-"}²/Hz]`, size: 70, values: ticks }],
    series,
    cursor: { drag: { x: true, y: true, uni: 40 } },
  }, data);
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

/** Restoring force against displacement: predicted mean, band edges and the measured loop. ``view``
 * ({x: [lo, hi], y: [lo, hi]}) sets the axes (a double-click goes back to the whole record). */
export function loopsPlot(el, loops, units, view) {
  const series = [{}];
  const data = [null];
  const add = (label, loop, stroke, width) => {
    if (!loop) return;
    series.push({ label, stroke, width, paths: xyPath, points: { show: false },
                  facets: [{ scale: "x", auto: true }, { scale: "y", auto: true }] });
    data.push([loop.x, loop.force]);
  };
  add("band lower", loops.lower, C.edge, 0.6);
  add("band upper", loops.upper, C.edge, 0.6);
  add("measured", loops.measured, C.measLoop, 1);
  add("predicted mean", loops.predicted, C.pred, 1.4);
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
  el.dataset.ready = "1";
}

export { fmt };
