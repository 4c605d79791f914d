"""Request and response models (pydantic v2) of the HTTP API.

Field names are the API contract (docs/api.md): records are ``u``, ``fs``, ``y``, ``y0``,
``mc_paths``, ``seed``, ``confidence`` (and ``method``); answers hold ``mean``, ``lower``,
``upper``, ``std`` and, when a measured ``y`` was sent, ``fit``, ``rmse``, ``coverage``.
Numbers must be finite JSON numbers (NaN/Infinity are refused); numeric fields are strict (a
string "1.0" or a boolean is not a number).

Bounds that can be changed by environment variables (``service.settings``) are not encoded as
schema constraints; their defaults are stated in the descriptions and enforced by the service with
a 413/422 problem detail naming the field and the limit.
"""
from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict, StrictBool

from gpnarx.operations.stream_token import MAX_TOKEN_CHARS

from .settings import DEFAULT_BOUNDS

B = DEFAULT_BOUNDS

FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False)]
StrictInt = Annotated[int, Strict()]

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
VERSION_PATTERN = r"^(?:[1-9][0-9]{0,8}|[A-Za-z][A-Za-z0-9_-]{0,31})$"  # a version or an alias (production)

_U_DESC = (f"Input record (input units of the model, e.g. force in N or shaker voltage in V), one value per "
           f"sample at `fs`. 1 to {B['max_samples']} samples by default (GPNARX_MAX_SAMPLES); a longer "
           f"record is refused with 413.")
_FS_DESC = "Sampling frequency of the record [Hz]; must equal the model's `fs` (422 naming both values otherwise)."
_Y_DESC = ("Optional measured output record (output units, e.g. m or m/s), same length as `u`. When sent, the "
           "answer adds `fit` (%, eq. 14), `rmse` and `coverage` (% of samples inside the band).")
_Y0_DESC = ("Optional first `ny` measured outputs (ny = the model's output lag). They are taken as known and the "
            "free run starts after them; without `y0` the system starts from rest, except for novelty, which "
            "starts from the first `ny` samples of `y` (the record's own measured start). Extra values are ignored.")
_MC_DESC = (f"Monte Carlo paths for `method`='mc' (default: the model's, `default_mc_paths` of GET "
            f"/v1/models/{{name}}: its trained config's `[predict] mc_paths`, as the CLI uses, unless "
            f"GPNARX_MC_PATHS_DEFAULT is set; at most {B['mc_paths_max']} by default: GPNARX_MC_PATHS_MAX; "
            f"above the maximum -> 422). "
            f"mc_paths x samples is capped at {B['max_mc_work']} path-steps per HTTP request "
            f"(GPNARX_MAX_MC_WORK; a batch shares one budget) -> 413. Ignored for 'linear'.")
_SEED_DESC = "Seed of the Monte Carlo draws; the same request with the same seed gives the same answer."
_CONF_DESC = "Two-sided band probability, in [0.5, 1). Default 0.99 (the 0.5% and 99.5% quantiles)."
_START_DESC = ("Where the free run starts: 'rest' (the system at rest before the record; the default for predict "
               "and loops without `y0`) or 'measured' (from the record's first `ny` measured outputs, taken from "
               "`y0` or else from `y`; the default for novelty and with `y0`; 'rest' with `y0` is a 422). Use "
               "'measured' for a window cut from the middle of a steady run, 'rest' for a record that starts with "
               "the structure at rest.")
_BACKEND_DESC = ("Array backend of the free run: 'numpy' (the default) or 'jax' (one compiled program; on a GPU "
                 "where the server has the CUDA build of JAX; Monte Carlo evaluates eq. 8-9 exactly at every path, "
                 "so its bands agree with numpy's within Monte Carlo error, not path for path). Default: the "
                 "server's `GPNARX_BACKEND`. A server without JAX answers 'jax' with 422.")
_METHOD_DESC = ("Uncertainty propagation: 'mc' (Monte Carlo over `mc_paths` paths, the paper's method) or "
                "'linear' (first-order propagation of mean and variance, one pass). Default: the model's "
                "`default_method` (GET /v1/models/{name}): the trained config's, and for novelty the one its "
                "threshold was calibrated with.")


_GAPS_DESC = (" A gap (samples the acquisition dropped) is `null`: the answer holds null through it and the free "
              "run restarts after it, from the measured outputs where `y` is sent, from rest otherwise; the answer "
              "lists `gaps`, and fit and coverage skip them. At most 2 s a gap and half the record in gaps "
              "(422 naming the field otherwise); predict only (loops and novelty: 422), not in a stream.")
_HORIZON_DESC = ("k-step-ahead prediction (predict only): every `horizon` = k samples the free run restarts from "
                 "the measured outputs, so `y` is required. Sample s + j of a segment starting at s is predicted "
                 "j + 1 steps ahead of the last measured output it uses (MATLAB `compare(data, sys, k)`). The run "
                 "starts from y's first ny samples (`y0` and `start` do not apply). k = 1 is the one-step-ahead "
                 "prediction of eqs. 8-9; k >= the record's length, the free run from the measured start. The band "
                 "is eqs. 8-9's propagated over the at most k steps since the last restart (the free run's "
                 "discrepancy term is not added). numpy backend; not in a stream (422). The answer says `horizon`.")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


_STATE_DESC = ("A stream's state: the `state` token of the previous chunk's answer (same model and version, "
               "same `method`, and for Monte Carlo the same `mc_paths`). The free run continues from it instead "
               "of starting at rest or at measured outputs, so a record sent in chunks gets the answers of the "
               "record sent whole. `y0` and `start` do not apply. Damaged, truncated or forged tokens: 422, "
               "field `state`; a token of another model version: 409.")
_RETURN_STATE_DESC = ("Return the free run's end state as `state` in the answer, to continue the stream with the "
                      "next chunk. The band's last half-window is then computed for a record that goes on.")


class RecordRequest(_Strict):
    """A record to predict from (the body of predict and loops)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"u": [0.0, 1.5, 2.0, -0.5, -1.0, 0.25], "fs": 750.0, "mc_paths": 64, "seed": 0, "confidence": 0.99}]})

    u: list[FiniteFloat | None] = Field(..., min_length=1, description=_U_DESC + _GAPS_DESC)
    fs: FiniteFloat = Field(..., gt=0, description=_FS_DESC)
    y: list[FiniteFloat | None] | None = Field(None, min_length=1, description=_Y_DESC + " A `null` sample is a gap.")
    y0: list[FiniteFloat] | None = Field(None, description=_Y0_DESC)
    mc_paths: StrictInt | None = Field(None, ge=1, description=_MC_DESC)
    seed: StrictInt = Field(0, ge=0, le=2**63 - 1, description=_SEED_DESC)
    confidence: FiniteFloat = Field(0.99, ge=0.5, lt=1.0, description=_CONF_DESC)
    method: Literal["mc", "linear"] | None = Field(None, description=_METHOD_DESC)
    backend: Literal["numpy", "jax"] | None = Field(None, description=_BACKEND_DESC)
    start: Literal["rest", "measured"] | None = Field(None, description=_START_DESC)
    state: str | None = Field(None, min_length=1, max_length=MAX_TOKEN_CHARS, description=_STATE_DESC)
    return_state: StrictBool = Field(False, description=_RETURN_STATE_DESC)
    horizon: StrictInt | None = Field(None, ge=1, description=_HORIZON_DESC)


class NoveltyRequest(RecordRequest):
    """A measured record to score against the model (``y`` is required)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"u": [0.0, 1.5, 2.0, -0.5, -1.0, 0.25], "y": [0.0, 1e-5, 3e-5, 2e-5, -1e-5, -2e-5], "fs": 750.0,
         "mc_paths": 64, "seed": 0}]})

    y: list[FiniteFloat] = Field(..., min_length=1, description="Measured output record (output units), same "
                                 "length as `u`. Required: the score compares it with the predicted band.")


class BatchItem(RecordRequest):
    """One record of a batch: the single call's fields plus the model and the operation."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"model": "bouc-wen", "operation": "predict", "u": [0.0, 1.5, 2.0, -0.5], "fs": 750.0, "mc_paths": 32}]})

    model: str = Field(..., pattern=NAME_PATTERN, description="Model name.")
    version: str | None = Field(None, pattern=VERSION_PATTERN, description="Model version or alias (`production`, "
                                "...; default: latest).")
    operation: Literal["predict", "loops", "novelty"] = Field("predict", description="What to compute; 'novelty' "
                                                               "needs `y`.")


class BatchRequest(_Strict):
    """Many records, each answered or failed on its own."""

    requests: list[BatchItem] = Field(..., description=(
        f"Records to process in order, 1 to {B['max_batch']} by default (GPNARX_MAX_BATCH; more -> 413). Each "
        f"item is validated on its own: a malformed item is answered by a problem detail in its slot and never "
        f"loses the others."))


# ---------------------------------------------------------------------------------------- answers
class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [{
        "type": "https://gpnarx.dev/problems/invalid-request", "title": "Unprocessable Content", "status": 422,
        "detail": "mc_paths: 10000 exceeds the limit of 4096 Monte Carlo paths", "field": "mc_paths"}]})

    type: str = Field(..., description="URI naming the kind of problem.")
    title: str = Field(..., description="Short summary of the kind of problem.")
    status: int = Field(..., description="HTTP status code.")
    detail: str = Field(..., description="What was wrong with this request, naming the field and the limit.")
    field: str | None = Field(None, description="Dotted path of the offending request field (e.g. `u`, "
                                 "`mc_paths`, `requests.2.mc_paths`), null when no single field is to blame.")
    errors: list[dict[str, Any]] | None = Field(None, description="Every validation error found: "
                                                   "{field, message, type}.")


class Units(BaseModel):
    model_config = ConfigDict(extra="allow")
    u: str | None = Field(None, description="Input unit (e.g. N, V).")
    y: str | None = Field(None, description="Output unit (e.g. m, m/s).")


_DIVERGED_DESC = ("Monte Carlo paths whose sampled output left the training output envelope: peak |y| above 3x "
                  "the largest peak |y| of the training records. The linearised method reports 0 or 1 by the same "
                  "rule on its mean. Non-zero: the mean, band and summary numbers are extrapolations of the "
                  "kernel, not predictions the model stands behind.")
_OOR_DESC = ("What lies outside the model's knowledge: 'u' when the record's peak |u| exceeds 1.5x the largest "
             "training peak |u|, 'y' when the measured output's peak |y| exceeds 1.5x the training peak |y|, "
             "'prediction' when the predicted mean's does, 'frequency' when more than 10 % of the drive's power "
             "lies in frequency bands where it is over 2x stronger than the training inputs ever were (for "
             "novelty also: 'u'/'y' outside the healthy "
             "calibration records' peak range widened 2x each way, and 'probe' when the drive does not match the "
             "monitor's probe). Empty when everything lies inside. Non-empty: treat the answer as an "
             "extrapolation.")


class _Knowledge(BaseModel):
    start: Literal["rest", "measured", "state"] = Field("rest", description="How the free run started (see the "
                                                         "request's `start`): 'measured' from `y0` or `y`'s first "
                                                         "`ny` samples, 'rest' also when a 'measured' record's `y` "
                                                         "holds no more than `ny` samples, 'state' when it "
                                                         "continued a stream from the request's `state`.")
    state: str | None = Field(None, description="With `return_state`: the token of where this free run ended. "
                                                "Send it as the next chunk's `state` (docs/api.md, Streams).")
    stream_position: int | None = Field(None, description="With `state` or `return_state`: samples of the "
                                                          "stream consumed up to the end of this chunk.")
    diverged_paths: int = Field(0, description=_DIVERGED_DESC)
    out_of_range: list[Literal["u", "y", "prediction", "frequency", "probe"]] = Field(default_factory=list,
                                                                         description=_OOR_DESC)


class Gap(BaseModel):
    """One gap of a record: a run of null (missing) samples in `u` or `y`."""

    start: int = Field(..., description="First missing sample (index from 0).")
    end: int = Field(..., description="First sample after the gap (exclusive end).")
    start_s: float = Field(..., description="Start of the gap [s from the record's first sample].")
    end_s: float = Field(..., description="End of the gap [s].")


class PredictResponse(_Knowledge):
    model: str
    version: str
    mean: list[float | None] = Field(..., description="Free-run predicted mean, output units (null through a gap).")
    lower: list[float | None] = Field(..., description="Lower edge of the band at `confidence`.")
    upper: list[float | None] = Field(..., description="Upper edge of the band at `confidence`.")
    std: list[float | None] = Field(..., description="Predictive standard deviation, output units.")
    confidence: float
    mc_paths: int = Field(..., description="Monte Carlo paths used (0 for method 'linear').")
    method: Literal["mc", "linear"]
    backend: Literal["numpy", "jax"] = Field("numpy", description="The array backend that ran the free run.")
    seed: int
    n_samples: int
    units: Units
    fit: float | None = Field(None, description="Only when `y` was sent: fit % of eq. (14) (null when y is "
                                 "identically zero).")
    rmse: float | None = Field(None, description="Only when `y` was sent: RMSE, output units.")
    coverage: float | None = Field(None, description="Only when `y` was sent: % of measured samples inside "
                                      "[lower, upper].")
    horizon: int | None = Field(None, description="Only when `horizon` was sent: k of the k-step-ahead prediction "
                                "(samples between restarts from the measured outputs).")
    gaps: list[Gap] | None = Field(None, description="Only when the record holds gaps (null samples in u or y): "
                                   "each gap's samples and times; the answer is null through them.")


class Loop(BaseModel):
    x: list[float] = Field(..., description="Displacement [m].")
    force: list[float] = Field(..., description="Restoring force R = g u - m x'' [N].")
    area: float = Field(..., description="Area enclosed by the (x, R) trajectory [J] (shoelace formula).")


class Physics(BaseModel):
    model_config = ConfigDict(extra="allow")
    mass: float = Field(..., description="Mass [kg].")
    input_gain: float = Field(..., description="Force per input unit g (N/N or N/V).")
    output: Literal["displacement", "velocity"]


class Cycle(BaseModel):
    """One steady cycle of the record (see docs/api.md, per-cycle loops)."""

    start: float = Field(..., description="Start of the cycle [s from the record's first sample].")
    end: float = Field(..., description="End of the cycle [s].")
    energy: float | None = Field(..., description="Energy dissipated over the cycle by the predicted mean loop "
                                 "(loop area, integral of R dx) [`units.energy`, J].")
    energy_lower: float | None = Field(..., description="Lower end of the energy's interval at `confidence`: "
                                       "quantile of the per-path energies across the Monte Carlo paths; for "
                                       "method 'linear', w.mean - z sqrt(w' C w) with the linearised output "
                                       "covariance C over the cycle [J].")
    energy_upper: float | None = Field(..., description="Upper end of the energy's interval [J].")
    stiffness: float | None = Field(..., description="Secant stiffness of the predicted mean loop over the "
                                    "cycle, (R(x_max) - R(x_min)) / (x_max - x_min) [`units.stiffness`, N/m].")
    stiffness_lower: float | None = Field(None, description="Lower end of the secant stiffness across the Monte "
                                          "Carlo paths (null for 'linear'); wide when the model's noise is large, "
                                          "as R holds the second derivative of each path.")
    stiffness_upper: float | None = Field(None, description="Upper end of the secant stiffness across the paths.")
    measured_energy: float | None = Field(None, description="Only when `y` was sent: the measured loop's energy "
                                          "over the same cycle [J].")
    measured_stiffness: float | None = Field(None, description="Only when `y` was sent: the measured loop's "
                                             "secant stiffness [N/m].")


class CycleBasis(BaseModel):
    basis: Literal["drive", "response", "stream"] = Field(
        ..., description="'drive': cycles of a sine drive (zero crossings of the sine fitted to u at its dominant "
        "frequency); 'response': a broadband drive, cycles of the predicted displacement (upward zero "
        "crossings); 'stream': a call with `state` or `return_state`: the cycles completed by this chunk, each "
        "reported once across the stream, cut causally at upward zero crossings of the predicted mean output "
        "(docs/api.md, Streams).")
    frequency: float | None = Field(..., description="Dominant frequency of u [Hz] (null in a stream).")
    n_cycles: int = Field(..., description="Whole cycles found in the record (in a stream: in `cycles`).")
    steady_from: int = Field(..., description="Index of the first steady cycle among them; the earlier ones "
                             "(start-up of a free run from rest) are not in `cycles`.")


class LoopsResponse(_Knowledge):
    model: str
    version: str
    confidence: float
    mc_paths: int
    method: Literal["mc", "linear"]
    backend: Literal["numpy", "jax"] = Field("numpy", description="The array backend that ran the free run.")
    seed: int
    n_samples: int
    physics: Physics
    units: dict[str, str] = Field(..., description="Units of `x`, `force` (N: g converts the input), `energy` "
                                  "and `stiffness`, from the bundle's output unit.")
    predicted: Loop = Field(..., description="Loop of the predicted mean response.")
    lower: Loop = Field(..., description="Loop of the lower band edge (not a confidence statement about the "
                        "loop: see `cycles` for intervals).")
    upper: Loop = Field(..., description="Loop of the upper band edge.")
    measured: Loop | None = Field(None, description="Only when `y` was sent: loop of the measured response.")
    cycles: list[Cycle] = Field(default_factory=list, description="One entry per steady cycle: dissipated "
                                "energy and secant stiffness of the predicted loop with intervals across the "
                                "Monte Carlo paths (or the linearised equivalent), and the measured loop's when "
                                "`y` was sent.")
    cycle_basis: CycleBasis | None = Field(None, description="How the record was cut into cycles.")


class Drive(BaseModel):
    kind: Literal["sine", "broadband"] = Field(..., description="'sine' when at least 80 % of u's power lies at "
                                               "its dominant frequency, else 'broadband'.")
    frequency: float | None = Field(..., description="Dominant frequency of u [Hz].")
    amplitude: float = Field(..., description="Sine: peak of the sine fitted at the dominant frequency; "
                             "broadband: RMS of u [input unit].")
    amplitude_kind: Literal["peak", "rms"]


class Probe(BaseModel):
    """The excitation a monitor's novelty threshold was calibrated for (from its healthy records)."""

    model_config = ConfigDict(extra="allow")
    kind: Literal["sine", "broadband"]
    frequency: float | None = Field(..., description="Probe frequency [Hz]: median dominant frequency of the "
                                    "healthy records.")
    frequency_tolerance: float | None = Field(..., description="A sine request whose dominant frequency is "
                                              "further off [Hz] does not match (at least 3 % of the frequency, "
                                              "the healthy records' spread and 0.5 / the request's duration).")
    amplitude: list[float] = Field(..., description="[min, max] amplitude of the healthy records [input unit]: "
                                   "sine peak or broadband RMS (`amplitude_kind`).")
    amplitude_kind: Literal["peak", "rms"]
    amplitude_tolerance: float = Field(..., description="Relative widening of the amplitude range each way.")
    start: Literal["rest", "measured"] = Field(..., description="Start rule of the free run the threshold was "
                                               "calibrated with.")
    n_records: int


class NoveltyWindow(BaseModel):
    """The rolling window of a novelty stream: its last samples scored together, carried in the state token."""

    chunks: int = Field(..., description="Chunks with samples in the window.")
    samples: int = Field(..., description="Samples in the window (at most 8 s of the stream).")
    seconds: float = Field(..., description="Length of the window [s].")
    score: float = Field(..., description="The score of the window's samples, as a record's.")
    threshold: float
    verdict: Literal["healthy", "novel", "unjudged"]


class NoveltyResponse(_Knowledge):
    model: str
    version: str
    score: float | None = Field(..., description="RMS standardised residual of y under the predictive distribution "
                                "(about 1 for a healthy record); with score_method 'segment_median_rms', the median "
                                "of that RMS over 16 contiguous segments (robust to isolated spikes). Null only "
                                "beyond the double range (a y some 1e308 predictive std from the mean).")
    score_method: Literal["rms_standardised_residual", "segment_median_rms"] = Field(
        "rms_standardised_residual", description="How the score was computed: the bundle's calibrated method, "
        "so score and threshold are always comparable.")
    threshold: float = Field(..., description="Score above which the record is 'novel'.")
    verdict: Literal["healthy", "novel", "unjudged"] = Field(
        ..., description="'unjudged' when the drive does not match the monitor's probe ('probe' in out_of_range, "
        "`probe_match` false, `probe_reasons` say why): the score is kept but not compared with the threshold, "
        "and the verdict is neither healthy nor an alarm. Else 'novel' when the record left the calibration "
        "envelope ('u' or 'y' in out_of_range) or score > threshold; else 'healthy'.")
    probe_match: bool | None = Field(None, description="Whether the request's drive (and start rule) matches the "
                                     "probe the threshold was calibrated for (the model's `probe`); null when "
                                     "the bundle states no probe.")
    probe_reasons: list[str] = Field(default_factory=list, description="Why the drive does not match the probe "
                                     "(empty when it does).")
    drive: Drive | None = Field(None, description="The request's drive as estimated from `u`.")
    false_alarm_rate: float | None = Field(..., description="False-alarm rate the threshold was calibrated for "
                                              "(null if the calibration does not say).")
    nlpd: float | None = Field(..., description="Mean negative log predictive density; null when it exceeds the "
                               "double range (a y more than about 1e154 predictive std from the mean, where the "
                               "score is still a number).")
    n_samples: int = Field(..., description="Samples that entered the score.")
    novelty_window: NoveltyWindow | None = Field(
        None, description="With `state` or `return_state`: the verdict over the stream's last 8 s (this chunk "
        "and the earlier ones the state token carries), scored like a record.")
    confidence: float = Field(..., description="Band level of the free run the score was computed from (the "
                              "request's `confidence`).")
    mc_paths: int
    method: Literal["mc", "linear"]
    backend: Literal["numpy", "jax"] = Field("numpy", description="The array backend that ran the free run.")
    seed: int


class BatchResponse(BaseModel):
    results: list[PredictResponse | LoopsResponse | NoveltyResponse | Problem] = Field(
        ..., description="One entry per request, in order: that operation's answer or a problem detail.")


class Lags(BaseModel):
    ny: int
    nu: int


class ModelSummary(BaseModel):
    name: str
    versions: list[str]
    latest: str
    fs: float
    units: Units
    lags: Lags
    novelty: bool = Field(..., description="Whether the latest version has a novelty calibration.")


class ModelList(BaseModel):
    models: list[ModelSummary]


class ModelDetail(BaseModel):
    name: str
    version: str
    versions: list[str]
    aliases: dict[str, str] = Field({}, description="Alias -> version: `latest` (the newest version) and the "
                                    "aliases an operator set (`gpnarx alias set`) whose version is served. Any "
                                    "alias can stand for a version in a path or a batch record.")
    created: str | None = None
    lags: Lags
    mode: str
    fs: float
    units: Units
    kernel: dict[str, Any]
    hyperparameters: dict[str, Any]
    noise_calibration: dict[str, Any] | None = Field(
        None, description="Held-out calibration of the noise variance (method, n_records, n_residuals, "
                          "noise_var_ml2, noise_var, residual_var, latent_var_mean; standardised output "
                          "units) or null when the bundle keeps ML-II's value.")
    band_discrepancy: dict[str, Any] | None = Field(
        None, description="The free-run band's model-discrepancy term (method, scale: fraction of the local "
                          "amplitude, window [samples], window_kind, hold [samples], gp_scale: the factor on the "
                          "propagated band (1 when absent), target, reached, records, coverage_before, "
                          "coverage_after) or null when the band is eq. 9's alone.")
    default_method: dict[str, Literal["mc", "linear"]] = Field(
        ..., description="The propagation each operation (predict, loops, novelty) uses when a request names no "
                         "`method`.")
    default_mc_paths: dict[str, int] = Field(
        ..., description="The Monte Carlo paths each operation (predict, loops, novelty) uses when a request names "
                         "no `mc_paths`: the trained config's `[predict] mc_paths` (novelty: the paths its "
                         "threshold was calibrated with), as the CLI uses; GPNARX_MC_PATHS_DEFAULT overrides it "
                         "when set.")
    n_train: int | None = None
    training: dict[str, Any] = Field(..., description="Training metrics.")
    novelty: dict[str, Any] | None = Field(None, description="Novelty calibration (threshold, "
                                              "false_alarm_rate, n_healthy, ...) or null.")
    probe: Probe | None = Field(None, description="The probe contract of the novelty calibration: the excitation "
                                "(kind, frequency [Hz], amplitude range [input unit], start rule) the threshold "
                                "holds for; null when the model has no novelty calibration or was calibrated "
                                "before probe contracts existed.")
    physics: dict[str, Any] = Field(..., description="Physical constants for restoring force.")
    package_versions: dict[str, Any] = {}


class RefusedBundle(BaseModel):
    path: str = Field(..., description="NAME/VERSION inside the registry.")
    reason: str


class Live(BaseModel):
    status: Literal["alive"]


class StartupStatus(BaseModel):
    """Bundles the server is still building at start-up (``gpnarx serve`` without ``--registry``
    builds the missing default bundles in the background, one at a time, lightest first)."""

    built: list[str] = Field(..., description="Loaded and served: present at start or built since.")
    building: list[str] = Field(..., description="Being built now (at most one).")
    pending: list[str] = Field(..., description="Waiting to be built, in build order.")
    failed: list[str] = Field(..., description="Builds that failed (reason in `reasons`); the others are served.")
    skipped: list[str] = Field(default_factory=list, description="Not built (reason in `reasons`), e.g. the real "
                               "BERT bundle without its lab records.")
    reasons: dict[str, str] = Field(default_factory=dict, description="Why each failed or skipped bundle was "
                                    "not built.")
    done: bool = Field(..., description="True when nothing is building or pending.")


class RegistryHeld(BaseModel):
    """A registry scan that dropped every served version, or more than ``GPNARX_REGISTRY_DROP_SHARE``
    of them, held back: the last good registry keeps serving until the same listing is seen on
    ``GPNARX_REGISTRY_CONFIRM_SCANS`` consecutive scans or ``POST /v1/admin/reload?accept_removal=true``."""

    detail: str
    served: int = Field(description="Versions the served registry lists")
    listed: int = Field(description="Versions the held scan lists")
    dropped: list[str] = Field(description="`NAME:VERSION` the held scan drops (at most 50)")
    scans: int = Field(description="Consecutive scans that showed the held listing")
    needed: int = Field(description="Consecutive scans needed to serve it (GPNARX_REGISTRY_CONFIRM_SCANS)")


class AuditStatus(BaseModel):
    target: str = Field(..., description="`stdout`, `off`, the file or the fsspec URL (without credentials) of "
                        "GPNARX_AUDIT_LOG.")
    ok: bool = Field(..., description="Whether the last write to the target succeeded (true before any write).")
    written: int = Field(..., description="Audit lines written since the start.")
    failed: int = Field(..., description="Audit lines lost to failed writes (unwritable or full target).")
    dropped: int = Field(..., description="Audit lines dropped because GPNARX_AUDIT_QUEUE lines were waiting.")
    lost: int = Field(0, description="Audit lines accepted but not in the trail: `failed` + `dropped`.")
    torn: int = Field(0, description="Fragments of failed writes that could not be cut off from the file: each "
                      "ended by a newline, alone on its line (every other line parses).")
    reopened: int = Field(0, description="Times the trail's file was reopened: deleted or renamed (rotated) "
                          "under the server, on SIGHUP, or after a failed write (by reason in `reopens`).")
    reopens: dict[str, int] = Field(default_factory=dict, description="`reopened` by reason: `deleted`, "
                                    "`rotated`, `signal`, `error`.")
    queued: int = Field(..., description="Audit lines waiting to be written.")
    last_error: str | None = Field(None, description="The last failed write's error.")
    last_error_time: str | None = Field(None, description="When it failed (UTC, ISO 8601).")


class Ready(BaseModel):
    status: Literal["ready"]
    bundles: int
    refused_count: int = Field(..., description="Versions refused (bad checksum, unreadable, ...).")
    models: dict[str, list[str]] | None = Field(None, description="Served versions of each model; absent for a "
                                                "caller without the key when GPNARX_API_KEY is set (as every "
                                                "member below).")
    refused: list[RefusedBundle] | None = Field(None, description="The refused versions and why.")
    registry_held: RegistryHeld | None = Field(None, description="Only while a registry scan that dropped too "
                                               "many versions is held back (the service stays ready).")
    startup: StartupStatus | None = Field(None, description="Only while or after the server builds its default "
                                          "bundles (`gpnarx serve` without `--registry`); also in the 503 answer.")
    audit: AuditStatus | None = Field(None, description="The audit trail's target and counts: a failing target "
                                      "shows here (`ok` false) without failing readiness; also in the 503 answer.")


class ReloadResponse(BaseModel):
    bundles: int
    models: dict[str, list[str]]
    refused: list[RefusedBundle]
    added: list[str]
    removed: list[str]
    held: RegistryHeld | None = Field(None, description="Only when the scan was held back: what is still served is "
                                      "listed above")
