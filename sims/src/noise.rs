//! Value-noise fBm for procedural textures: the random lattice of one seed, the f64
//! reference evaluation, and the fixed-point one the renderer samples through (one
//! point at a time, or four at once in SIMD lanes); also the fast floor that noise
//! and checkerboard lookups share.

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

/// `x.floor()` without a libm call on targets without SSE4.1 (finite inputs within
/// ±2⁶³; others saturate, which only shifts a texture pattern). Defined here, below
/// [`crate::material`], whose checkerboards use it too.
#[inline]
pub(crate) fn fast_floor(x: f64) -> f64 {
    let i = x as i64;
    let f = i as f64;
    if f > x { f - 1.0 } else { f }
}

/// Points [`NoiseTable::fbm_fixed_lanes`] evaluates at once (four f32 lanes of an
/// SSE register).
pub const LANES: usize = 4;

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

/// [`to_fixed`] of [`LANES`] coordinates, the same values. Below 2^51 in fixed point
/// (2^27 lattice cells) the floor is taken in SIMD-friendly f64 arithmetic: adding
/// and subtracting 1.5 · 2^52 rounds to an integer (exactly, as every value there is
/// one), a comparison turns that into the floor, and adding 1.5 · 2^52 again puts the
/// integer plus 2^51 in the mantissa, whose low 32 bits are the integer's modulo
/// 2^32 (2^51 is a multiple of 2^32). Anything else goes through [`to_fixed`].
#[inline]
fn to_fixed_lanes(v: &[f64; LANES]) -> [u32; LANES] {
    const SCALE: f64 = (1u64 << FIXED_BITS) as f64;
    const LIMIT: f64 = (1u64 << 51) as f64;
    const MAGIC: f64 = 1.5 * (1u64 << 52) as f64;
    let scaled: [f64; LANES] = std::array::from_fn(|l| v[l] * SCALE);
    // NaN fails the comparison too.
    if !scaled.iter().all(|s| s.abs() < LIMIT) {
        return std::array::from_fn(|l| to_fixed(v[l]));
    }
    std::array::from_fn(|l| {
        let s = scaled[l];
        let nearest = (s + MAGIC) - MAGIC;
        let floor = if nearest > s { nearest - 1.0 } else { nearest };
        (floor + MAGIC).to_bits() as u32
    })
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

    /// [`Self::fbm_fixed`] at [`LANES`] points at once, bit for bit the same values:
    /// the octaves' integer and f32 arithmetic is the same per point, written lane by
    /// lane so the compiler does it in SIMD registers, four points per instruction.
    /// Every octave goes through the fading filter's formula; for an octave kept whole
    /// its keep is exactly 1 and `(n - 0.5) · 1` is `n - 0.5`, and for one faded out
    /// it is exactly 0, which adds the octave's mean `0.5 · amp` as the scalar path
    /// does, in the same order.
    pub fn fbm_fixed_lanes(
        &self,
        x: &[f64; LANES],
        y: &[f64; LANES],
        footprint: &[f64; LANES],
        octaves: u32,
    ) -> [f32; LANES] {
        let octaves = octaves.min(16) as usize;
        if octaves == 0 {
            return [0.5; LANES];
        }
        let (fx, fy) = (to_fixed_lanes(x), to_fixed_lanes(y));
        let norm = 2.0 - 1.0 / (1u32 << (octaves - 1)) as f32;
        let mut sum = [0.0f32; LANES];
        let mut freq = 1.0f64;
        let mut amp = 1.0f32;
        let octave = |o: usize| {
            let (sx, sy) = OCTAVE_SHIFTS[o];
            self.value_noise_lanes(
                &std::array::from_fn(|l| (fx[l] << o).wrapping_add(sx)),
                &std::array::from_fn(|l| (fy[l] << o).wrapping_add(sy)),
            )
        };
        // Octaves every point keeps whole come first (as in `fbm_fixed`), without the
        // filter's arithmetic.
        let widest = footprint.iter().fold(0.0f64, |a, &f| a.max(f));
        let mut o = 0;
        while o < octaves && freq * widest <= 0.25 {
            let n = octave(o);
            for l in 0..LANES {
                sum[l] += amp * (0.5 + (n[l] - 0.5));
            }
            freq *= 2.0;
            amp *= 0.5;
            o += 1;
        }
        for o in o..octaves {
            let keep: [f32; LANES] = std::array::from_fn(|l| {
                (1.0 - (freq * footprint[l] - 0.25) * 2.0).clamp(0.0, 1.0) as f32
            });
            if keep.iter().all(|&k| k <= 0.0) {
                // This octave and every finer one are faded out at every point: they
                // add their means.
                for _ in o..octaves {
                    for s in &mut sum {
                        *s += 0.5 * amp;
                    }
                    amp *= 0.5;
                }
                break;
            }
            let n = octave(o);
            for l in 0..LANES {
                sum[l] += amp * (0.5 + (n[l] - 0.5) * keep[l]);
            }
            freq *= 2.0;
            amp *= 0.5;
        }
        std::array::from_fn(|l| sum[l] / norm)
    }

    /// [`Self::value_noise_fixed`] at [`LANES`] points.
    #[inline]
    fn value_noise_lanes(&self, x: &[u32; LANES], y: &[u32; LANES]) -> [f32; LANES] {
        const CELL: u32 = FIXED_BITS;
        const SCALE: f32 = 1.0 / (1u32 << CELL) as f32;
        let smooth = |v: u32| {
            // Below 2^24, so exact in f32 and positive in i32 (a plain SIMD conversion).
            let t = (v & ((1 << CELL) - 1)) as i32 as f32 * SCALE;
            t * t * (3.0 - 2.0 * t)
        };
        let sx: [f32; LANES] = std::array::from_fn(|l| smooth(x[l]));
        let sy: [f32; LANES] = std::array::from_fn(|l| smooth(y[l]));
        let cells: [[f32; 4]; LANES] = std::array::from_fn(|l| {
            self.corners[(((y[l] >> CELL) << 8) | (x[l] >> CELL)) as u16 as usize]
        });
        std::array::from_fn(|l| {
            let [a, b, c, d] = cells[l];
            let top = a + (b - a) * sx[l];
            let bottom = c + (d - c) * sx[l];
            top + (bottom - top) * sy[l]
        })
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

    /// The SIMD-friendly fixed-point conversion gives what the scalar one gives, at
    /// ordinary coordinates, at exact integers and half-integers of the fixed point,
    /// around the 2^51 edge of its fast path, and for far, infinite and NaN values.
    #[test]
    fn fixed_point_lanes_match_the_scalar_conversion() {
        let ulp = 1.0 / (1u64 << FIXED_BITS) as f64;
        let edge = (1u64 << 51) as f64 * ulp;
        let mut values = vec![
            0.0,
            -0.0,
            ulp,
            -ulp,
            0.5 * ulp,
            -0.5 * ulp,
            1.5 * ulp,
            -1.5 * ulp,
            2.5 * ulp,
            -2.5 * ulp,
            255.999,
            -255.999,
            256.0,
            -256.0,
            edge,
            -edge,
            edge.next_down(),
            (-edge).next_up(),
            edge.next_up(),
            1.0e30,
            -1.0e30,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            f64::MIN_POSITIVE,
        ];
        let mut s = 3u64;
        for _ in 0..4000 {
            s = mix64(s);
            let magnitude = 10f64.powi((s % 16) as i32 - 6);
            values.push(((s >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * magnitude);
        }
        // Each value alone among ordinary ones (the fast path whenever it is in its
        // range), then in groups.
        for &v in &values {
            let lanes: [f64; LANES] = std::array::from_fn(|l| if l == 1 { v } else { 0.25 });
            assert_eq!(to_fixed_lanes(&lanes)[1], to_fixed(v), "{v}");
        }
        for chunk in values.chunks(LANES) {
            let lanes: [f64; LANES] =
                std::array::from_fn(|l| chunk.get(l).copied().unwrap_or(0.25));
            let fast = to_fixed_lanes(&lanes);
            for l in 0..LANES {
                assert_eq!(fast[l], to_fixed(lanes[l]), "{}", lanes[l]);
            }
        }
    }

    /// Four points at once give exactly what one at a time gives, whatever mix of
    /// footprints (octaves kept whole, faded, gone) the lanes hold.
    #[test]
    fn lanes_match_one_point_at_a_time_bit_for_bit() {
        let table = NoiseTable::new(12);
        let mut s = 9u64;
        let mut next = || {
            s = mix64(s);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for case in 0..20_000 {
            let mut x = [0.0; LANES];
            let mut y = [0.0; LANES];
            let mut footprint = [0.0; LANES];
            for l in 0..LANES {
                x[l] = (next() - 0.5) * 2000.0;
                y[l] = (next() - 0.5) * 2000.0;
                // Zero, tiny, fading and beyond every octave.
                footprint[l] = match (case + l) % 4 {
                    0 => 0.0,
                    1 => next() * next() * 0.2,
                    2 => next() * 2.0,
                    _ => next() * 1.0e-3,
                };
            }
            let octaves = (case % 8) as u32 + u32::from(case % 3 == 0) * 9;
            let lanes = table.fbm_fixed_lanes(&x, &y, &footprint, octaves);
            for l in 0..LANES {
                let one = table.fbm_fixed(x[l], y[l], footprint[l], octaves);
                assert_eq!(
                    lanes[l].to_bits(),
                    one.to_bits(),
                    "case {case} lane {l}: {} against {one}",
                    lanes[l]
                );
            }
        }
    }
}
