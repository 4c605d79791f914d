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
  try {
    const d = await getJSON(versionBase());
    state.detail = d;
    showError(null);
    $("model-detail").hidden = false;
    kvTable($("meta"), d, [["name", "name"], ["version", "version"], ["created", "created"], ["mode", "mode"],
      ["fs", "fs [Hz]"], ["units", "units"], ["lags", "lags"], ["n_train", "training points"], ["physics", "physics"],
      ["noise_calibration", "noise calibration"]]);
    kvTable($("training"), d.training);
    kvTable($("novelty-cal"), d.novelty ? { ...d.novelty, ...(d.probe ? { probe: d.probe } : {}) } : null);
    $("meta-more").textContent = JSON.stringify({ kernel: d.kernel, hyperparameters: d.hyperparameters,
                                                  package_versions: d.package_versions }, null, 1);
    checkRecord();
  } catch (err) {
    showError(err);
  }
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
    frame.src = state.reportUrl;
    frame.hidden = false;
    const a = $("download-report");
    a.href = state.reportUrl;
    a.download = `${state.model}-${$("version").value}-report.html`;
    a.hidden = false;
    $("report-state").textContent = "";
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
                 mc_paths: Math.round(Number($("mc-paths").value) || 64), seed: Math.round(Number($("seed").value) || 0),
                 confidence: Number($("confidence").value) || 0.99 };
  if (rec.y) body.y = rec.y.slice(i0, i0 + n);
  const start = $("start").value;
  if (start === "measured" && !rec.y) throw new Error("start 'measured' needs a record with a measured y");
  if (start) body.start = start;
  return { body, i0, n };
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
  const t0 = performance.now();
  const [pred, loops, nov] = await Promise.allSettled([
    postJSON(`${base}/predict`, body),
    wantLoops ? postJSON(`${base}/loops`, body) : Promise.resolve(null),
    wantNovelty ? postJSON(`${base}/novelty`, body) : Promise.resolve(null),
  ]);
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

function renderNovelty(nv, wanted, body) {
  const v = $("verdict"), table = $("novelty");
  v.className = "verdict";
  $("gauge").hidden = true;
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
  v.classList.add(nv.verdict);
  const top = Math.max(nv.score, nv.threshold) * 1.25;
  $("gauge").hidden = false;
  $("gauge-bar").style.width = `${Math.min(100, (100 * nv.score) / top)}%`;
  $("gauge-bar").className = nv.verdict;
  $("gauge-thr").style.left = `${(100 * nv.threshold) / top}%`;
  $("gauge").title = `score ${fmt(nv.score)} against threshold ${fmt(nv.threshold)}`;
  kvTable(table, { score: nv.score, threshold: nv.threshold, "score / threshold": nv.score / nv.threshold,
    "false-alarm rate": nv.false_alarm_rate, "score method": nv.score_method, "out of range": nv.out_of_range,
    "samples scored": nv.n_samples, NLPD: nv.nlpd, start: nv.start });
}

function renderLoops(lp, wanted) {
  const note = $("loops-note");
  const box = $("cycles-box");
  box.hidden = true;
  if (!lp) {
    $("loops-plot").replaceChildren();
    note.textContent = wanted ? "the loops call failed" : "this version has no physical constants (mass): no restoring force";
    return;
  }
  loopsPlot($("loops-plot"), lp, lp.units);
  const area = (l) => (l ? fmt(l.area) : "-");
  note.textContent = `loop area (whole record): predicted ${area(lp.predicted)}, band ${area(lp.lower)} .. ${area(lp.upper)}`
    + (lp.measured ? `, measured ${area(lp.measured)}` : "") + ` [${lp.units?.force || "N"} ${lp.units?.x || "m"}]`;
  if (Array.isArray(lp.cycles) && lp.cycles.length) {
    const cols = ["start", "end", "energy", "energy_lower", "energy_upper", "stiffness", "measured_energy"]
      .filter((k) => lp.cycles.some((c) => c[k] != null));
    $("cycles").replaceChildren(el("tr", {}, ...cols.map((k) => el("th", { textContent: k.replace("_", " ") }))),
      ...lp.cycles.map((c) => el("tr", {}, ...cols.map((k) => el("td", { className: "num", textContent: fmt(c[k]) })))));
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
