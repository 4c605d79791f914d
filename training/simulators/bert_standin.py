"""BERT STAND-IN: a documented single-mode hysteretic model of the UNESP-BERT bolted beam.

This is a *stand-in*, not the rig. The real BERT subset in ``../shared/data/bert-t5nm`` holds only
steady sines near 0.15 V and one white-noise run at 5 N m, not the paper's swept sines, other torques
or 50 realizations. The stand-in lets the whole section-4 protocol and the bolt-loosening use case
run end to end. Never present its numbers as the rig's.

Model (per unit modal mass; x = free-end displacement of the first mode [m])::

    x'' + 2 zeta_v w1 x' + w1^2 [ (1 - sum r_i) x + sum r_i z_i ] + c_e ln(1 + (x/x_e)^2) = g u(t)

- ``u``: shaker amplifier voltage [V]; ``g`` [m/s^2 per V] is the modal force per volt divided by the
  modal mass (``input_gain / modal_mass``).
- ``w1 = 2 pi f_stuck``: first-mode frequency with the joint fully stuck (zero amplitude).
- ``z_i`` (i = 1..4): Bouc-Wen elements (nu = 1, A = 1, beta = gamma = 1 / (2 s_i)),
  ``dz/dx = 1 - (beta sgn(x' z) + gamma) |z|``: elastic (slope 1) on unloading, saturating at the slip
  displacement ``s_i`` on loading (a Masing-like friction slider). Four elements with slip
  displacements spread over 0.02-6 mm and stiffness fractions ``r_i`` (5 % of the stiffness in total)
  give the softening backbone measured on the rig: the free-decay frequency falls about
  logarithmically with amplitude, from 18.91 Hz at 0.02 mm to 18.58 Hz at 9.5 mm, while the decay
  damping stays near 0.5 % (half viscous, half friction).
- ``c_e ln(1 + (x/x_e)^2)``: an even (asymmetric) joint-contact term. It grows like ``x^2`` below
  ``x_e`` (0.32 mm) and only logarithmically above, so it gives the strong second super-harmonic the
  rig shows at 0.5-0.6 mm (drive near half the resonance, 9-9.75 Hz) without distorting the
  large-amplitude response (the rig's 2x content at 17-20 Hz is below 0.5 %).
- A second, linear bending mode (97.3 Hz, 1.4 % damping, negative participation ``g2``) is added to
  the velocity and displacement outputs; it was fitted to the rig's random-excitation FRF and is what
  makes the response per volt below the first resonance match (5-10 Hz).

Integration: RK4 with ``substeps`` steps per sample (default: 4 at 1024 Hz, i.e. 4096 Hz), input
linearly interpolated between samples (first-order hold). The hysteretic variables are advanced with
the exact solution of the (rate-independent) Bouc-Wen law for the displacement increment of each RK
stage, which removes the stiffness of the sharp small-slip elements; the linear second mode is
integrated exactly (first-order-hold discretisation, ``scipy.signal.lfilter``). 16384 samples take
about 0.3 s in plain Python floats.

Calibration (5 N m, the nominal parameters, ``seed=None``) against the real records; run
:func:`calibration_table` to recompute it from the data:

- first resonance: low-amplitude noise FRF peak (0.00265 V RMS over 0-110 Hz, like ``Rand0p25``;
  :func:`resonance_from_noise`) at 18.78-18.86 Hz over noise seeds (rig: 18.75 Hz from the LMS FRF
  ``FRF_Laser__X_Shaker__X``, 18.85 Hz in the free decays at 0.05 mm). Softening: at 0.3 V RMS the
  peak moves to about 18.53 Hz. Zero-amplitude (joint stuck) frequency: 18.95 Hz.
- FRF magnitude at the rig's noise level, against the rig's LMS FRF: within 12 % over 3-15 Hz and
  20-95 Hz (0.101 vs 0.103 (m/s)/V at 5 Hz, 3.44 vs 3.33 at 20 Hz, 5.77 vs 5.84 at 95 Hz), 17-25 %
  low at 17-18 Hz: the noise run was recorded four days after the sine runs and its resonance sits
  slightly lower; the stand-in follows the sine runs (its gain is 5 % below a fit to the noise FRF).
- steady-state velocity amplitude of the fundamental at 0.149 V peak, 13 frequencies 5-20 Hz:
  within 5 % of the rig (19 Hz: +5 %, 20 Hz: -4 %, others within 2 %).
- super-harmonics: the second super-harmonic (2x drive, around the first resonance) is reproduced in
  level and shape: 2x/1x velocity ratio about 0.04-0.05 at 5-6.75 Hz, 0.09 at 8 Hz, 0.14 at 8.5 Hz,
  0.32 at 9 Hz, 0.69 at 9.5 Hz, 0.29 at 9.75 Hz (rig: 0.03-0.05, 0.09, 0.14, 0.33, 0.71, 0.27).
  The third super-harmonic (3x drive near resonance, 6-6.75 Hz) is present but about half the rig's
  (0.027 vs 0.053 at 6 Hz, 0.026 vs 0.054 at 6.5 Hz, 0.012 vs 0.031 at 6.75 Hz).

With the torque law below, the low-amplitude noise resonance is about 18.8 / 19.0 / 19.1 Hz at
5 / 7 / 9 N m, and 18.55 / 18.74 / 18.78 Hz at 0.3 V RMS.

Torque dependence (an assumption, NOT calibrated: only 5 N m records exist here). Clamping force,
hence the friction limit of each slip element, is taken proportional to the tightening torque ``T``:
``s_i(T) = s_i (T / 5 N m)``; the stuck-joint frequency grows slightly with contact pressure,
``f_stuck(T) = f_stuck (T / 5)^0.02``; the even contact term scales as ``5 / T``. So a higher torque
is stiffer, slips less and is more linear; *loosening is a decrease of torque*: e.g. a model trained
on the healthy (tight) 9 N m stand-in should flag records of the 7 N m or 5 N m stand-in as novel
(lower resonance, stronger amplitude-dependent softening, friction damping and super-harmonics).

Realizations (``seed`` given): each realization draws its parameters around the nominal ones
(log-normal), with the relative standard deviations of :data:`REALIZATION_SD` times ``scatter``
(default 1): stuck frequency 0.04 % (stiffness 0.08 %), slip displacements (friction), stiffness
fractions and viscous damping 0.5 %, gain 0.2 %, even term 1 %. ``seed=None`` gives the nominal
parameters.

Why so small (calibration of the scatter). Only one quantitative statement bounds the
rig's realization-to-realization repeatability of a swept-sine *time history*: the paper's lag
surface, whose chosen lags predict a held-out 0.10 V realization at 96.1 % fit (eq. 14, Fig. 14).
No predictor can beat the true system's own scatter, so the scatter must let the nominal system
predict its realizations at about that level. Over 24 realizations of the 0.10 V sweep, the median
fit of the nominal stand-in to a realization is 96.4 % at ``scatter=1`` (p10 90.6 %). A 10x
larger scatter (``scatter=10``: stuck frequency 0.4 %, the order of the day-to-day scatter of the
rig's FRFs, Fig. 13) gives a median of 66.0 % (p10 22.6 %): an exact copy of the stand-in's own
equations, or the ensemble mean of 40 realizations (median 70.4 %), cannot reach the paper's
figure, so that scatter contradicts the paper. The resonance frequency is what matters: a lightly
damped mode swept at 5 Hz/s rings after resonance, and a 0.3 % frequency error alone costs about
40 points of fit. Evidence the other way: the rig's noise run, recorded four days after its sine runs,
sits slightly lower in frequency (see the FRF calibration above), so day-to-day drift of the order of
0.1-0.5 % exists; ``scatter`` lets a user study that regime (``gpnarx simulate ... --scatter 10``).
"""
from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import signal

from gpnarx.storage.record_files import read_record
from gpnarx.training.datapaths import bert_data_dir
from gpnarx.training.excitations import band_limited_noise

__all__ = [
    "BertStandin",
    "StandinParams",
    "NOMINAL",
    "REALIZATION_SD",
    "STANDIN_FS",
    "steady_amplitude",
    "steady_response",
    "noise_frf",
    "resonance_from_noise",
    "harmonic_amplitudes",
    "real_sine_amplitudes",
    "calibration_table",
    "format_calibration_table",
]

STANDIN_FS = 1024.0  # Hz, like the LMS SCADAS acquisition of the rig

#: relative standard deviations [-] of one realization's parameters at ``scatter=1`` (log-normal);
#: see "Why so small" in the module docstring
REALIZATION_SD = {"f_stuck": 0.0004, "slip": 0.005, "r": 0.005, "zeta_v": 0.005, "gain": 0.002, "c_even": 0.01}
NOMINAL_TORQUE = 5.0  # N m, the torque of the real records


@dataclass(frozen=True)
class StandinParams:
    """Parameters of the BERT stand-in (see the module docstring for the equation).

    f_stuck [Hz]: first-mode frequency with the joint stuck; zeta_v [-]: viscous damping ratio;
    r [-]: stiffness fraction of each of the 4 Bouc-Wen slip elements; slip [m]: their slip
    displacements; gain [m/s^2 per V]: modal force per volt / modal mass; c_even [m/s^2] and
    x_even [m]: even contact term ``c_even ln(1 + (x/x_even)^2)``; f2 [Hz], zeta2 [-], g2 [m/s^2 per V]:
    linear second mode; modal_mass [kg]: modal mass used to express forces in N (assumed: a quarter
    of the 0.235 kg of the two beams, the tip-referenced first-mode mass of a cantilever).
    """

    f_stuck: float = 18.9464
    zeta_v: float = 0.00246
    r: tuple = (0.01456, 0.00698, 0.01237, 0.01360)
    slip: tuple = (0.02e-3, 0.15e-3, 1.0e-3, 6.0e-3)
    gain: float = 48.0
    c_even: float = 0.13
    x_even: float = 0.32e-3
    f2: float = 97.26
    zeta2: float = 0.0138
    g2: float = -194.5
    modal_mass: float = 0.06

    @property
    def input_gain(self) -> float:
        """Modal force per volt [N/V] (``gain * modal_mass``)."""
        return self.gain * self.modal_mass


NOMINAL = StandinParams()


def _bounded(value, name: str, lo: float, hi: float, kind: str, suffix: str) -> float:
    """``value`` as a float in [lo, hi], else a ValueError naming ``name`` and the limits."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number {kind}, got {value!r}") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise ValueError(f"{name} must be between {lo:g} and {hi:g}{suffix}, got {v}")
    return v


def _check_signal(u, label="u") -> np.ndarray:
    a = np.asarray(u, dtype=np.float64)
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{label} must be a non-empty 1-D array of voltages [V], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{label} holds NaN/inf values")
    return a


class BertStandin:
    """BERT stand-in simulator (shaker voltage [V] -> free-end velocity [m/s], displacement [m]).

    torque: tightening torque [N m] (> 0; 5 is the torque of the real records, 7 and 9 are the
    tighter states of the protocol; see the module docstring for the assumed law).
    seed: ``None`` for the nominal (calibrated) parameters, or an int/SeedSequence to draw one
    realization (small scatter of stiffness, friction, damping, gain: :data:`REALIZATION_SD`).
    scatter: multiplier [-] of the realization standard deviations (>= 0; 1 is the calibrated
    default, 10 the order of the rig's day-to-day FRF scatter; see the module docstring). Ignored when ``seed`` is None.
    substeps: RK4 steps per sample (default: enough for a 4096 Hz internal rate).
    """

    fs = STANDIN_FS
    units = {"u": "V", "y": "m/s", "x": "m", "z": "N"}

    def __init__(self, torque: float = NOMINAL_TORQUE, seed=None, substeps: int | None = None,
                 params: StandinParams | None = None, scatter: float = 1.0):
        torque = _bounded(torque, "torque", 0.5, 50.0, "in N m", " N m")
        if substeps is not None and (isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1):
            raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
        scatter = _bounded(scatter, "scatter", 0.0, 100.0, "(multiplier of the realization scatter)",
                           " (1 = calibrated default)")
        self.torque = torque
        self.seed = seed
        self.scatter = scatter
        self.substeps = None if substeps is None else int(substeps)
        base = params if params is not None else NOMINAL
        if len(base.r) != 4 or len(base.slip) != 4:
            raise ValueError("the stand-in has exactly 4 slip elements (r and slip of length 4)")
        self.nominal_params = base
        self.params = self._realize(self._at_torque(base, torque), seed, scatter)

    # ------------------------------------------------------------------ parameters
    @staticmethod
    def _at_torque(p: StandinParams, torque: float) -> StandinParams:
        ratio = torque / NOMINAL_TORQUE
        return replace(
            p,
            f_stuck=p.f_stuck * ratio ** 0.02,
            slip=tuple(s * ratio for s in p.slip),
            c_even=p.c_even / ratio,
        )

    @staticmethod
    def _realize(p: StandinParams, seed, scatter: float = 1.0) -> StandinParams:
        if seed is None:
            return p
        rng = np.random.default_rng(seed)
        sd = {k: v * scatter for k, v in REALIZATION_SD.items()}

        def lognorm(name, size=None):
            return np.exp(sd[name] * rng.standard_normal(size))

        # draw order fixed (f_stuck, slip, r, zeta_v, gain, c_even): a seed gives the same
        # standard normals at every scatter, so realizations are comparable across scatters
        return replace(
            p,
            f_stuck=p.f_stuck * float(lognorm("f_stuck")),
            slip=tuple(float(v) for v in np.asarray(p.slip) * lognorm("slip", 4)),
            r=tuple(float(v) for v in np.asarray(p.r) * lognorm("r", 4)),
            zeta_v=p.zeta_v * float(lognorm("zeta_v")),
            gain=p.gain * float(lognorm("gain")),
            c_even=p.c_even * float(lognorm("c_even")),
        )

    @property
    def modal_mass(self) -> float:
        """Modal mass [kg] used for forces in N (restoring force R = input_gain * u - modal_mass * acc)."""
        return self.params.modal_mass

    @property
    def input_gain(self) -> float:
        """Modal force per volt [N/V]."""
        return self.params.input_gain

    @property
    def linear_resonance(self) -> float:
        """Zero-amplitude (joint stuck) undamped first-mode frequency [Hz]."""
        return self.params.f_stuck

    def describe(self) -> dict:
        """Parameters as a plain dict (for reports and bundle metadata)."""
        d = asdict(self.params)
        seed = self.seed if isinstance(self.seed, (int, type(None))) else str(self.seed)
        d.update(torque=self.torque, scatter=self.scatter, seed=seed, input_gain=self.input_gain, kind="bert-standin")
        return d

    # ------------------------------------------------------------------ simulation
    def simulate(self, u, fs: float = STANDIN_FS, callback=None) -> dict:
        """Simulate the stand-in from rest for the shaker voltage samples ``u`` [V] at ``fs`` [Hz].

        Returns ``dict(y=free-end velocity [m/s], x=free-end displacement [m], z=hysteretic (slip
        element) force [N], u=input [V], fs=fs)``. ``callback(k)``, if given, is called as k more
        samples are done (progress bars).
        """
        u = _check_signal(u)
        fs = float(fs)
        if not math.isfinite(fs) or fs <= 0:
            raise ValueError(f"fs must be a positive frequency in Hz, got {fs}")
        p = self.params
        sub = self.substeps or max(1, math.ceil(4096.0 / fs - 1e-9))
        x1, v1, zf = _integrate_mode1(u, fs, sub, p, callback)
        q, qd = _mode2(u, fs, p)
        return {"y": v1 + qd, "x": x1 + q, "z": zf * p.modal_mass, "u": u, "fs": fs}

    # ------------------------------------------------------------------ helpers
    def steady_response(self, freq: float, volts: float, fs: float = STANDIN_FS, settle: float = 8.0,
                        measure: float = 2.0, n_harmonics: int = 3) -> dict:
        """Steady-state response to ``volts * sin(2 pi freq t)``.

        Simulates ``settle + measure`` seconds from rest (8 s is about 5 decay time constants of
        the first mode) and fits the last ``measure`` seconds by least squares with a constant and
        ``n_harmonics`` harmonics of ``freq``. Returns ``dict(velocity=[amplitude of harmonic k,
        k = 1..n] m/s, displacement=[...] m, freq, volts)``.
        """
        freq = float(freq)
        if not math.isfinite(freq) or freq <= 0 or freq * n_harmonics >= fs / 2:
            raise ValueError(f"freq must be positive and its {n_harmonics} harmonics below fs/2, got {freq}")
        n = int(round((settle + measure) * fs))
        m = int(round(measure * fs))
        t = np.arange(n) / fs
        out = self.simulate(float(volts) * np.sin(2.0 * np.pi * freq * t), fs)
        return {
            "velocity": harmonic_amplitudes(out["y"][-m:], freq, fs, n_harmonics).tolist(),
            "displacement": harmonic_amplitudes(out["x"][-m:], freq, fs, n_harmonics).tolist(),
            "freq": freq,
            "volts": float(volts),
        }

    def steady_amplitude(self, freq: float, volts: float, **kw) -> float:
        """Steady-state velocity amplitude [m/s] of the fundamental for a ``volts`` [V] peak sine."""
        return float(self.steady_response(freq, volts, **kw)["velocity"][0])


# ============================================================================ integration kernels
def _integrate_mode1(u: np.ndarray, fs: float, sub: int, p: StandinParams, callback=None):
    """RK4 of the hysteretic first mode; returns displacement, velocity, hysteretic force / mass."""
    w1 = 2.0 * math.pi * p.f_stuck
    w1s = w1 * w1
    k0 = w1s * (1.0 - sum(p.r))
    k1, k2, k3, k4 = (w1s * r for r in p.r)
    s1, s2, s3, s4 = p.slip
    i1, i2, i3, i4 = (1.0 / s for s in p.slip)
    cz = 2.0 * p.zeta_v * w1
    g = p.gain
    ce = p.c_even
    ixe = 1.0 / p.x_even
    exp = math.exp
    log1p = math.log1p
    h = 1.0 / (fs * sub)
    h2 = 0.5 * h
    h6 = h / 6.0
    n = u.size
    uu = u.tolist()
    uu.append(uu[-1])
    X = [0.0] * n
    V = [0.0] * n
    Z = [0.0] * n
    x = v = 0.0
    z1 = z2 = z3 = z4 = 0.0

    def phi(z0, d, s, inv):
        # exact Bouc-Wen (nu=1, beta=gamma=1/(2s)) update of z for a displacement increment d
        if d > 0.0:
            w = z0
            xi = d
        else:
            w = -z0
            xi = -d
        if w < 0.0:  # unloading: elastic (slope 1) until z crosses 0
            if xi <= -w:
                w += xi
                return w if d > 0.0 else -w
            xi += w
            w = 0.0
        w = s + (w - s) * exp(-xi * inv)  # loading: saturates at the slip displacement s
        return w if d > 0.0 else -w

    def acc(xs, vs, us, x0):
        d = xs - x0
        if d != 0.0:
            f = k1 * phi(z1, d, s1, i1) + k2 * phi(z2, d, s2, i2) + k3 * phi(z3, d, s3, i3) + k4 * phi(z4, d, s4, i4)
        else:
            f = k1 * z1 + k2 * z2 + k3 * z3 + k4 * z4
        q = xs * ixe
        return g * us - cz * vs - k0 * xs - f - ce * log1p(q * q)

    report = max(1, n // 100)
    for i in range(n):
        X[i] = x
        V[i] = v
        Z[i] = k1 * z1 + k2 * z2 + k3 * z3 + k4 * z4
        ua = uu[i]
        du = (uu[i + 1] - ua) / sub
        for j in range(sub):
            u0 = ua + du * j
            um = u0 + 0.5 * du
            a1 = acc(x, v, u0, x)
            xb = x + h2 * v
            vb = v + h2 * a1
            a2 = acc(xb, vb, um, x)
            xc = x + h2 * vb
            vc = v + h2 * a2
            a3 = acc(xc, vc, um, x)
            xd = x + h * vc
            vd = v + h * a3
            a4 = acc(xd, vd, u0 + du, x)
            xn = x + h6 * (v + 2.0 * vb + 2.0 * vc + vd)
            v = v + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            d = xn - x
            if d != 0.0:
                z1 = phi(z1, d, s1, i1)
                z2 = phi(z2, d, s2, i2)
                z3 = phi(z3, d, s3, i3)
                z4 = phi(z4, d, s4, i4)
            x = xn
        if callback is not None and (i + 1) % report == 0:
            callback(report)
    if callback is not None and n % report:
        callback(n % report)
    return np.array(X), np.array(V), np.array(Z)


def _mode2(u: np.ndarray, fs: float, p: StandinParams):
    """Linear second mode, exact first-order-hold discretisation: displacement and velocity."""
    w2 = 2.0 * math.pi * p.f2
    a = np.array([[0.0, 1.0], [-w2 * w2, -2.0 * p.zeta2 * w2]])
    b = np.array([[0.0], [p.g2]])
    c = np.eye(2)
    d = np.zeros((2, 1))
    ad, bd, cd, dd, _ = signal.cont2discrete((a, b, c, d), 1.0 / fs, method="foh")
    num, den = signal.ss2tf(ad, bd, cd, dd)
    return signal.lfilter(num[0], den, u), signal.lfilter(num[1], den, u)


# ============================================================================ analysis helpers
def harmonic_amplitudes(x, freq: float, fs: float, n_harmonics: int = 3) -> np.ndarray:
    """Amplitudes of harmonics 1..n of ``freq`` [Hz] in ``x`` (joint least-squares fit with a constant)."""
    x = np.asarray(x, dtype=np.float64)
    t = np.arange(x.size) / fs
    cols = [np.ones_like(t)]
    for k in range(1, n_harmonics + 1):
        cols += [np.cos(2 * np.pi * k * freq * t), np.sin(2 * np.pi * k * freq * t)]
    coef = np.linalg.lstsq(np.array(cols).T, x, rcond=None)[0]
    return np.hypot(coef[1::2], coef[2::2])


def steady_amplitude(freq: float, volts: float, torque: float = NOMINAL_TORQUE, seed=None, **kw) -> float:
    """Steady-state fundamental velocity amplitude [m/s] of the stand-in for a ``volts`` [V] peak sine."""
    return BertStandin(torque=torque, seed=seed).steady_amplitude(freq, volts, **kw)


def steady_response(freq: float, volts: float, torque: float = NOMINAL_TORQUE, seed=None, **kw) -> dict:
    """See :meth:`BertStandin.steady_response`."""
    return BertStandin(torque=torque, seed=seed).steady_response(freq, volts, **kw)


def noise_frf(model: BertStandin | None = None, rms: float = 0.00265, duration: float = 32.0,
              f_band=(0.0, 110.0), seed=0, fs: float = STANDIN_FS, nperseg: int = 8192):
    """H1 FRF estimate (velocity per volt, (m/s)/V) of the stand-in under band-limited white noise.

    Default level: 0.00265 V RMS over 0-110 Hz, the level of the rig's ``Rand0p25`` run.
    Returns ``(f [Hz], H complex)``.
    """
    model = model or BertStandin()
    u = band_limited_noise(fs, duration, f_band[0], f_band[1], rms, seed=seed)
    y = model.simulate(u, fs)["y"]
    f, puy = signal.csd(u, y, fs, nperseg=nperseg)
    _, puu = signal.welch(u, fs, nperseg=nperseg)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(puu > 0, puy / puu, 0.0)
    return f, h


def resonance_from_noise(model: BertStandin | None = None, band=(10.0, 30.0), **kw) -> float:
    """First resonance [Hz] of the stand-in: peak of :func:`noise_frf` in ``band``, refined by a
    parabola through the three bins around the maximum of |H|."""
    f, h = noise_frf(model, **kw)
    sel = np.nonzero((f >= band[0]) & (f <= band[1]))[0]
    i = sel[np.argmax(np.abs(h[sel]))]
    a, b, c = np.abs(h[i - 1 : i + 2])
    den = a - 2 * b + c
    off = 0.5 * (a - c) / den if den != 0 else 0.0
    return float(f[i] + off * (f[1] - f[0]))


# ============================================================================ calibration against the rig
_SINE_DIR = re.compile(r"Sine_(\d+)(?:p(\d+))?Hz$")


def _bert_data_dir(data_dir=None) -> Path:
    return Path(data_dir) if data_dir is not None else bert_data_dir()


def _drive_frequency(u: np.ndarray, fs: float, nominal: float | None) -> float:
    """Drive frequency [Hz]: FFT peak of u, refined from the phase drift between the two halves.

    The nominal frequency (from the folder name) is kept when the estimate agrees within 5 mHz.
    """
    n = u.size
    spec = np.abs(np.fft.rfft(u * np.hanning(n)))
    f = np.fft.rfftfreq(n, 1.0 / fs)
    f0 = float(f[np.argmax(spec[1:]) + 1])
    half = n // 2
    t = np.arange(half) / fs
    phases = []
    for seg in (u[:half], u[half : 2 * half]):
        c = np.linalg.lstsq(np.column_stack([np.cos(2 * np.pi * f0 * t), np.sin(2 * np.pi * f0 * t),
                                             np.ones(half)]), seg, rcond=None)[0]
        phases.append(math.atan2(-c[1], c[0]))
    dphi = (phases[1] - phases[0] - 2 * math.pi * f0 * half / fs + math.pi) % (2 * math.pi) - math.pi
    est = f0 + dphi / (2 * math.pi * half / fs)
    return float(nominal) if nominal is not None and abs(est - nominal) < 5e-3 else float(est)


def real_sine_amplitudes(data_dir=None, n_harmonics: int = 3) -> list[dict]:
    """Steady-state amplitudes of the rig's sine records (``Sine/*`` LMS folders).

    For each record: drive frequency [Hz], voltage amplitude [V] and velocity amplitudes [m/s] of
    harmonics 1..n, all by least squares on the steady part of the burst (from 10 s after the start
    to 1 s before the drive stops).
    """
    root = _bert_data_dir(data_dir) / "Sine"
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: BERT sine records not found (set GPNARX_BERT_DATA)")
    rows = []
    for folder in sorted(root.iterdir()):
        m = _SINE_DIR.search(folder.name)
        if not m or not folder.is_dir():
            continue
        nominal = float(m.group(1) + ("." + m.group(2) if m.group(2) else ""))
        rec = read_record(folder)
        fs = rec.fs
        on = np.nonzero(np.abs(rec.u) > 0.1 * np.max(np.abs(rec.u)))[0]
        i0 = int(10 * fs)
        i1 = int(on[-1] - fs)
        if i1 - i0 < 4 * fs:
            i0, i1 = int(on[0] + 0.3 * (on[-1] - on[0])), int(on[-1])
        u = rec.u[i0:i1]
        y = rec.y[i0:i1]
        fd = _drive_frequency(u, fs, nominal)
        ua = harmonic_amplitudes(u, fd, fs, 1)[0]
        ya = harmonic_amplitudes(y, fd, fs, n_harmonics)
        rows.append({"record": folder.name, "freq": fd, "volts": float(ua),
                     "velocity": ya.tolist(), "window_s": (i0 / fs, i1 / fs)})
    rows.sort(key=lambda r: r["freq"])
    return rows


def calibration_table(data_dir=None, torque: float = NOMINAL_TORQUE, seed=None, settle: float = 8.0,
                      measure: float = 2.0) -> list[dict]:
    """Real vs stand-in steady-state velocity amplitude per frequency, computed from the records.

    Each row: ``record``, ``freq`` [Hz], ``volts`` [V] (the rig's measured drive amplitude, also used
    to drive the stand-in), ``real`` and ``standin`` fundamental velocity amplitudes [m/s],
    ``error_pct`` (stand-in vs real), and the 2x and 3x super-harmonic ratios (harmonic / fundamental)
    ``real_h2``, ``standin_h2``, ``real_h3``, ``standin_h3``.
    """
    model = BertStandin(torque=torque, seed=seed)
    rows = []
    for r in real_sine_amplitudes(data_dir, 3):
        s = model.steady_response(r["freq"], r["volts"], settle=settle, measure=measure, n_harmonics=3)["velocity"]
        real = r["velocity"]
        rows.append({
            "record": r["record"], "freq": r["freq"], "volts": r["volts"],
            "real": real[0], "standin": s[0], "error_pct": 100.0 * (s[0] / real[0] - 1.0),
            "real_h2": real[1] / real[0], "standin_h2": s[1] / s[0],
            "real_h3": real[2] / real[0], "standin_h3": s[2] / s[0],
        })
    return rows


def format_calibration_table(rows: list[dict] | None = None) -> str:
    """Plain-text (Markdown) rendering of :func:`calibration_table`."""
    rows = calibration_table() if rows is None else rows
    lines = [
        "| f [Hz] | drive [V] | rig v1 [m/s] | stand-in v1 [m/s] | error [%] | rig 2x/1x | stand-in 2x/1x "
        "| rig 3x/1x | stand-in 3x/1x |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['freq']:.2f} | {r['volts']:.4f} | {r['real']:.4g} | {r['standin']:.4g} | {r['error_pct']:+.1f} "
            f"| {r['real_h2']:.3f} | {r['standin_h2']:.3f} | {r['real_h3']:.3f} | {r['standin_h3']:.3f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":  # python -m training.simulators.bert_standin
    print(format_calibration_table())
    print(f"stand-in resonance from a 0.00265 V RMS noise FRF: {resonance_from_noise():.3f} Hz")
