//! What one scan offers each world surface cell, quantised to 8 bytes an offer, and
//! the packed form a retired scan keeps them in (about 11 bytes an offer instead
//! of 32): most scans of a long session are retired, so their offers are most of
//! what the retirement index holds.

use std::borrow::Cow;
use std::collections::HashMap;

use nalgebra::{Point3, Vector3};

use super::{MIN_RANGE_M, ScanCoverage};
use crate::pose::Pose;

/// A world surface cell: the integer coordinates of a cube of edge `cell_m`.
pub(super) type CellKey = [i64; 3];

/// Cell coordinates beyond this are clamped (a point 1e15 cells away is not a
/// surface anyone renders; the clamp keeps the cast defined).
const MAX_CELL_INDEX: f64 = 1.0e15;

/// The largest range a code tells apart from larger ones, metres.
const MAX_CODED_RANGE_M: f64 = 1.0e6;

/// Range codes per unit of `ln(range)`: the 16-bit code spans `MIN_RANGE_M` to
/// `MAX_CODED_RANGE_M` in equal ratios of 1.00042 (an error of at most 0.021 %).
fn range_codes_per_log() -> f64 {
    f64::from(u16::MAX) / (MAX_CODED_RANGE_M / MIN_RANGE_M).ln()
}

/// Octahedral codes per unit of the octahedron's coordinates (a direction to
/// within about 0.005 degrees).
const DIRECTION_CODES: f64 = i16::MAX as f64;

/// What a scan offers one cell: the mean acquisition direction of its samples there
/// (from the surface towards the centre of projection), their mean normal accuracy
/// and mean acquisition range, each quantised. Decisions are taken on the decoded
/// values, the same whether the scan is served or retired (packed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Offer {
    /// The direction's octahedral code.
    direction: [i16; 2],
    /// Normal accuracy in [0, 1], in 65,535ths.
    accuracy: u16,
    /// `ln(range / MIN_RANGE_M)` in `range_codes_per_log` steps.
    range: u16,
}

impl Offer {
    /// The offer closest to the given values. A direction that is not a finite,
    /// non-zero vector is coded as +z (callers drop such samples before).
    pub(super) fn new(direction: &Vector3<f64>, normal_accuracy: f64, range_m: f64) -> Self {
        let accuracy = if normal_accuracy.is_finite() {
            (normal_accuracy.clamp(0.0, 1.0) * f64::from(u16::MAX)).round() as u16
        } else {
            0
        };
        let log = (range_m.max(MIN_RANGE_M) / MIN_RANGE_M).ln() * range_codes_per_log();
        let range = if log.is_finite() {
            log.round().clamp(0.0, f64::from(u16::MAX)) as u16
        } else {
            u16::MAX
        };
        Self {
            direction: encode_direction(direction),
            accuracy,
            range,
        }
    }

    /// The unit acquisition direction.
    pub(super) fn direction(&self) -> Vector3<f64> {
        decode_direction(self.direction)
    }

    pub(super) fn normal_accuracy(&self) -> f64 {
        f64::from(self.accuracy) / f64::from(u16::MAX)
    }

    pub(super) fn range_m(&self) -> f64 {
        MIN_RANGE_M * (f64::from(self.range) / range_codes_per_log()).exp()
    }

    /// This offer with its direction rotated.
    fn rotated(&self, rotation: &nalgebra::UnitQuaternion<f64>) -> Self {
        Self {
            direction: encode_direction(&(rotation * self.direction())),
            ..*self
        }
    }

    fn to_bytes(self) -> [u8; 8] {
        let [a, b] = self.direction;
        let mut out = [0u8; 8];
        out[0..2].copy_from_slice(&a.to_le_bytes());
        out[2..4].copy_from_slice(&b.to_le_bytes());
        out[4..6].copy_from_slice(&self.accuracy.to_le_bytes());
        out[6..8].copy_from_slice(&self.range.to_le_bytes());
        out
    }

    fn from_bytes(b: [u8; 8]) -> Self {
        Self {
            direction: [
                i16::from_le_bytes([b[0], b[1]]),
                i16::from_le_bytes([b[2], b[3]]),
            ],
            accuracy: u16::from_le_bytes([b[4], b[5]]),
            range: u16::from_le_bytes([b[6], b[7]]),
        }
    }
}

/// Octahedral code of a direction (Meyer et al. 2010): the unit vector projected
/// on the octahedron |x|+|y|+|z| = 1, the lower half folded over the upper.
fn encode_direction(d: &Vector3<f64>) -> [i16; 2] {
    let l1 = d.x.abs() + d.y.abs() + d.z.abs();
    if !l1.is_finite() || l1 <= 0.0 {
        return [0, 0];
    }
    let (mut u, mut v) = (d.x / l1, d.y / l1);
    if d.z < 0.0 {
        (u, v) = ((1.0 - v.abs()) * sign(u), (1.0 - u.abs()) * sign(v));
    }
    let code = |c: f64| (c.clamp(-1.0, 1.0) * DIRECTION_CODES).round() as i16;
    [code(u), code(v)]
}

/// The unit vector of an octahedral code. Never degenerate: a point of the
/// octahedron is at least 1/sqrt(3) from the origin.
fn decode_direction(code: [i16; 2]) -> Vector3<f64> {
    let u = f64::from(code[0]) / DIRECTION_CODES;
    let v = f64::from(code[1]) / DIRECTION_CODES;
    let z = 1.0 - u.abs() - v.abs();
    let (x, y) = if z < 0.0 {
        ((1.0 - v.abs()) * sign(u), (1.0 - u.abs()) * sign(v))
    } else {
        (u, v)
    };
    let p = Vector3::new(x, y, z);
    p / p.norm().max(f64::MIN_POSITIVE)
}

fn sign(x: f64) -> f64 {
    if x >= 0.0 { 1.0 } else { -1.0 }
}

/// The cell of world point `p`, `None` when a coordinate is not finite.
pub(super) fn cell_of(p: &Point3<f64>, cell_m: f64) -> Option<CellKey> {
    let mut key = [0i64; 3];
    for (k, c) in key.iter_mut().zip(p.iter()) {
        let i = (c / cell_m).floor();
        if !i.is_finite() {
            return None;
        }
        *k = i.clamp(-MAX_CELL_INDEX, MAX_CELL_INDEX) as i64;
    }
    Some(key)
}

/// The offers of a signature placed at `world_from_scan`, one per cell it reaches,
/// sorted by cell.
pub(super) fn offers_of(
    coverage: &ScanCoverage,
    world_from_scan: &Pose,
    cell_m: f64,
) -> Vec<(CellKey, Offer)> {
    let cop = world_from_scan * Point3::from(coverage.cop_m);
    // Per cell: direction sum, accuracy sum, range sum, count.
    let mut sums: HashMap<CellKey, (Vector3<f64>, f64, f64, u32)> = HashMap::new();
    for s in &coverage.samples {
        let local = Point3::new(
            f64::from(s.point_m[0]),
            f64::from(s.point_m[1]),
            f64::from(s.point_m[2]),
        );
        let p = world_from_scan * local;
        let to_cop = cop - p;
        let range_m = to_cop.norm();
        let accuracy = f64::from(s.normal_accuracy);
        if !range_m.is_finite() || range_m < MIN_RANGE_M || !accuracy.is_finite() {
            continue;
        }
        let Some(key) = cell_of(&p, cell_m) else {
            continue;
        };
        let e = sums.entry(key).or_insert((Vector3::zeros(), 0.0, 0.0, 0));
        e.0 += to_cop / range_m;
        e.1 += accuracy.clamp(0.0, 1.0);
        e.2 += range_m;
        e.3 += 1;
    }
    let mut offers: Vec<(CellKey, Offer)> = sums
        .into_iter()
        .filter_map(|(key, (dir, acc, range, n))| {
            let len = dir.norm();
            // Opposite directions in one cell (both faces of a thin wall) cancel:
            // no single direction stands for them, so the cell is left out.
            if n == 0 || len < 1.0e-6 {
                return None;
            }
            let n = f64::from(n);
            Some((key, Offer::new(&(dir / len), acc / n, range / n)))
        })
        .collect();
    offers.sort_by_key(|(k, _)| *k);
    offers
}

/// `offers` (made at `from`) carried rigidly to `to`: each cell's centre and
/// direction moved by the pose change, the most accurate offer kept where two land
/// in one cell. An approximation for a scan whose signature is lost.
pub(super) fn moved_offers(
    offers: &[(CellKey, Offer)],
    from: &Pose,
    to: &Pose,
    cell_m: f64,
) -> Vec<(CellKey, Offer)> {
    let change = to * from.inverse();
    let mut moved: Vec<(CellKey, Offer)> = offers
        .iter()
        .filter_map(|(key, offer)| {
            let centre = Point3::new(
                (key[0] as f64 + 0.5) * cell_m,
                (key[1] as f64 + 0.5) * cell_m,
                (key[2] as f64 + 0.5) * cell_m,
            );
            let new_key = cell_of(&(change * centre), cell_m)?;
            Some((new_key, offer.rotated(&change.rotation)))
        })
        .collect();
    moved.sort_by(|(a, x), (b, y)| a.cmp(b).then(y.accuracy.cmp(&x.accuracy)));
    moved.dedup_by_key(|(k, _)| *k);
    moved
}

/// A scan's offers, sorted by cell: open while served (witness searches read them
/// by binary search), packed while retired (read whole, only when the scan itself
/// is tested again).
#[derive(Debug, Clone)]
pub(super) enum Offers {
    Open(Vec<(CellKey, Offer)>),
    Packed(Box<[u8]>),
}

impl Default for Offers {
    fn default() -> Self {
        Self::Open(Vec::new())
    }
}

impl Offers {
    /// The offers: borrowed when open, decoded when packed.
    pub(super) fn view(&self) -> Cow<'_, [(CellKey, Offer)]> {
        match self {
            Self::Open(v) => Cow::Borrowed(v),
            Self::Packed(bytes) => Cow::Owned(unpack(bytes)),
        }
    }

    /// Packs open offers (no-op when packed).
    pub(super) fn pack(&mut self) {
        if let Self::Open(v) = self {
            *self = Self::Packed(pack(v));
        }
    }

    /// Opens packed offers (no-op when open).
    pub(super) fn open(&mut self) {
        if let Self::Packed(bytes) = self {
            *self = Self::Open(unpack(bytes));
        }
    }

    /// Offer at `key`, for open offers only (`None` when packed or absent).
    pub(super) fn get(&self, key: &CellKey) -> Option<Offer> {
        let Self::Open(v) = self else {
            return None;
        };
        let i = v.binary_search_by_key(key, |(k, _)| *k).ok()?;
        v.get(i).map(|(_, o)| *o)
    }

    /// Bytes on the heap.
    pub(super) fn heap_bytes(&self) -> usize {
        match self {
            Self::Open(v) => v.capacity() * std::mem::size_of::<(CellKey, Offer)>(),
            Self::Packed(bytes) => bytes.len(),
        }
    }
}

/// The packed form: per offer, the cell's difference from the previous cell (from
/// 0 for the first) as three zig-zag varints, then the offer's 8 bytes. Sorted
/// cells of one scan are neighbours, so a difference takes about a byte a
/// coordinate.
pub(super) fn pack(offers: &[(CellKey, Offer)]) -> Box<[u8]> {
    let mut out = Vec::with_capacity(offers.len() * 11);
    let mut previous: CellKey = [0; 3];
    for (key, offer) in offers {
        for (k, p) in key.iter().zip(&previous) {
            put_varint(&mut out, zigzag(k.wrapping_sub(*p)));
        }
        out.extend_from_slice(&offer.to_bytes());
        previous = *key;
    }
    out.into_boxed_slice()
}

/// The offers of a packed form. Stops at the first incomplete offer (the index
/// only unpacks what it packed, so there is none).
pub(super) fn unpack(bytes: &[u8]) -> Vec<(CellKey, Offer)> {
    let mut offers = Vec::with_capacity(bytes.len() / 11 + 1);
    let mut at = 0usize;
    let mut previous: CellKey = [0; 3];
    'offers: while at < bytes.len() {
        let mut key = [0i64; 3];
        for (k, p) in key.iter_mut().zip(&previous) {
            let Some((v, used)) = get_varint(&bytes[at..]) else {
                break 'offers;
            };
            at += used;
            *k = p.wrapping_add(unzigzag(v));
        }
        let Some(code) = bytes
            .get(at..at + 8)
            .and_then(|b| <[u8; 8]>::try_from(b).ok())
        else {
            break;
        };
        at += 8;
        offers.push((key, Offer::from_bytes(code)));
        previous = key;
    }
    offers
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8 & 0x7f) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// A varint and the bytes it took; `None` when incomplete or longer than 10 bytes.
fn get_varint(bytes: &[u8]) -> Option<(u64, usize)> {
    let mut v = 0u64;
    for (i, b) in bytes.iter().enumerate().take(10) {
        v |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Some((v, i + 1));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use proptest::prelude::*;

    use super::*;

    fn arb_offer() -> impl Strategy<Value = Offer> {
        (any::<[i16; 2]>(), any::<u16>(), any::<u16>()).prop_map(|(direction, accuracy, range)| {
            Offer {
                direction,
                accuracy,
                range,
            }
        })
    }

    proptest! {
        #[test]
        fn packing_round_trips_any_sorted_offers(
            mut offers in proptest::collection::vec(
                (proptest::array::uniform3(-(1i64 << 50)..(1i64 << 50)), arb_offer()),
                0..300,
            )
        ) {
            offers.sort_by_key(|(k, _)| *k);
            offers.dedup_by_key(|(k, _)| *k);
            let packed = pack(&offers);
            prop_assert_eq!(unpack(&packed), offers);
        }

        #[test]
        fn a_direction_survives_coding_within_a_hundredth_of_a_degree(
            x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0,
        ) {
            let d = Vector3::new(x, y, z);
            prop_assume!(d.norm() > 1.0e-3);
            let d = d / d.norm();
            let back = decode_direction(encode_direction(&d));
            prop_assert!((back.norm() - 1.0).abs() < 1.0e-12);
            prop_assert!(d.dot(&back) > (0.01f64).to_radians().cos(), "{d:?} -> {back:?}");
        }

        #[test]
        fn ranges_and_accuracies_survive_coding(
            range_m in 1.0e-3f64..1.0e5, accuracy in 0.0f64..=1.0,
        ) {
            let o = Offer::new(&Vector3::z(), accuracy, range_m);
            prop_assert!((o.range_m() / range_m - 1.0).abs() < 2.2e-4);
            prop_assert!((o.normal_accuracy() - accuracy).abs() <= 0.5 / 65535.0 + 1e-12);
        }

        #[test]
        fn any_code_decodes_to_a_finite_unit_vector(code in any::<[i16; 2]>()) {
            let d = decode_direction(code);
            prop_assert!(d.iter().all(|c| c.is_finite()));
            prop_assert!((d.norm() - 1.0).abs() < 1.0e-12);
        }
    }

    #[test]
    fn degenerate_values_code_to_finite_offers() {
        let o = Offer::new(&Vector3::new(f64::NAN, 0.0, 0.0), f64::NAN, f64::INFINITY);
        assert!(o.direction().iter().all(|c| c.is_finite()));
        assert_eq!(o.normal_accuracy(), 0.0);
        assert!(o.range_m().is_finite());
        let zero = Offer::new(&Vector3::zeros(), 2.0, 0.0);
        assert_eq!(zero.normal_accuracy(), 1.0);
        assert!((zero.range_m() - MIN_RANGE_M).abs() < 1.0e-12);
    }

    #[test]
    fn a_scan_of_neighbouring_cells_packs_into_about_eleven_bytes_an_offer() {
        let offers: Vec<(CellKey, Offer)> = (0..10)
            .flat_map(|x| (0..6).map(move |z| [x - 5, 2, z]))
            .map(|k| (k, Offer::new(&Vector3::x(), 0.8, 3.0)))
            .collect();
        let packed = pack(&offers);
        assert_eq!(unpack(&packed), offers);
        assert!(
            packed.len() <= offers.len() * 11 + 2,
            "{} bytes",
            packed.len()
        );
    }

    #[test]
    fn truncated_packs_give_their_whole_offers_only() {
        let offers: Vec<(CellKey, Offer)> = (0..5)
            .map(|i| ([i, 0, 0], Offer::new(&Vector3::y(), 0.5, 2.0)))
            .collect();
        let packed = pack(&offers);
        for cut in 0..packed.len() {
            let got = unpack(&packed[..cut]);
            assert!(got.len() < offers.len());
            assert_eq!(got[..], offers[..got.len()]);
        }
    }
}
