// The engineers' page: models and versions, a record (file or example), and the prediction, PSD,
// restoring-force loops and novelty verdict, all through the service's /v1 API.

import { ApiError, apiKey, enc, getJSON, getText, parseRecord, postJSON, root, setApiKey, staticBlob } from "./api.js";
import { lowpassStretch, welch } from "./dsp.js";
import { fmt, LOOP_COLOURS, loopsPlot, psdPlot, timePlot, trendPlot } from "./plots.js";

const $ = (id) => document.getElementById(id);
const state = { models: [], model: null, detail: null, record: null, examples: [], reportUrl: null, loops: null };

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
    $("mc-paths").title = `Monte Carlo paths of predict and loops; empty: the model's default${mcDefault ? ` (${mcDefault})` : ""}`;
    $("model-detail").hidden = false;
    pathsNote();
    loadTrend();
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

/** What the paths field costs, and what novelty runs with (its calibration's paths, whatever the field says). */
function pathsNote() {
  const d = state.detail;
  if (!d) return;
  const field = $("mc-paths").value.trim();
  const model = d.default_mc_paths?.predict;
  const paths = field ? Math.round(Number(field)) : model;
  const parts = [];
  if ($("method").value === "linear") {
    parts.push("Linearised: one propagation of the mean and covariance, no Monte Carlo paths.");
  } else if (paths) {
    parts.push(`Predict and loops run ${paths} Monte Carlo paths${field ? "" : " (the model's default)"}: their time `
      + "grows with paths x samples (64 paths answer a few thousand samples in seconds)"
      + (model > paths ? `; the model's default, ${model} paths, takes up to ${Math.round(model / paths)} times as long `
        + "and gives a smoother band (its edges are quantiles across the paths)." : "."));
  }
  if (d.novelty) {
    parts.push(`Novelty runs as its threshold was calibrated (method ${d.default_method?.novelty || "of the calibration"}, `
      + `${d.default_mc_paths?.novelty || "the calibration's"} paths), whatever these fields say, so its verdict is the `
      + "one a monitoring system gets for the same record; it is drawn when it arrives.");
  }
  $("paths-note").textContent = parts.join(" ");
}

/** The novelty trend of the selected model (GET /v1/models/NAME/novelty/history), when it has a calibration. */
async function loadTrend() {
  const box = $("trend-box"), note = $("trend-note"), plot = $("trend-plot");
  const d = state.detail;
  box.hidden = !d?.novelty;
  if (!d?.novelty) return;
  const model = state.model;
  delete plot.dataset.ready;
  try {
    const h = await getJSON(`/v1/models/${enc(model)}/novelty/history?limit=200`);
    if (state.model !== model) return;
    const pts = h.points.filter((p) => p.score != null && p.score > 0);
    plot.hidden = !pts.length;
    if (!pts.length) {
      plot.replaceChildren();
      plot.dataset.points = "0";
      plot.dataset.ready = "1";
      note.textContent = `No verdict to draw: ${h.reason || "none in the audit trail"}.`;
      return;
    }
    trendPlot(plot, pts);
    const last = pts[pts.length - 1];
    plot.dataset.last = JSON.stringify({ verdict: last.verdict, score: last.score, request_id: last.request_id });
    const count = (v) => pts.filter((p) => p.verdict === v).length;
    const versions = [...new Set(pts.map((p) => p.version))].join(", ");
    note.textContent = `${pts.length} verdict${pts.length > 1 ? "s" : ""} from ${pts[0].time} to ${pts[pts.length - 1].time} `
      + `(UTC; version ${versions}): ${count("healthy")} healthy, ${count("novel")} novel, ${count("unjudged")} unjudged`
      + `; the dashed line${pts.length === 1 ? " (a ring for a single verdict)" : ""} is the threshold each was judged `
      + `against. Read from ${h.target}`
      + (h.older_unread ? "; older verdicts lie beyond what one call reads" : "")
      + (h.skipped_lines ? `; ${h.skipped_lines} damaged line(s) skipped` : "") + ".";
  } catch (err) {
    plot.replaceChildren();
    plot.hidden = true;
    note.textContent = `The trend could not be read: ${err.message}`;
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

const PANELS = { predict: ["predict-card", "time-plot", "psd-plot"], loops: ["loops-plot"], novelty: ["verdict-card"] };

/** A "running..." state on a call's result panels while it is out (it takes seconds). */
function loading(op, on) {
  for (const id of PANELS[op]) $(id).classList.toggle("loading", on);
  if (op === "novelty" && on) {
    $("verdict").className = "verdict";
    $("verdict").textContent = "running...";
    $("novelty-reasons").replaceChildren();
    $("gauge").hidden = true;
  }
}

/** A failed call's HTTP status and problem detail, as the page says them. */
function problemText(err) {
  if (err instanceof ApiError) {
    const p = err.problem || {};
    return `${err.status} ${p.title || "error"}: ${p.detail || "no detail"}${p.field ? ` (field ${p.field})` : ""}`;
  }
  return String(err?.message || err);
}

const failure = (op, err) => `${op}: ${problemText(err)}`;

async function run() {
  showError(null);
  let req;
  try { req = requestBody(); } catch (err) { showError(err); return; }
  const { body, i0 } = req;
  const d = state.detail;
  const base = versionBase();
  const wantLoops = d.physics && d.physics.mass != null;
  const wantNovelty = !!d.novelty && !!body.y;
  // novelty as its threshold was calibrated: the model's method and paths for novelty (none sent)
  const { mc_paths: _paths, method: _method, ...noveltyBody } = body;
  $("run").disabled = true;
  $("results").hidden = false;
  // what a reader (or a test) waits for is cleared until this run's answers are drawn
  for (const id of ["time-plot", "psd-plot", "loops-plot"]) delete $(id).dataset.ready;
  delete $("verdict").dataset.verdict;
  delete $("verdict").dataset.failed;
  delete $("predict-metrics").dataset.samples;
  delete $("run-state").dataset.outcome;
  const narrowed = body.u.length < state.record.n_samples;
  const span = narrowed ? `${body.u.length} of the record's ${state.record.n_samples} samples (from ${fmt(i0 / body.fs)} s, `
    + `narrowed by "from" and "samples")` : `the whole record, ${body.u.length} samples`;
  $("run-state").dataset.narrowed = String(narrowed);
  $("run-state").textContent = `running on ${span}...`;
  const t0 = performance.now();
  const took = {}, failed = {};
  const call = (op, path, b, render) => {
    loading(op, true);
    return postJSON(path, b).then((v) => { took[op] = (performance.now() - t0) / 1000; loading(op, false); render(v); },
      (err) => { failed[op] = err; loading(op, false); render(null, err); });
  };
  const calls = [call("predict", `${base}/predict`, body, (p, err) => renderPrediction(p, body, i0, err))];
  if (wantLoops) calls.push(call("loops", `${base}/loops`, body, (lp, err) => renderLoops(lp, true, body, err)));
  else renderLoops(null, false, body);
  if (wantNovelty) calls.push(call("novelty", `${base}/novelty`, noveltyBody, (nv, err) => renderNovelty(nv, true, body, err)));
  else renderNovelty(null, false, body);
  await Promise.all(calls);
  $("run").disabled = false;
  const ops = Object.keys(failed);
  const answered = Object.keys(took).map((op) => `${op} ${fmt(took[op])} s`).join(", ");
  if (ops.length) {
    const problems = ops.map((op) => failure(op, failed[op]));
    $("run-state").dataset.outcome = "failed";
    $("run-state").dataset.failed = ops.join(",");
    $("run-state").textContent = `${ops.length === calls.length ? "Run failed" : `Run partly failed (${ops.join(", ")})`} `
      + `on ${span}: ${problems.join("; ")}` + (answered ? `. Answered: ${answered}.` : ".");
    showError({ message: problems.join("\n") });
  } else {
    $("run-state").dataset.outcome = "ok";
    $("run-state").textContent = `answered in ${fmt((performance.now() - t0) / 1000)} s (${answered}), on ${span}`;
  }
  if (wantNovelty && !failed.novelty) setTimeout(loadTrend, 500);  // the new verdict's audit line, once written
}

function renderPrediction(p, body, i0, err) {
  if (!p) {
    kvTable($("predict-metrics"), { note: `the predict call failed: ${problemText(err)}` });
    for (const id of ["time-plot", "psd-plot"]) $(id).replaceChildren();
    return;
  }
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

function renderNovelty(nv, wanted, body, err) {
  const v = $("verdict"), table = $("novelty");
  v.className = "verdict";
  $("gauge").hidden = true;
  $("novelty-reasons").replaceChildren();
  delete v.dataset.verdict;
  if (!nv) {
    v.textContent = "-";
    kvTable(table, { note: !state.detail.novelty ? "this version has no novelty calibration"
      : !body.y ? "the record has no measured y" : wanted ? `the novelty call failed: ${problemText(err)}` : "-" });
    if (wanted && err) {
      v.textContent = "failed";
      v.dataset.failed = "1";
    }
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
    "samples scored": nv.n_samples, NLPD: nv.nlpd, start: nv.start,
    "method, paths (as calibrated)": `${nv.method}${nv.method === "mc" ? `, ${nv.mc_paths}` : ""}` });
}

/** Units of a loop as the API states them (model.restoring.loop_units), from the bundle's units and physics. */
function loopUnits(units, physics) {
  const yu = String(units?.y || "m");
  const x = (physics?.output || "displacement") === "displacement" ? yu : (yu.endsWith("/s") ? yu.slice(0, -2) : "m");
  const xs = x || "m";
  return { x: xs, force: "N", energy: xs === "m" ? "J" : `N ${xs}`, stiffness: `N/${xs}` };
}

/** The samples of the steady cycles (the loops answer's `cycles`: the start-up cycles of a free run from rest and
 * the record's ends are not among them), as [first, end) indices; the whole record when there is none. */
function steadyWindow(lp, fs) {
  const n = lp.predicted.x.length;
  if (!Array.isArray(lp.cycles) || !lp.cycles.length) return { i0: 0, i1: n, steady: false };
  const i0 = Math.max(0, Math.floor(lp.cycles[0].start * fs));
  const i1 = Math.min(n, Math.ceil(lp.cycles[lp.cycles.length - 1].end * fs) + 1);
  return i1 - i0 > 1 ? { i0, i1, steady: true } : { i0: 0, i1: n, steady: false };
}

/** The low-pass cut-off of the loops [Hz]: a sine drive (the loops answer's cycle basis 'drive') keeps its first
 * harmonics, 3.5 x its frequency; a broadband drive is cut 1.25 x above the top of its band (the frequency below
 * which 99 % of u's power lies, Welch PSD); at most 0.4 fs. */
function autoCutoff(lp, u, fs) {
  let top;
  if (lp.cycle_basis?.basis === "drive" && lp.cycle_basis.frequency > 0) {
    top = 3.5 * lp.cycle_basis.frequency;
  } else {
    const { f, p } = welch(u, fs);
    const total = p.reduce((a, b) => a + b, 0);
    let acc = 0, k = 0;
    while (k < p.length - 1 && acc + p[k] < 0.99 * total) acc += p[k++];
    top = 1.25 * f[k];
  }
  return Number((Math.min(top, 0.4 * fs)).toPrecision(3));
}

/** Axis limits that fit the 0.5-99.5 % quantiles of the given loops, widened 8 %: a start-up transient or a
 * noisy loop's outliers do not stretch them. */
function robustView(loops) {
  const span = (key) => {
    const v = [];
    for (const l of loops) for (const a of l[key]) if (Number.isFinite(a)) v.push(a);
    v.sort((a, b) => a - b);
    if (!v.length) return null;
    const q = (p) => v[Math.min(v.length - 1, Math.max(0, Math.round(p * (v.length - 1))))];
    const [lo, hi] = [q(0.005), q(0.995)];
    const pad = 0.08 * (hi - lo || Math.abs(hi) || 1);
    return [lo - pad, hi + pad];
  };
  const x = span("x"), y = span("force");
  return x && y ? { x, y } : null;
}

const ordered = (a, b) => (a != null && b != null && a > b ? [b, a] : [a, b]);

/** The loops drawn from the loops answer: predicted mean, band edges and measured, low-passed (zero-phase) when
 * the filter is on, over the steady cycles unless "whole record" is ticked; the measured loop as the API gives it
 * (the raw record differentiated twice: a cloud of noise) only when "measured, unfiltered" is ticked. */
function loopSeries(lp, fs, fc, filter, whole) {
  const win = whole ? { i0: 0, i1: lp.predicted.x.length, steady: false } : steadyWindow(lp, fs);
  const cut = (a) => Array.prototype.slice.call(a, win.i0, win.i1);
  const on = filter && fc > 0 && fc < fs / 2 && win.i1 - win.i0 > 15;
  const smooth = (a) => (on ? Array.from(lowpassStretch(a, win.i0, win.i1, fc, fs, whole ? 0 : 5)) : cut(a));
  const tag = on ? `, low-passed ${fmt(fc)} Hz` : "";
  const out = [];
  const add = (key, label, stroke, width) => {
    const l = lp[key];
    if (l) out.push({ key, label: `${label}${tag}`, x: smooth(l.x), force: smooth(l.force), stroke, width });
  };
  add("lower", "band lower", LOOP_COLOURS.edge, 0.6);
  add("upper", "band upper", LOOP_COLOURS.edge, 0.6);
  add("measured", "measured", LOOP_COLOURS.meas, 1);
  add("predicted", "predicted mean", LOOP_COLOURS.pred, 1.4);
  return { loops: out, win, filtered: on };
}

function renderLoops(lp, wanted, body, err) {
  const note = $("loops-note");
  const box = $("cycles-box");
  box.hidden = true;
  state.loops = lp ? { lp, fs: body.fs, u: body.u } : null;
  if (!lp) {
    $("loops-plot").replaceChildren();
    note.textContent = wanted ? `the loops call failed: ${problemText(err)}`
      : "this version has no physical constants (mass): no restoring force";
    return;
  }
  $("loops-fc").value = autoCutoff(lp, body.u, body.fs);
  drawLoops();
  const units = { ...loopUnits(state.detail?.units, state.detail?.physics), ...(lp.units || {}) };
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

/** (Re)draw the loops of the last loops answer with the loop controls' settings. */
function drawLoops() {
  if (!state.loops) return;
  const { lp, fs } = state.loops;
  const plot = $("loops-plot");
  const units = { ...loopUnits(state.detail?.units, state.detail?.physics), ...(lp.units || {}) };
  const fc = Number($("loops-fc").value);
  const whole = $("loops-whole").checked;
  const { loops, win, filtered } = loopSeries(lp, fs, fc, $("loops-filter").checked, whole);
  // the axes fit the loops drawn by default (never the unfiltered measured cloud)
  const view = robustView(loops);
  if ($("loops-raw").checked && lp.measured) {
    const cut = (a) => Array.prototype.slice.call(a, win.i0, win.i1);
    loops.unshift({ key: "measured-raw", label: "measured, unfiltered", x: cut(lp.measured.x),
                    force: cut(lp.measured.force), stroke: LOOP_COLOURS.raw, width: 0.6 });
  }
  loopsPlot(plot, loops, units, view);
  const n = lp.predicted.x.length;
  let outside = 0;
  const pred = loops.find((l) => l.key === "predicted");
  if (view && pred) {
    for (let i = 0; i < pred.x.length; i++) {
      const a = pred.x[i], b = pred.force[i];
      if (a < view.x[0] || a > view.x[1] || b < view.y[0] || b > view.y[1]) outside++;
    }
  }
  plot.dataset.window = JSON.stringify([win.i0, win.i1]);
  plot.dataset.cutoff = filtered ? String(fc) : "";
  plot.dataset.clipped = String(outside);
  const area = (l) => (l ? fmt(l.area) : "-");
  const [lo, hi] = ordered(lp.lower?.area, lp.upper?.area);
  const cycles = Array.isArray(lp.cycles) ? lp.cycles.length : 0;
  const shown = win.steady
    ? `Drawn: the ${cycles} steady cycle${cycles === 1 ? "" : "s"} of the loops answer (${fmt(win.i0 / fs)} to `
      + `${fmt(win.i1 / fs)} s; ${n - (win.i1 - win.i0)} of ${n} samples, the start-up transient and the record's `
      + "ends, left out: tick whole record to draw them)"
    : `Drawn: the whole record (${n} samples)${outside ? `; axes fitted to the bulk of the loops, ${outside} points `
      + "of the predicted loop (the start-up transient) lie outside: drag to zoom, double-click to fit all" : ""}`;
  const filt = filtered
    ? `, every loop low-passed at ${fmt(fc)} Hz (zero-phase Butterworth, order 4): R = g u - m x'' holds the output `
      + "differentiated twice, which lifts its noise by (2 pi f)^2; the measured loop unfiltered is a cloud (tick "
      + "measured, unfiltered to draw it)"
    : ", unfiltered";
  $("loops-note").textContent = `${shown}${filt}. Loop area (whole record, unfiltered) [${units.energy}]: predicted `
    + `${area(lp.predicted)}, band edges ${fmt(lo)} to ${fmt(hi)}` + (lp.measured ? `, measured ${area(lp.measured)}` : "")
    + "; the per-cycle energies below never differentiate the output.";
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
  for (const id of ["loops-filter", "loops-fc", "loops-raw", "loops-whole"]) $(id).addEventListener("change", drawLoops);
  for (const id of ["mc-paths", "method"]) $(id).addEventListener("change", pathsNote);
  document.body.dataset.root = root;
  loadModels();
  loadExamples();
}

init();
