// Welch power spectral density, as gpnarx.model.psd.psd computes it with scipy.signal.welch
// (Hann window, 512-sample segments or the whole record when shorter, 50 % overlap, mean removed
// per segment, one-sided density in units^2/Hz). Segments are a power of two here (the largest
// one not above min(512, n)) so a plain radix-2 FFT serves.

export const PSD_NPERSEG = 512;

function fftInPlace(re, im) {
  const n = re.length;
  for (let i = 1, j = 0; i < n; i++) {
    let bit = n >> 1;
    for (; j & bit; bit >>= 1) j ^= bit;
    j ^= bit;
    if (i < j) {
      [re[i], re[j]] = [re[j], re[i]];
      [im[i], im[j]] = [im[j], im[i]];
    }
  }
  for (let len = 2; len <= n; len <<= 1) {
    const ang = (-2 * Math.PI) / len;
    const wr = Math.cos(ang), wi = Math.sin(ang);
    for (let i = 0; i < n; i += len) {
      let cr = 1, ci = 0;
      for (let k = 0; k < len / 2; k++) {
        const a = i + k, b = a + len / 2;
        const tr = re[b] * cr - im[b] * ci, ti = re[b] * ci + im[b] * cr;
        re[b] = re[a] - tr; im[b] = im[a] - ti;
        re[a] += tr; im[a] += ti;
        const ncr = cr * wr - ci * wi;
        ci = cr * wi + ci * wr;
        cr = ncr;
      }
    }
  }
}

/** Segment length used for n samples: the largest power of two <= min(nperseg, n). */
export function segmentLength(n, nperseg = PSD_NPERSEG) {
  return 2 ** Math.floor(Math.log2(Math.max(2, Math.min(nperseg, n))));
}

/** Welch PSD of x sampled at fs -> {f: Float64Array [Hz], p: Float64Array [units^2/Hz]}. */
export function welch(x, fs, nperseg = PSD_NPERSEG) {
  const seg = segmentLength(x.length, nperseg);
  const step = seg < x.length ? seg / 2 : seg;
  const win = new Float64Array(seg);
  let s2 = 0;
  for (let i = 0; i < seg; i++) {
    win[i] = 0.5 - 0.5 * Math.cos((2 * Math.PI * i) / seg); // periodic Hann, as scipy's get_window
    s2 += win[i] * win[i];
  }
  const nf = seg / 2 + 1;
  const p = new Float64Array(nf);
  const re = new Float64Array(seg), im = new Float64Array(seg);
  let count = 0;
  for (let start = 0; start + seg <= x.length; start += step) {
    let mean = 0;
    for (let i = 0; i < seg; i++) mean += x[start + i];
    mean /= seg;
    for (let i = 0; i < seg; i++) { re[i] = (x[start + i] - mean) * win[i]; im[i] = 0; }
    fftInPlace(re, im);
    for (let k = 0; k < nf; k++) p[k] += re[k] * re[k] + im[k] * im[k];
    count++;
  }
  const scale = 1 / (fs * s2 * Math.max(count, 1));
  const f = new Float64Array(nf);
  for (let k = 0; k < nf; k++) {
    f[k] = (k * fs) / seg;
    p[k] *= scale * (k === 0 || k === nf - 1 ? 1 : 2);
  }
  return { f, p };
}

// Zero-phase low-pass, as scipy.signal.sosfiltfilt(scipy.signal.butter(order, fc, fs=fs, output="sos"), x)
// computes it: a Butterworth filter as second-order sections, run forward then backward over the record
// extended at each end by an odd reflection (3 * (2 * sections + 1) samples), each pass started from the
// sections' steady state for the extension's first sample. Used to band-limit a restoring force before it
// is drawn: R = g u - m y'' holds the measured output differentiated twice, which lifts its noise by
// (2 pi f)^2 at frequency f.

/** Second-order sections [b0, b1, b2, a1, a2] (a0 = 1) of a Butterworth low-pass of even ``order``, cut-off
 * ``fc`` [Hz] at ``fs`` [Hz]: analogue poles prewarped, bilinear transform, unit gain at 0 Hz. */
export function butterLowpass(order, fc, fs) {
  if (!(order >= 2 && order % 2 === 0)) throw new Error("order must be even");
  if (!(fc > 0 && fc < fs / 2)) throw new Error(`cut-off ${fc} Hz must lie in (0, ${fs / 2}) Hz`);
  const k = 2 * fs;
  const wc = k * Math.tan((Math.PI * fc) / fs);
  const sos = [];
  for (let i = 0; i < order / 2; i++) {
    // a conjugate pair of the analogue prototype's poles, scaled to wc: s = wc (re +- j im)
    const theta = (Math.PI * (2 * i + 1)) / (2 * order);
    const re = -wc * Math.sin(theta), im = wc * Math.cos(theta);
    // bilinear z = (k + s) / (k - s) of the pair: denominator 1 + a1 z^-1 + a2 z^-2
    const dr = k - re, di = -im; // k - s
    const nr = k + re, ni = im; // k + s
    const den = dr * dr + di * di;
    const zr = (nr * dr + ni * di) / den, zi = (ni * dr - nr * di) / den;
    const a1 = -2 * zr, a2 = zr * zr + zi * zi;
    // two zeros at z = -1; gain for 1 at z = 1
    const g = (1 + a1 + a2) / 4;
    sos.push([g, 2 * g, g, a1, a2]);
  }
  return sos;
}

/** The steady state of one section for a unit step (scipy.signal.lfilter_zi). */
function sectionZi([b0, b1, b2, a1, a2]) {
  // (I - A^T) zi = b[1:] - a[1:] b0 with A the companion matrix [[-a1, 1], [-a2, 0]]
  const r0 = b1 - a1 * b0, r1 = b2 - a2 * b0;
  const det = (1 + a1) * 1 + a2;
  const z0 = (r0 * 1 + r1) / det;
  const z1 = r1 - a2 * z0;
  return [z0, z1];
}

function sosZi(sos) {
  let scale = 1;
  return sos.map((s) => {
    const [z0, z1] = sectionZi(s);
    const zi = [z0 * scale, z1 * scale];
    scale *= (s[0] + s[1] + s[2]) / (1 + s[3] + s[4]);
    return zi;
  });
}

function sosfilt(sos, x, zi, x0) {
  const y = Float64Array.from(x);
  sos.forEach((s, j) => {
    const [b0, b1, b2, a1, a2] = s;
    let z0 = zi[j][0] * x0, z1 = zi[j][1] * x0;
    for (let i = 0; i < y.length; i++) {
      const xi = y[i];
      const yi = b0 * xi + z0;
      z0 = b1 * xi - a1 * yi + z1;
      z1 = b2 * xi - a2 * yi;
      y[i] = yi;
    }
  });
  return y;
}

/** x filtered forward and backward by ``sos``, as scipy.signal.sosfiltfilt(sos, x, padlen=padlen) with its odd
 * padding (padlen: scipy's default 3 * (2 * sections + 1) unless given). */
export function sosfiltfilt(sos, x, padlen) {
  const n = x.length;
  const pad = padlen ?? 3 * (2 * sos.length + 1);
  if (n <= pad) throw new Error(`the record must be longer than ${pad} samples to be filtered`);
  const ext = new Float64Array(n + 2 * pad);
  for (let i = 0; i < pad; i++) {
    ext[i] = 2 * x[0] - x[pad - i];
    ext[n + pad + i] = 2 * x[n - 1] - x[n - 2 - i];
  }
  for (let i = 0; i < n; i++) ext[pad + i] = x[i];
  const zi = sosZi(sos);
  const fwd = sosfilt(sos, ext, zi, ext[0]);
  fwd.reverse();
  const back = sosfilt(sos, fwd, zi, fwd[0]);
  back.reverse();
  return back.subarray(pad, pad + n);
}

/** Samples on each side of a stretch that a low-pass at fc [Hz] mixes into it: three periods of fc. */
export function filterMargin(fc, fs) {
  return Math.ceil((3 * fs) / fc);
}

/** Zero-phase Butterworth low-pass (order 4: two sections, 24 dB per octave each way) at fc [Hz] of x[i0:i1].
 * The odd padding holds each end of what is filtered at its own value, noise included, so the stretch is
 * filtered with up to filterMargin samples of x on each side (not closer than ``guard`` samples to x's ends,
 * where the loops answer's frequency-domain derivative of a record that is not periodic rings), and padded
 * with filterMargin samples beyond that; then cut back to x[i0:i1]. */
export function lowpassStretch(x, i0, i1, fc, fs, guard = 5) {
  const m = filterMargin(fc, fs);
  const a = Math.min(i0, Math.max(guard, i0 - m));
  const b = Math.max(i1, Math.min(x.length - guard, i1 + m));
  const seg = Array.prototype.slice.call(x, a, b);
  const y = sosfiltfilt(butterLowpass(4, fc, fs), seg, Math.min(m, seg.length - 1));
  return y.slice(i0 - a, i1 - a);
}

/** Zero-phase Butterworth low-pass of the whole of x at fc [Hz] (order 4). */
export function lowpass(x, fc, fs, order = 4) {
  return sosfiltfilt(butterLowpass(order, fc, fs), x);
}
