//! Colour from the acquisition views (Lechelek et al. 2019, §4, eqs. 1-5): a surface
//! point seen in view `C` takes the pixels of the acquisition views `C_k` that see it,
//! weighted by `max(0, V · V_k) / (δ + 1)`: the angle between the viewing directions
//! (eq. 2) and the difference of distances to the point (eq. 4). A view whose
//! direction grazes the surface (`N · V_k ≤ λ`) does not count; the seed prints the
//! condition to meet as `N · V_k < λ`, a slip for the angle below π/2 it states.

use nalgebra::Vector3;

/// The seed's λ: a view must see the surface at least this far from edge-on.
pub const GRAZING_LAMBDA: f64 = 1.0e-4;

/// Eq. 5's weight of acquisition centre `c_k` for the point `p` with normal `normal`
/// seen from `c`; 0 for a grazing or back-facing view and for any degenerate
/// geometry (a centre on the point, a zero normal).
pub fn view_weight(
    c: &Vector3<f64>,
    p: &Vector3<f64>,
    normal: &Vector3<f64>,
    c_k: &Vector3<f64>,
) -> f64 {
    let (to_c, to_c_k) = (c - p, c_k - p);
    let (d, d_k, n) = (to_c.norm(), to_c_k.norm(), normal.norm());
    let usable = |x: f64| x > 0.0 && x.is_finite();
    if !(usable(d) && usable(d_k) && usable(n)) {
        return 0.0;
    }
    let (v, v_k, n) = (to_c / d, to_c_k / d_k, normal / n);
    if n.dot(&v_k) <= GRAZING_LAMBDA {
        return 0.0;
    }
    let cos = v.dot(&v_k).max(0.0);
    let delta = (d - d_k).abs();
    cos / (delta + 1.0)
}

/// The weighted mean of the samples' colours (eq. 5), `None` when no sample carries
/// weight (no 0/0).
pub fn blend(samples: &[([f32; 3], f64)]) -> Option<[f32; 3]> {
    let mut sum = [0.0f64; 3];
    let mut total = 0.0;
    for (colour, w) in samples {
        if !(w.is_finite() && *w > 0.0) {
            continue;
        }
        for (s, c) in sum.iter_mut().zip(colour) {
            *s += w * f64::from(*c);
        }
        total += w;
    }
    (total > 0.0).then(|| sum.map(|s| (s / total) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_normal_perpendicular_to_every_view_gives_no_colour() {
        let p = Vector3::zeros();
        let normal = Vector3::z();
        let c = Vector3::new(0.0, -2.0, 0.0);
        let views = [Vector3::new(1.0, -2.0, 0.0), Vector3::new(-3.0, 1.0, 0.0)];
        let samples: Vec<([f32; 3], f64)> = views
            .iter()
            .map(|c_k| ([1.0, 0.5, 0.2], view_weight(&c, &p, &normal, c_k)))
            .collect();
        assert!(samples.iter().all(|s| s.1 == 0.0));
        assert_eq!(blend(&samples), None);
        // Degenerate geometry weighs nothing either.
        assert_eq!(view_weight(&p, &p, &normal, &views[0]), 0.0);
        assert_eq!(view_weight(&c, &p, &Vector3::zeros(), &views[0]), 0.0);
        assert_eq!(view_weight(&c, &p, &normal, &p), 0.0);
    }

    #[test]
    fn similar_direction_and_distance_weigh_most() {
        let p = Vector3::zeros();
        let normal = Vector3::z();
        let c = Vector3::new(0.0, 0.0, 2.0);
        let same = view_weight(&c, &p, &normal, &Vector3::new(0.0, 0.0, 2.0));
        let farther = view_weight(&c, &p, &normal, &Vector3::new(0.0, 0.0, 5.0));
        let oblique = view_weight(&c, &p, &normal, &Vector3::new(2.0, 0.0, 0.5));
        assert!((same - 1.0).abs() < 1e-12);
        assert!((farther - 0.25).abs() < 1e-12, "{farther}");
        assert!(oblique < same && oblique > 0.0);
        let mixed = blend(&[([1.0; 3], same), ([0.0; 3], farther)]).unwrap();
        assert!((mixed[0] - 0.8).abs() < 1e-6);
    }
}
