// The engineers' page: models and versions, a record (file or example), and the prediction, PSD,
// restoring-force loops and novelty verdict, all through the service's /v1 API.

import { ApiError, apiKey, enc, getJSON, getText, parseRecord, postJSON, root, setApiKey, staticBlob } from "./api.js";
import { welch } from "./dsp.js";
import { fmt, loopsPlot, psdPlot, timePlot } from "./plots.js";

const $ = (id) => document.getElementById(id);
const state = { models: [], model: null, detail: null, record: null, examples: [], reportUrl: null };

// ------------------------------------------------------------------------------------------ helpers
function showError(err) {
  const box = $("error");
  if (!err) { box.hidden = true; box.textContent = ""; return; }
  box.textContent = err instanceof ApiError && err.status === 401
    ? `${err.message}\nEnter the service's API key at the top right.` : String(err.message || err);
  box.hidden = false;
}

function el(tag, props = {}, ...children) {
  const e = document.createElement(tag);
  const { dataset, ...rest } = props;
  Object.assign(e, rest);
  Object.assign(e.dataset, dataset || {});
  e.append(...children.filter((c) => c != null));
  return e;
}

function show(v) {
  if (v == null) return "-";
  if (typeof v === "number") return fmt(v);
  if (Array.isArray(v)) return v.length > 8 ? `[${v.slice(0, 8).map(show).join(", ")}, ... (${v.length})]` : `[${v.map(show).join(", ")}]`;
  if (typeof v === "object") return Object.entries(v).map(([k, x]) => `${k}: ${show(x)}`).join("; ");
  return String(v);
}

function kvTable(table, obj, keys) {
  const entries = keys ? keys.filter(([k]) => obj && obj[k] !== undefined).map(([k, label]) => [label, obj[k]])
                       : Object.entries(obj || {});
  table.replaceChildren(...(entries.length ? entries.map(([k, v]) =>
    el("tr", {}, el("th", { textContent: k }), el("td", { textContent: show(v), className: typeof v === "number" ? "num" : "" })))
    : [el("tr", {}, el("td", { className: "note", textContent: "none" }))]));
}

function versionBase() {
  return `/v1/models/${enc(state.model)}/versions/${enc($("version").value)}`;
}

// ------------------------------------------------------------------------------------------ models
async function loadModels() {
  const body = $("models").tBodies[0];
  try {
    const { models } = await getJSON("/v1/models");
    state.models = models;
    showError(null);
    body.replaceChildren(...(models.length ? models.map((m) => {
      const tr = el("tr", { dataset: { name: m.name } },
        el("td", { textContent: m.name }), el("td", { textContent: m.versions.join(", ") }),
        el("td", { className: "num", textContent: fmt(m.fs) }),
        el("td", { textContent: `${m.units.u || "-"} / ${m.units.y || "-"}` }),
        el("td", { textContent: `${m.lags.ny}, ${m.lags.nu}` }), el("td", { textContent: m.novelty ? "calibrated" : "-" }));
      tr.addEventListener("click", () => selectModel(m.name));
      return tr;
    }) : [el("tr", {}, el("td", { colSpan: 6, className: "note", textContent: "no model loaded" }))]));
    if (models.length && !state.model) await selectModel(models[0].name);
  } catch (err) {
    body.replaceChildren(el("tr", {}, el("td", { colSpan: 6, className: "note", textContent: "could not list the models" })));
    showError(err);
  }
}

async function selectModel(name) {
  state.model = name;
  for (const tr of $("models").tBodies[0].rows) tr.classList.toggle("selected", tr.dataset.name === name);
  const summary = state.models.find((m) => m.name === name);
  const sel = $("version");
  sel.replaceChildren(...summary.versions.map((v) => el("option", { value: v, textContent: v })));
  sel.value = summary.latest;
  await loadVersion();
  renderExamples();
}

async function loadVersion() {
  closeReport();
  $("report-link").href = `${root}${versionBase()}/report`;
  for (const id of ["meta", "training", "novelty-cal"]) {
    $(id).replaceChildren(el("tr", {}, el("td", { className: "note", textContent: "loading..." })));
  }
  try {
    const d = await getJSON(versionBase());
    state.detail = d;
    showError(null);
    const mcDefault = d.default_mc_paths?.predict;
    $("mc-paths").placeholder = mcDefault ? `${mcDefault}` : "model's";
    $("mc-paths").title = `Monte Carlo paths; empty: the model's default${mcDefault ? ` (${mcDefault} for predict and loops, `
      + `${d.default_mc_paths.novelty} for novelty)` : ""}`;
    $("model-detail").hidden = false;
    kvTable($("meta"), d, [["name", "name"], ["version", "version"], ["created", "created"], ["mode", "mode"],
      ["fs", "fs [Hz]"], ["units", "units"], ["lags", "lags"], ["n_train", "training points"], ["physics", "physics"],
      ["noise_calibration", "noise calibration"]]);
    renderTraining(d);
    kvTable($("novelty-cal"), d.novelty ? { ...d.novelty, ...(d.probe ? { probe: d.probe } : {}) } : null);
    $("meta-more").textContent = JSON.stringify({ kernel: d.kernel, hyperparameters: d.hyperparameters,
                                                  package_versions: d.package_versions }, null, 1);
    checkRecord();
  } catch (err) {
    showError(err);
  }
}

// training metrics: labels and units of the scalars and of each record's metrics (training.pipeline)
const TRAIN_SCALARS = { fit_seconds: ["fit time", "s"], n_train: ["training points", ""], n_rows: ["regressor rows", ""],
                        nlml: ["NLML (ML-II objective)", ""], train_records: ["training records", ""] };

function trainColumns(d) {
  const yu = d.units?.y || "-", e = loopUnits(d.units, d.physics).energy;
  return [["role", "role", ""], ["use", "use", ""], ["fit", "fit", "%"], ["fit_clean", "fit (noise-free)", "%"],
    ["rmse", "RMSE", yu], ["nrmse", "NRMSE", "-"], ["coverage", "coverage", "%"], ["coverage_latent", "coverage (latent)", "%"],
    ["band_width", "band width", yu], ["n_samples", "samples", ""], ["duration_s", "duration", "s"],
    ["drive_freq", "drive", "Hz"], ["loop_area_predicted", "loop area predicted", e],
    ["loop_area_measured", "loop area measured", e], ["novelty_score", "novelty score", "-"], ["verdict", "verdict", ""],
    ["psd_peaks_measured", "PSD peaks measured", "Hz"], ["psd_peaks_predicted", "PSD peaks predicted", "Hz"]];
}

/** Training metrics: the run's scalars as label [unit] / value, and one row per record with units in the header. */
function renderTraining(d) {
  const t = d.training || {};
  const scalars = Object.entries(t).filter(([k, v]) => k !== "records" && (typeof v !== "object" || Array.isArray(v)));
  $("training").replaceChildren(...(scalars.length ? scalars.map(([k, v]) => {
    const [label, unit] = TRAIN_SCALARS[k] || [k.replaceAll("_", " "), ""];
    return el("tr", {}, el("th", { textContent: unit ? `${label} [${unit}]` : label }),
      el("td", { textContent: Array.isArray(v) ? v.join(", ") : show(v), className: typeof v === "number" ? "num" : "" }));
  }) : [el("tr", {}, el("td", { className: "note", textContent: "none" }))]));
  const recs = t.records && typeof t.records === "object" ? Object.entries(t.records) : [];
  const table = $("training-records");
  $("training-records-box").hidden = !recs.length;
  if (!recs.length) { table.replaceChildren(); return; }
  const known = trainColumns(d);
  const cols = known.filter(([k]) => recs.some(([, m]) => m && m[k] != null));
  const cell = (v) => (Array.isArray(v) ? v.map(fmt).join(", ") : typeof v === "number" ? fmt(v) : String(v ?? "-"));
  table.replaceChildren(
    el("thead", {}, el("tr", {}, el("th", { textContent: "record" }),
      ...cols.map(([, label, unit]) => el("th", { textContent: unit ? `${label} [${unit}]` : label })))),
    el("tbody", {}, ...recs.map(([name, m]) => el("tr", { dataset: { record: name } }, el("th", { textContent: name }),
      ...cols.map(([k]) => el("td", { className: typeof m[k] === "number" ? "num" : "", textContent: cell(m[k]) }))))));
}

function closeReport() {
  $("report-frame").hidden = true;
  $("report-frame").removeAttribute("src");
  $("download-report").hidden = true;
  $("report-state").textContent = "";
  if (state.reportUrl) URL.revokeObjectURL(state.reportUrl);
  state.reportUrl = null;
}

async function showReport() {
  closeReport();
  $("report-state").textContent = "loading the report...";
  try {
    // fetched with the API key, shown in a sandboxed frame (no script runs in it)
    const html = await getText(`${versionBase()}/report`);
    state.reportUrl = URL.createObjectURL(new Blob([html], { type: "text/html" }));
    const frame = $("report-frame");
    $("report-state").textContent = `drawing the report (${fmt(html.length / 1e6)} MB)...`;
    frame.addEventListener("load", () => { $("report-state").textContent = ""; }, { once: true });
    frame.src = state.reportUrl;
    frame.hidden = false;
    const a = $("download-report");
    a.href = state.reportUrl;
    a.download = `${state.model}-${$("version").value}-report.html`;
    a.hidden = false;
  } catch (err) {
    $("report-state").textContent = err instanceof ApiError && err.status === 404
      ? "this version has no training report" : String(err.message);
  }
}

// ------------------------------------------------------------------------------------------ records
async function loadExamples() {
  try {
    const text = await (await staticBlob("/static/examples/index.json")).text();
    state.examples = JSON.parse(text).examples || [];
  } catch (_) {
    state.examples = [];
  }
  renderExamples();
}

function renderExamples() {
  const sel = $("examples");
  const keep = sel.value;
  const fit = (e) => state.model && e.models.includes(state.model);
  const sorted = [...state.examples].sort((a, b) => fit(b) - fit(a));
  sel.replaceChildren(el("option", { value: "", textContent: "(choose)" }), ...sorted.map((e) =>
    el("option", { value: e.file, textContent: `${e.title}${fit(e) ? "  [for this model]" : ""}` })));
  sel.value = keep;
}

async function useFiles(files, label) {
  if (!files.length) return;
  $("record-info").hidden = false;
  $("record-info").textContent = `reading ${label}...`;
  try {
    const rec = await parseRecord(files, Number($("fs").value) || null);
    state.record = rec;
    showError(null);
    const dur = rec.n_samples / rec.fs;
    // a new record is used whole; the user narrows it afterwards with "from" and "samples"
    $("count").value = rec.n_samples;
    $("t0").value = 0;
    $("record-info").textContent = `${rec.name} (${rec.format}${rec.files.length > 1 ? ": " + rec.files.join(" + ") : ""}): `
      + `${rec.n_samples} samples at ${fmt(rec.fs)} Hz (${fmt(dur)} s); u [${rec.units.u || "-"}]`
      + (rec.y ? `, y [${rec.units.y || "-"}]` : ", no measured y (prediction only)");
    $("record-info").dataset.samples = String(rec.n_samples);
    checkRecord();
  } catch (err) {
    state.record = null;
    $("record-info").textContent = "no record";
    showError(err);
    checkRecord();
  }
}

function checkRecord() {
  const info = $("record-info");
  const rec = state.record, d = state.detail;
  $("run").disabled = !(rec && d);
  if (!rec || !d) return;
  const mismatch = Math.abs(rec.fs - d.fs) > 1e-6 * d.fs;
  info.classList.toggle("warn", mismatch);
  info.title = mismatch ? `the record's fs (${rec.fs} Hz) differs from the model's (${d.fs} Hz): the API will refuse it` : "";
}

async function loadExample() {
  const file = $("examples").value;
  if (!file) return;
  try {
    const blob = await staticBlob(`/static/examples/${enc(file)}`);
    // steady-state examples start their free run from the measured outputs (index.json says which)
    const start = state.examples.find((e) => e.file === file)?.start;
    if (start) $("start").value = start;
    await useFiles([new File([blob], file)], file);
  } catch (err) {
    showError(err);
  }
}

// ------------------------------------------------------------------------------------------ run
function requestBody() {
  const rec = state.record;
  const i0 = Math.max(0, Math.round(Number($("t0").value || 0) * rec.fs));
  if (i0 >= rec.n_samples) throw new Error(`'from' is past the end of the record (${fmt(rec.n_samples / rec.fs)} s)`);
  const n = Math.max(1, Math.min(Math.round(Number($("count").value) || rec.n_samples), rec.n_samples - i0));
  const body = { u: rec.u.slice(i0, i0 + n), fs: rec.fs, method: $("method").value,
                 seed: Math.round(Number($("seed").value) || 0), confidence: Number($("confidence").value) || 0.99 };
  // Monte Carlo paths: none sent unless the user names them, so the service applies the model's default
  // (default_mc_paths of GET /v1/models/NAME, the CLI's too)
  const paths = $("mc-paths").value.trim();
  if (paths) {
    const k = Math.round(Number(paths));
    if (!(k >= 1)) throw new Error(`paths must be a positive whole number, or empty for the model's default`);
    body.mc_paths = k;
  }
  if (rec.y) body.y = rec.y.slice(i0, i0 + n);
  const start = $("start").value;
  if (start === "measured" && !rec.y) throw new Error("start 'measured' needs a record with a measured y");
  if (start) body.start = start;
  return { body, i0, n };
}

/** A "running..." state on every result panel while the calls are out (they take seconds). */
function loading(on) {
  for (const id of ["verdict-card", "predict-card", "time-plot", "psd-plot", "loops-plot"]) $(id).classList.toggle("loading", on);
  if (on) {
    $("verdict").className = "verdict";
    $("verdict").textContent = "running...";
    $("novelty-reasons").replaceChildren();
    $("gauge").hidden = true;
  }
}

async function run() {
  showError(null);
  let req;
  try { req = requestBody(); } catch (err) { showError(err); return; }
  const { body, i0 } = req;
  const d = state.detail;
  const base = versionBase();
  const wantLoops = d.physics && d.physics.mass != null;
  const wantNovelty = !!d.novelty && !!body.y;
  $("run").disabled = true;
  $("results").hidden = false;
  // what a reader (or a test) waits for is cleared until this run's answers are drawn
  for (const id of ["time-plot", "psd-plot", "loops-plot"]) delete $(id).dataset.ready;
  delete $("verdict").dataset.verdict;
  delete $("predict-metrics").dataset.samples;
  const narrowed = body.u.length < state.record.n_samples;
  const span = narrowed ? `${body.u.length} of the record's ${state.record.n_samples} samples (from ${fmt(i0 / body.fs)} s, `
    + `narrowed by "from" and "samples")` : `the whole record, ${body.u.length} samples`;
  $("run-state").dataset.narrowed = String(narrowed);
  $("run-state").textContent = `running on ${span}...`;
  loading(true);
  const t0 = performance.now();
  const [pred, loops, nov] = await Promise.allSettled([
    postJSON(`${base}/predict`, body),
    wantLoops ? postJSON(`${base}/loops`, body) : Promise.resolve(null),
    wantNovelty ? postJSON(`${base}/novelty`, body) : Promise.resolve(null),
  ]);
  loading(false);
  $("run-state").textContent = `answered in ${fmt((performance.now() - t0) / 1000)} s, on ${span}`;
  $("run").disabled = false;
  const errors = [pred, loops, nov].filter((r) => r.status === "rejected").map((r) => r.reason.message);
  if (errors.length) showError({ message: errors.join("\n") });

  renderNovelty(nov.status === "fulfilled" ? nov.value : null, wantNovelty, body);
  if (pred.status === "fulfilled") renderPrediction(pred.value, body, i0);
  renderLoops(loops.status === "fulfilled" ? loops.value : null, wantLoops);
}

function renderPrediction(p, body, i0) {
  kvTable($("predict-metrics"), { "samples (API n_samples)": p.n_samples, "fit [%]": p.fit, RMSE: p.rmse,
    [`coverage of the ${Math.round(p.confidence * 1000) / 10} % band [%]`]: p.coverage, method: p.method,
    "Monte Carlo paths": p.mc_paths, seed: p.seed, start: p.start, "diverged paths": p.diverged_paths,
    "out of range": p.out_of_range });
  $("predict-metrics").dataset.samples = String(p.n_samples);
  const fs = body.fs;
  const n = p.mean.length;
  const t = Float64Array.from({ length: n }, (_, i) => (i0 + i) / fs);
  const unit = state.detail.units?.y || state.record.units.y;
  timePlot($("time-plot"), { t, y: body.y || null, mean: p.mean, lower: p.lower, upper: p.upper, unit,
                             bandLabel: `${Math.round(p.confidence * 1000) / 10} %` });
  const pm = welch(p.mean, fs);
  psdPlot($("psd-plot"), { f: pm.f, predicted: pm.p, measured: body.y ? welch(body.y, fs).p : null, unit });
}

// what each out_of_range entry means (docs/api.md, "out_of_range")
const OUT_OF_RANGE = {
  u: "the input u left the range of the records the model was trained or calibrated on",
  y: "the measured output y left the range of the calibration records (peak outside the healthy range, widened 2x)",
  prediction: "the predicted mean left the training output envelope",
  frequency: "more than 10 % of the drive's power lies outside the frequency band of the training records",
  probe: "the drive is not the probe this monitor's threshold was calibrated for",
};

function driveText(dr, unit) {
  if (!dr) return "-";
  const amp = `${dr.amplitude_kind === "rms" ? "RMS" : "peak"} ${fmt(dr.amplitude)} ${unit || ""}`.trim();
  return dr.kind === "sine" ? `sine at ${fmt(dr.frequency)} Hz, ${amp}`
    : `broadband (dominant ${fmt(dr.frequency)} Hz), ${amp}`;
}

function probeText(pr, unit) {
  if (!pr) return "this monitor states no probe contract";
  const f = pr.kind === "sine" ? `sine at ${fmt(pr.frequency)} Hz (within ${fmt(pr.frequency_tolerance)} Hz)` : "broadband";
  const [lo, hi] = pr.amplitude || [];
  return `${f}, ${pr.amplitude_kind === "rms" ? "RMS" : "peak"} ${fmt(lo)} to ${fmt(hi)} ${unit || ""} `
    + `(widened ${Math.round((pr.amplitude_tolerance || 0) * 100)} %), free run from ${pr.start}`;
}

/** Why the verdict is what it is: one list item per reason, each with data-reason for a reader (or a test). */
function noveltyReasons(nv) {
  const unit = state.detail?.units?.u || state.record?.units?.u;
  const items = [];
  const add = (reason, text) => items.push(el("li", { dataset: { reason }, textContent: text }));
  const mismatch = nv.probe_match === false;
  if (nv.verdict === "unjudged" || mismatch) {
    add("unjudged", "Not judged: the record's drive does not match the probe the threshold was calibrated for, so the "
      + "score measures the model's accuracy at another excitation, not a change of the structure.");
  }
  for (const r of nv.probe_reasons || []) add("probe-mismatch", `probe mismatch: ${r}`);
  const ratio = nv.score / nv.threshold;
  add("score", `score ${fmt(nv.score)} against threshold ${fmt(nv.threshold)} (${fmt(ratio)} x)`
    + (mismatch ? ": not compared" : nv.score > nv.threshold ? ": above" : ": below"));
  for (const k of nv.out_of_range || []) {
    if (k !== "probe") add(`out-of-range-${k}`, `out of range '${k}': ${OUT_OF_RANGE[k] || "see docs/api.md"}`);
  }
  add("drive", `drive found: ${driveText(nv.drive, unit)}`);
  if (nv.probe_match != null || state.detail?.probe) {
    add("probe", `probe expected: ${probeText(state.detail?.probe, unit)}`
      + (nv.probe_match === true ? " (matches)" : ""));
  }
  return items;
}

function renderNovelty(nv, wanted, body) {
  const v = $("verdict"), table = $("novelty");
  v.className = "verdict";
  $("gauge").hidden = true;
  $("novelty-reasons").replaceChildren();
  delete v.dataset.verdict;
  if (!nv) {
    v.textContent = "-";
    kvTable(table, { note: !state.detail.novelty ? "this version has no novelty calibration"
      : !body.y ? "the record has no measured y" : wanted ? "the novelty call failed" : "-" });
    return;
  }
  v.textContent = nv.verdict;
  v.dataset.verdict = nv.verdict;
  v.dataset.score = String(nv.score);
  v.dataset.samples = String(nv.n_samples);
  v.classList.add(nv.verdict);
  const top = Math.max(nv.score, nv.threshold) * 1.25;
  $("gauge").hidden = false;
  $("gauge-bar").style.width = `${Math.min(100, (100 * nv.score) / top)}%`;
  $("gauge-bar").className = nv.verdict;
  $("gauge-thr").style.left = `${(100 * nv.threshold) / top}%`;
  $("gauge").title = `score ${fmt(nv.score)} against threshold ${fmt(nv.threshold)}`;
  $("novelty-reasons").replaceChildren(...noveltyReasons(nv));
  kvTable(table, { score: nv.score, threshold: nv.threshold, "score / threshold": nv.score / nv.threshold,
    "probe match": nv.probe_match == null ? "no probe contract" : nv.probe_match ? "yes" : "no",
    "false-alarm rate": nv.false_alarm_rate, "score method": nv.score_method, "out of range": nv.out_of_range,
    "samples scored": nv.n_samples, NLPD: nv.nlpd, start: nv.start });
}

/** Units of a loop as the API states them (model.restoring.loop_units), from the bundle's units and physics. */
function loopUnits(units, physics) {
  const yu = String(units?.y || "m");
  const x = (physics?.output || "displacement") === "displacement" ? yu : (yu.endsWith("/s") ? yu.slice(0, -2) : "m");
  const xs = x || "m";
  return { x: xs, force: "N", energy: xs === "m" ? "J" : `N ${xs}`, stiffness: `N/${xs}` };
}

/** Axis limits of a loop view that the start-up transient of a free run from rest does not stretch: the
 * 0.5-99.5 % quantiles of the loops (predicted, measured, band edges) over the steady cycles (the answer's
 * `cycles`) when there are any, else over the whole record; widened 8 %. */
function robustView(lp, fs) {
  const loops = [lp.predicted, lp.measured, lp.lower, lp.upper].filter(Boolean);
  const n = lp.predicted.x.length;
  let i0 = 0, i1 = n;
  const steady = Array.isArray(lp.cycles) && lp.cycles.length;
  if (steady) {
    i0 = Math.max(0, Math.floor(lp.cycles[0].start * fs));
    i1 = Math.min(n, Math.ceil(lp.cycles[lp.cycles.length - 1].end * fs) + 1);
  }
  const span = (key) => {
    const v = [];
    for (const l of loops) for (let i = i0; i < i1; i++) if (Number.isFinite(l[key][i])) v.push(l[key][i]);
    v.sort((a, b) => a - b);
    if (!v.length) return null;
    const q = (p) => v[Math.min(v.length - 1, Math.max(0, Math.round(p * (v.length - 1))))];
    let [lo, hi] = [q(0.005), q(0.995)];
    const pad = 0.08 * (hi - lo || Math.abs(hi) || 1);
    return [lo - pad, hi + pad];
  };
  const x = span("x"), y = span("force");
  if (!x || !y) return null;
  // points of the whole record that the view leaves out (the start-up transient)
  let outside = 0;
  for (let i = 0; i < n; i++) {
    const a = lp.predicted.x[i], b = lp.predicted.force[i];
    if (a < x[0] || a > x[1] || b < y[0] || b > y[1]) outside++;
  }
  return { x, y, outside, basis: steady ? "the steady cycles" : "the bulk of the record" };
}

const ordered = (a, b) => (a != null && b != null && a > b ? [b, a] : [a, b]);

function renderLoops(lp, wanted) {
  const note = $("loops-note");
  const box = $("cycles-box");
  box.hidden = true;
  if (!lp) {
    $("loops-plot").replaceChildren();
    note.textContent = wanted ? "the loops call failed" : "this version has no physical constants (mass): no restoring force";
    return;
  }
  const units = { ...loopUnits(state.detail?.units, state.detail?.physics), ...(lp.units || {}) };
  const view = robustView(lp, state.record?.fs || state.detail?.fs || 1);
  loopsPlot($("loops-plot"), lp, units, view);
  const area = (l) => (l ? fmt(l.area) : "-");
  const [lo, hi] = ordered(lp.lower?.area, lp.upper?.area);
  note.textContent = `loop area (whole record) [${units.energy}]: predicted ${area(lp.predicted)}, band edges `
    + `${fmt(lo)} to ${fmt(hi)}` + (lp.measured ? `, measured ${area(lp.measured)}` : "")
    + (view && view.outside ? `. Axes fitted to ${view.basis}: ${view.outside} of ${lp.predicted.x.length} points `
      + "(the start-up transient) lie outside; drag to zoom, double-click for the whole record." : "");
  $("loops-plot").dataset.clipped = String(view ? view.outside : 0);
  if (Array.isArray(lp.cycles) && lp.cycles.length) {
    const U = { start: "s", end: "s", energy: units.energy, energy_lower: units.energy, energy_upper: units.energy,
                stiffness: units.stiffness, measured_energy: units.energy, measured_stiffness: units.stiffness };
    const cols = ["start", "end", "energy", "energy_lower", "energy_upper", "stiffness", "measured_energy",
                  "measured_stiffness"].filter((k) => lp.cycles.some((c) => c[k] != null));
    const rows = lp.cycles.map((c) => {
      const [a, b] = ordered(c.energy_lower, c.energy_upper);
      return { ...c, energy_lower: a, energy_upper: b };
    });
    $("cycles").replaceChildren(
      el("tr", {}, ...cols.map((k) => el("th", { textContent: `${k.replaceAll("_", " ")} [${U[k]}]` }))),
      ...rows.map((c) => el("tr", {}, ...cols.map((k) => el("td", { className: "num", textContent: fmt(c[k]) })))));
    box.hidden = false;
  }
}

// ------------------------------------------------------------------------------------------ wiring
function init() {
  $("api-key").value = apiKey();
  $("key-state").textContent = apiKey() ? "key set" : "";
  $("key-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    setApiKey($("api-key").value.trim());
    $("key-state").textContent = apiKey() ? "key set" : "no key";
    state.model = null;
    loadModels();
  });
  $("version").addEventListener("change", loadVersion);
  $("show-report").addEventListener("click", showReport);
  $("file").addEventListener("change", (ev) => useFiles([...ev.target.files], [...ev.target.files].map((f) => f.name).join(" + ")));
  $("folder").addEventListener("change", (ev) => {
    const files = [...ev.target.files].filter((f) => f.name === "Time.mat" || f.name === "TimeShaker.mat");
    if (files.length !== 2) showError({ message: "the folder holds no LMS export (Time.mat and TimeShaker.mat)" });
    else useFiles(files, files[0].webkitRelativePath.split("/")[0] || "LMS folder");
  });
  $("load-example").addEventListener("click", loadExample);
  $("run").addEventListener("click", run);
  document.body.dataset.root = root;
  loadModels();
  loadExamples();
}

init();
