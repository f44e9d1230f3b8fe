//! What global refinement costs as the model grows: synthetic pose graphs shaped like
//! the registrar's (a walk around a loop, 50 scans a lap, each scan linked to the 3
//! before it; with loops, each scan of a later lap also linked to the scan at the
//! same place one lap earlier), drifted by noisy odometry, then optimised once
//! from the drifted poses; the time of that optimisation against the scan count.

use nalgebra::{Matrix6, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;
use texel::Pose;

use texel_register::clock::Stopwatch;
use texel_register::graph::{Edge, PoseGraph};

/// Scans per lap of the synthetic walk.
pub const SCANS_PER_LAP: usize = 50;
/// Odometry edges per scan (the keyframe window).
const WINDOW: usize = 3;

/// One measurement.
#[derive(Debug, Clone, Serialize)]
pub struct GraphTiming {
    pub scans: usize,
    pub loops: bool,
    pub edges: usize,
    pub iterations: u32,
    /// Median CPU time of one optimisation, milliseconds.
    pub optimise_ms: f64,
    /// Per Gauss-Newton iteration.
    pub per_iteration_ms: f64,
    pub initial_cost: f64,
    pub final_cost: f64,
}

/// Deterministic uniform numbers in [-1, 1] (xorshift).
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn pose(&mut self, rotation_rad: f64, translation_m: f64) -> Pose {
        let r = Vector3::new(self.next(), self.next(), self.next()) * rotation_rad;
        let t = Vector3::new(self.next(), self.next(), self.next()) * translation_m;
        Pose::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r))
    }
}

/// The true pose of scan `k`: on a 3 m circle, looking inwards, bobbing a little.
fn truth(k: usize) -> Pose {
    let a = k as f64 / SCANS_PER_LAP as f64 * std::f64::consts::TAU;
    let eye = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 1.5 + 0.1 * (3.0 * a).sin());
    Pose::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_euler_angles(0.0, 0.0, a + std::f64::consts::PI),
    )
}

/// A graph of `scans` scans as described in the module documentation.
pub fn synthetic_graph(scans: usize, loops: bool, seed: u64) -> PoseGraph {
    let mut noise = Noise(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let information = Matrix6::from_diagonal(&nalgebra::Vector6::new(
        1.0e6, 1.0e6, 1.0e6, 1.0e5, 1.0e5, 1.0e5,
    ));
    let mut graph = PoseGraph::new();
    let mut drifted: Vec<Pose> = Vec::with_capacity(scans);
    let mut edges = Vec::new();
    for k in 0..scans {
        if k == 0 {
            drifted.push(truth(0));
        } else {
            // Odometry with 1 mrad / 1 mm noise and a small bias: the drift.
            let measured = truth(k - 1).inverse() * truth(k) * noise.pose(1.0e-3, 1.0e-3);
            let biased = measured * Pose::translation(0.002, 0.0, 0.0);
            drifted.push(drifted[k - 1] * biased);
        }
        for back in 1..=WINDOW.min(k) {
            let i = k - back;
            edges.push(Edge {
                i,
                j: k,
                measured: truth(i).inverse() * truth(k) * noise.pose(1.0e-3, 1.0e-3),
                information,
                loop_closure: false,
            });
        }
        if loops && k >= SCANS_PER_LAP {
            let i = k - SCANS_PER_LAP;
            edges.push(Edge {
                i,
                j: k,
                measured: truth(i).inverse() * truth(k) * noise.pose(1.0e-3, 1.0e-3),
                information,
                loop_closure: true,
            });
        }
    }
    for pose in drifted {
        graph.add_node(pose);
    }
    for edge in edges {
        graph.add_edge(edge);
    }
    graph
}

/// Times one optimisation (at most `max_iterations` iterations) of graphs of each
/// size, with and without loop edges, `repeats` times each (median).
pub fn measure(sizes: &[usize], max_iterations: u32, repeats: usize) -> Vec<GraphTiming> {
    let mut out = Vec::new();
    for loops in [false, true] {
        for &scans in sizes {
            let mut times = Vec::new();
            let mut last = None;
            for r in 0..repeats.max(1) {
                let mut graph = synthetic_graph(scans, loops, 7 + r as u64);
                let edges = graph.edges().len();
                let watch = Stopwatch::start();
                let report = graph.optimise(max_iterations);
                times.push(watch.elapsed().cpu_ms);
                last = Some((edges, report));
            }
            let Some((edges, report)) = last else {
                continue;
            };
            let optimise_ms = texel_register::clock::quantile(&times, 0.5);
            out.push(GraphTiming {
                scans,
                loops,
                edges,
                iterations: report.iterations,
                optimise_ms,
                per_iteration_ms: optimise_ms / f64::from(report.iterations.max(1)),
                initial_cost: report.initial_cost,
                final_cost: report.final_cost,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn optimising_a_drifted_loop_graph_lowers_its_cost_and_error() {
        let mut graph = synthetic_graph(120, true, 1);
        assert_eq!(graph.poses().len(), 120);
        // 3 odometry edges per scan (fewer for the first three) and one loop edge per
        // scan after the first lap.
        assert_eq!(graph.edges().len(), 3 * 120 - 6 + (120 - SCANS_PER_LAP));
        let error = |g: &PoseGraph| {
            let (_, d) = texel::pose::pose_difference(&g.poses()[119], &truth(119));
            d
        };
        let before = error(&graph);
        let report = graph.optimise(10);
        // Down to the measurement noise's floor (about one unit per edge).
        assert!(report.final_cost < 0.1 * report.initial_cost, "{report:?}");
        assert!(
            error(&graph) < 0.2 * before,
            "{} vs {before}",
            error(&graph)
        );
    }
}
