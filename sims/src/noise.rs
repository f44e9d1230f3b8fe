//! Value-noise fBm for procedural textures: the random lattice of one seed, the f64
//! reference evaluation, and the fixed-point one the renderer samples through.

use crate::material::fast_floor;
use crate::rng::mix64;

/// Side of the lattice of random values behind value noise; the noise repeats every
/// `NOISE_PERIOD` lattice cells (per octave, with octaves offset from each other, so
/// repeats are not visible).
const NOISE_PERIOD: usize = 256;

/// Random lattice values of one seed, looked up instead of hashed per sample.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseTable {
    /// Per lattice cell, row-major, `NOISE_PERIOD` by `NOISE_PERIOD`, the values at its
    /// four corners: (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1), wrapping at the
    /// period. A sample reads its cell's corners with one index and from one cache
    /// line, not four scattered reads (1 MiB a table, against 256 KiB for the values
    /// alone). A fixed-size array: any 16-bit cell index is in bounds, checked by the
    /// type rather than per sample.
    corners: Box<[[f32; 4]; LATTICE_LEN]>,
}

/// Values in a noise lattice.
const LATTICE_LEN: usize = NOISE_PERIOD * NOISE_PERIOD;

impl NoiseTable {
    pub fn new(seed: u64) -> Self {
        let value = |ix: usize, iy: usize| {
            let i = (iy % NOISE_PERIOD) * NOISE_PERIOD + ix % NOISE_PERIOD;
            (mix64(seed ^ mix64(i as u64 + 1)) >> 40) as f32 / (1u64 << 24) as f32
        };
        // Built on the heap: a 1 MiB array value could overflow a thread's stack.
        let corners: Box<[[f32; 4]]> = (0..LATTICE_LEN)
            .map(|i| {
                let (ix, iy) = (i % NOISE_PERIOD, i / NOISE_PERIOD);
                [
                    value(ix, iy),
                    value(ix + 1, iy),
                    value(ix, iy + 1),
                    value(ix + 1, iy + 1),
                ]
            })
            .collect();
        match corners.try_into() {
            Ok(corners) => Self { corners },
            Err(_) => unreachable!("LATTICE_LEN cells are collected"),
        }
    }

    #[inline]
    fn lattice(&self, ix: i64, iy: i64) -> f32 {
        let m = NOISE_PERIOD as i64 - 1;
        self.corners[((iy & m) as usize) * NOISE_PERIOD + (ix & m) as usize][0]
    }

    /// Smooth value noise in [0, 1].
    #[inline]
    fn value_noise(&self, x: f64, y: f64) -> f32 {
        let (fx, fy) = (fast_floor(x), fast_floor(y));
        let (ix, iy) = (fx as i64, fy as i64);
        let (tx, ty) = ((x - fx) as f32, (y - fy) as f32);
        let sx = tx * tx * (3.0 - 2.0 * tx);
        let sy = ty * ty * (3.0 - 2.0 * ty);
        let a = self.lattice(ix, iy);
        let b = self.lattice(ix + 1, iy);
        let c = self.lattice(ix, iy + 1);
        let d = self.lattice(ix + 1, iy + 1);
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }

    /// Fractional Brownian motion of value noise in [0, 1]; octaves whose period is
    /// below about two footprints fade out (band limiting) towards their mean.
    pub fn fbm(&self, x: f64, y: f64, footprint: f64, octaves: u32) -> f64 {
        let mut sum = 0.0f32;
        let mut norm = 0.0f32;
        let mut freq = 1.0f64;
        let mut amp = 1.0f32;
        for o in 0..octaves.min(16) {
            norm += amp;
            // Fraction of this octave that survives the footprint's low-pass.
            let keep = (1.0 - (freq * footprint - 0.25) * 2.0).clamp(0.0, 1.0) as f32;
            if keep <= 0.0 {
                // Every finer octave is gone too: they add their mean.
                sum += 0.5 * amp;
                let mut a = amp * 0.5;
                for _ in o + 1..octaves.min(16) {
                    sum += 0.5 * a;
                    norm += a;
                    a *= 0.5;
                }
                break;
            }
            let shift = f64::from(o) * 37.7;
            let n = self.value_noise(x * freq + shift, y * freq - shift * 0.61);
            sum += amp * (0.5 + (n - 0.5) * keep);
            freq *= 2.0;
            amp *= 0.5;
        }
        if norm > 0.0 {
            f64::from(sum / norm)
        } else {
            0.5
        }
    }
}

/// Fractional bits of the fixed-point lattice coordinates of [`NoiseTable::fbm_fixed`].
const FIXED_BITS: u32 = 24;
/// One lattice period in fixed point: coordinates wrap modulo this.
const FIXED_PERIOD: u64 = (NOISE_PERIOD as u64) << FIXED_BITS;
// `fbm_fixed` wraps coordinates in u32 and indexes the lattice with 16 bits.
const _: () = assert!(NOISE_PERIOD == 256 && FIXED_PERIOD == 1 << 32);

/// A lattice coordinate in the fixed point of [`NoiseTable::fbm_fixed`], modulo the
/// lattice period: `floor(v · 2^24) mod 2^32`. One lattice period is exactly 2^32 in
/// fixed point, so the wrap is the truncation to 32 bits of the integer part.
#[inline]
fn to_fixed(v: f64) -> u32 {
    const SCALE: f64 = (1u64 << FIXED_BITS) as f64;
    // Below 2^62 in magnitude `floor(v · 2^24)` is an exact i64 (2^24 is a power of
    // two, so the product is exact) and its low 32 bits are the wrapped coordinate.
    const LIMIT: f64 = (1u64 << 62) as f64;
    let scaled = v * SCALE;
    if scaled.abs() < LIMIT {
        let truncated = scaled as i64;
        let floor = if truncated as f64 > scaled {
            truncated - 1
        } else {
            truncated
        };
        return floor as u32;
    }
    // Far away, NaN or infinite: reduce modulo the period first, in f64 (for finite
    // `v` exactly the same value; anything else lands at 0).
    let period = NOISE_PERIOD as f64;
    let wrapped = v - period * fast_floor(v / period);
    (wrapped * SCALE) as u64 as u32
}

impl NoiseTable {
    /// [`Self::fbm`] evaluated the fast way, to within 1e-5 of it: the base
    /// coordinates are reduced modulo the lattice period (which every octave's period
    /// divides) and turned into fixed point with 24 fractional bits once, so each
    /// octave's cell and fraction are a shift and a mask instead of a float floor. The
    /// renderer samples noise textures through this.
    pub fn fbm_fixed(&self, x: f64, y: f64, footprint: f64, octaves: u32) -> f32 {
        let octaves = octaves.min(16) as usize;
        if octaves == 0 {
            return 0.5;
        }
        let (fx, fy) = (to_fixed(x), to_fixed(y));
        // The amplitudes 1, 1/2, 1/4, … of the octaves sum to 2 - 2^(1 - octaves): in
        // f32 exactly (at most 16 powers of two), whatever order they are added in.
        let norm = 2.0 - 1.0 / (1u32 << (octaves - 1)) as f32;
        // The octave's coordinates: base × 2^o plus its offset (as in `fbm`).
        let octave = |o: usize| {
            let (sx, sy) = OCTAVE_SHIFTS[o];
            self.value_noise_fixed((fx << o).wrapping_add(sx), (fy << o).wrapping_add(sy))
        };
        let mut sum = 0.0f32;
        let mut freq = 1.0f64;
        let mut amp = 1.0f32;
        let mut o = 0;
        // Octaves whose cell is at least four footprints wide are kept whole: there
        // the filter's keep is 1 exactly (1 - 2 · (freq · footprint - 0.25) with a
        // non-positive difference), and (n - 0.5) · 1 is n - 0.5, so skipping its
        // arithmetic gives the same sum. freq · footprint only grows with the octave
        // (exact doublings), so these octaves come first; with a small footprint they
        // are all of them.
        while o < octaves && freq * footprint <= 0.25 {
            let n = octave(o);
            sum += amp * (0.5 + (n - 0.5));
            freq *= 2.0;
            amp *= 0.5;
            o += 1;
        }
        // The octaves the footprint fades towards their mean.
        while o < octaves {
            let keep = (1.0 - (freq * footprint - 0.25) * 2.0).clamp(0.0, 1.0) as f32;
            if keep <= 0.0 {
                // Every finer octave is gone too: they add their mean.
                sum += 0.5 * amp;
                let mut a = amp * 0.5;
                for _ in o + 1..octaves {
                    sum += 0.5 * a;
                    a *= 0.5;
                }
                break;
            }
            let n = octave(o);
            sum += amp * (0.5 + (n - 0.5) * keep);
            freq *= 2.0;
            amp *= 0.5;
            o += 1;
        }
        sum / norm
    }

    /// [`Self::value_noise`] at fixed-point coordinates (wrapping).
    #[inline]
    fn value_noise_fixed(&self, x: u32, y: u32) -> f32 {
        const CELL: u32 = FIXED_BITS;
        let (ix, iy) = (x >> CELL, y >> CELL);
        let fraction = |v: u32| (v & ((1 << CELL) - 1)) as f32 * (1.0 / (1u32 << CELL) as f32);
        let (tx, ty) = (fraction(x), fraction(y));
        let sx = tx * tx * (3.0 - 2.0 * tx);
        let sy = ty * ty * (3.0 - 2.0 * ty);
        // 8-bit cell coordinates: (row << 8 | column) is 16 bits.
        let [a, b, c, d] = self.corners[((iy << 8) | ix) as u16 as usize];
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }
}

/// The per-octave offsets of [`NoiseTable::fbm`] (`+37.7 o`, `-37.7 · 0.61 o` lattice
/// cells) in fixed point, modulo the lattice period.
const OCTAVE_SHIFTS: [(u32, u32); 16] = {
    let mut out = [(0u32, 0u32); 16];
    let mut o = 0;
    while o < 16 {
        let sx = 37.7 * o as f64;
        let sy = -37.7 * 0.61 * o as f64;
        let period = NOISE_PERIOD as f64;
        // Wrap into [0, period) without a float floor (not const): whole periods.
        let wx = sx - period * ((sx / period) as i64 as f64);
        let mut wy = sy - period * ((sy / period) as i64 as f64);
        if wy < 0.0 {
            wy += period;
        }
        let scale = (1u64 << FIXED_BITS) as f64;
        out[o] = (
            ((wx * scale) as u64 % FIXED_PERIOD) as u32,
            ((wy * scale) as u64 % FIXED_PERIOD) as u32,
        );
        o += 1;
    }
    out
};

#[cfg(test)]
mod tests {
    use super::*;

    /// The renderer's fixed-point fBm against the f64 reference (which also makes the
    /// committed mural): within 1e-5 everywhere, at any footprint, including negative
    /// and far-away coordinates.
    #[test]
    fn fixed_point_fbm_matches_the_reference() {
        let table = NoiseTable::new(11);
        let mut s = 5u64;
        let mut next = || {
            s = mix64(s);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut worst = 0.0f64;
        for _ in 0..20_000 {
            let x = (next() - 0.5) * 2000.0;
            let y = (next() - 0.5) * 2000.0;
            let footprint = next() * next() * 0.2;
            let octaves = 1 + (next() * 7.0) as u32;
            let reference = table.fbm(x, y, footprint, octaves);
            let fast = f64::from(table.fbm_fixed(x, y, footprint, octaves));
            worst = worst.max((reference - fast).abs());
        }
        assert!(worst < 1e-5, "{worst}");
    }
}
