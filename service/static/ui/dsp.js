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
