//! The pose graph of global refinement: one node per keyframe (the registrar derives
//! every other scan's pose from its keyframe's), one edge per pair of overlapping
//! keyframes registered to each other (a relative pose and its information matrix),
//! optimised by Gauss-Newton with Levenberg-Marquardt damping on SE(3) (Grisetti et
//! al. 2010, "A tutorial on graph-based SLAM", Sec. IV), over all nodes or over a
//! contiguous range of them with the rest held fixed.
//!
//! Cost: each iteration assembles the `6F x 6F` normal matrix of the `F` free nodes
//! in O(E) into its envelope in the nodes' time order and factors it there
//! (`envelope.rs`): row `r` costs its width times its overlap with the rows it meets.
//! Odometry edges reach only the keyframe window back, so without loops the factor is
//! banded and an iteration is O(F). A loop edge from node `j` back to node `i` widens
//! the rows of `j` to `j - i` blocks: a walk that keeps revisiting ground `k` nodes
//! back costs O(F · k²) an iteration.

use std::ops::Range;

use nalgebra::{Matrix6, Vector6};
use texel::Pose;

use super::envelope::Envelope;
use super::se3;

/// A relative-pose measurement `node_from_other = T_i⁻¹ T_j`.
#[derive(Debug, Clone)]
pub struct Edge {
    pub i: usize,
    pub j: usize,
    pub measured: Pose,
    /// Information of a right perturbation of `T_j` (in `j`'s frame), `(ω, v)` order.
    pub information: Matrix6<f64>,
    pub loop_closure: bool,
}

/// The outcome of one optimisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraphReport {
    pub iterations: u32,
    pub initial_cost: f64,
    pub final_cost: f64,
}

#[derive(Debug, Clone, Default)]
pub struct PoseGraph {
    poses: Vec<Pose>,
    edges: Vec<Edge>,
}

/// `J_r⁻¹(e) ≈ I + ½ ad(e)`: the first-order inverse right Jacobian of SE(3).
fn inverse_right_jacobian(e: &Vector6<f64>) -> Matrix6<f64> {
    Matrix6::identity() + se3::small_adjoint(e) * 0.5
}

impl PoseGraph {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a node; returns its index.
    pub fn add_node(&mut self, pose: Pose) -> usize {
        self.poses.push(pose);
        self.poses.len() - 1
    }

    /// Adds an edge between existing nodes (ignored otherwise, or when the
    /// information is not finite).
    pub fn add_edge(&mut self, edge: Edge) {
        if self.is_valid(&edge) {
            self.edges.push(edge);
        }
    }

    /// Adds an edge, or fuses it into the edge of the same kind already joining the
    /// same two nodes, so that revisiting the same ground again and again does not
    /// grow the graph while every visit still counts. Fusion (same direction): the
    /// measurements are averaged on SE(3) weighted by their information's traces and
    /// the information is summed, up to `max_gain` times the new edge's (repeated
    /// views of one place are not fully independent); an edge the other way round is
    /// replaced. Returns whether the edge was taken.
    pub fn upsert_edge(&mut self, edge: Edge, max_gain: f64) -> bool {
        if !self.is_valid(&edge) {
            return false;
        }
        let pair = (edge.i.min(edge.j), edge.i.max(edge.j));
        let Some(existing) = self
            .edges
            .iter_mut()
            .find(|e| e.loop_closure == edge.loop_closure && (e.i.min(e.j), e.i.max(e.j)) == pair)
        else {
            self.edges.push(edge);
            return true;
        };
        let (old_trace, new_trace) = (existing.information.trace(), edge.information.trace());
        if existing.i != edge.i || !(old_trace > 0.0) || !(new_trace > 0.0) {
            *existing = edge;
            return true;
        }
        let w = new_trace / (old_trace + new_trace);
        let step = se3::log(&(existing.measured.inverse() * edge.measured)) * w;
        let measured = existing.measured * se3::exp(&step);
        let mut information = existing.information + edge.information;
        let cap = max_gain.max(1.0) * new_trace;
        let trace = information.trace();
        if trace > cap {
            information *= cap / trace;
        }
        if se3::is_finite(&measured) && information.iter().all(|c| c.is_finite()) {
            existing.measured = measured;
            existing.information = information;
        }
        true
    }

    fn is_valid(&self, edge: &Edge) -> bool {
        edge.i < self.poses.len()
            && edge.j < self.poses.len()
            && edge.i != edge.j
            && edge.information.iter().all(|c| c.is_finite())
    }

    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    pub fn poses(&self) -> &[Pose] {
        &self.poses
    }

    pub fn edges(&self) -> &[Edge] {
        &self.edges
    }

    pub fn set_pose(&mut self, i: usize, pose: Pose) {
        if let Some(p) = self.poses.get_mut(i) {
            *p = pose;
        }
    }

    fn residual(&self, edge: &Edge) -> Vector6<f64> {
        let e = edge.measured.inverse() * self.poses[edge.i].inverse() * self.poses[edge.j];
        se3::log(&e)
    }

    /// `Σ eᵀ Ω e` over the edges.
    pub fn cost(&self) -> f64 {
        let all: Vec<usize> = (0..self.edges.len()).collect();
        self.cost_of(&all)
    }

    /// Optimises every pose but node 0's (which fixes the gauge).
    pub fn optimise(&mut self, max_iterations: u32) -> GraphReport {
        self.optimise_range(0..self.poses.len(), max_iterations)
    }

    /// Optimises the nodes in `free` (node 0 always stays fixed, as the gauge) with
    /// every other node held where it is; only the edges that touch a free node take
    /// part, so one call costs what its range costs, however large the graph.
    pub fn optimise_range(&mut self, free: Range<usize>, max_iterations: u32) -> GraphReport {
        let free = free.start.max(1)..free.end.min(self.poses.len());
        let active: Vec<usize> = (0..self.edges.len())
            .filter(|&k| {
                let e = &self.edges[k];
                free.contains(&e.i) || free.contains(&e.j)
            })
            .collect();
        let initial_cost = self.cost_of(&active);
        let mut cost = initial_cost;
        let mut damping = 1.0e-6;
        let mut iterations = 0;
        if free.is_empty() || active.is_empty() {
            return GraphReport {
                iterations: 0,
                initial_cost,
                final_cost: cost,
            };
        }
        while iterations < max_iterations {
            iterations += 1;
            let Some(delta) = self.step(&free, &active, damping) else {
                damping *= 10.0;
                if damping > 1.0e6 {
                    break;
                }
                continue;
            };
            let saved: Vec<Pose> = self.poses[free.clone()].to_vec();
            for k in free.clone() {
                let base = 6 * (k - free.start);
                let d = Vector6::from_fn(|r, _| delta[base + r]);
                self.poses[k] *= se3::exp(&d);
            }
            let new_cost = self.cost_of(&active);
            if new_cost.is_finite() && new_cost <= cost {
                let improvement = cost - new_cost;
                cost = new_cost;
                damping = (damping / 10.0).max(1.0e-12);
                if improvement <= 1.0e-10 * cost.max(1.0e-300)
                    || delta.iter().fold(0.0f64, |m, c| m.max(c.abs())) < 1.0e-10
                {
                    break;
                }
            } else {
                self.poses[free.clone()].copy_from_slice(&saved);
                damping *= 10.0;
                if damping > 1.0e6 {
                    break;
                }
            }
        }
        GraphReport {
            iterations,
            initial_cost,
            final_cost: cost,
        }
    }

    fn cost_of(&self, active: &[usize]) -> f64 {
        active
            .iter()
            .map(|&k| {
                let e = &self.edges[k];
                let r = self.residual(e);
                (r.transpose() * e.information * r)[0]
            })
            .sum()
    }

    /// One damped Gauss-Newton step for the free nodes, `None` if the system could not
    /// be factored. The normal matrix is assembled straight into its lower envelope
    /// in time order (each node's rows start at its oldest free neighbour) and
    /// factored there.
    fn step(&self, free: &Range<usize>, active: &[usize], damping: f64) -> Option<Vec<f64>> {
        let count = free.end - free.start;
        let dim = 6 * count;
        let block = |k: usize| free.contains(&k).then(|| k - free.start);
        // Oldest free neighbour of each free node (itself when none is older).
        let mut oldest: Vec<usize> = (0..count).collect();
        for &k in active {
            let edge = &self.edges[k];
            if let (Some(a), Some(c)) = (block(edge.i), block(edge.j)) {
                let (lo, hi) = (a.min(c), a.max(c));
                oldest[hi] = oldest[hi].min(lo);
            }
        }
        let start: Vec<usize> = (0..dim).map(|r| 6 * oldest[r / 6]).collect();
        let mut h = Envelope::zeros(start);
        let mut b = vec![0.0; dim];
        for &k in active {
            let edge = &self.edges[k];
            let e = self.residual(edge);
            let jr = inverse_right_jacobian(&e);
            let j_j = jr;
            let j_i = -jr * se3::adjoint(&(self.poses[edge.j].inverse() * self.poses[edge.i]));
            let omega = &edge.information;
            let parts = [(block(edge.i), j_i), (block(edge.j), j_j)];
            for &(a, ja) in &parts {
                let Some(a) = a else { continue };
                let g = ja.transpose() * omega * e;
                for r in 0..6 {
                    b[6 * a + r] -= g[r];
                }
                for &(c, jc) in &parts {
                    // Lower triangle only: each block pair once.
                    let Some(c) = c else { continue };
                    if c > a {
                        continue;
                    }
                    let blk = ja.transpose() * omega * jc;
                    for r in 0..6 {
                        for q in 0..6 {
                            let (row, col) = (6 * a + r, 6 * c + q);
                            if c < a || q <= r {
                                h.add(row, col, blk[(r, q)]);
                            }
                        }
                    }
                }
            }
        }
        for k in 0..count {
            // Damping (and a floor, so nodes with no edges stay put).
            let base = 6 * k;
            let scale = (0..6)
                .map(|r| h.get(base + r, base + r))
                .fold(0.0f64, f64::max);
            for r in 0..6 {
                h.add(base + r, base + r, damping * scale.max(1.0) + 1.0e-9);
            }
        }
        let factor = h.cholesky()?;
        let out = factor.solve(&b);
        out.iter().all(|c| c.is_finite()).then_some(out)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_loop_spreads_the_error_and_fixes_node_zero() {
        // A square of 4 poses with a 10 cm error in the odometry, closed by a loop edge.
        let step = Pose::from_parts(
            nalgebra::Translation3::new(1.0, 0.0, 0.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        );
        let mut g = PoseGraph::new();
        let mut truth = vec![Pose::identity()];
        for k in 1..4 {
            truth.push(truth[k - 1] * step);
        }
        let bias = Pose::translation(0.1, 0.0, 0.0);
        let mut drifted = Pose::identity();
        g.add_node(drifted);
        for _ in 1..4 {
            drifted = drifted * step * bias;
            g.add_node(drifted);
        }
        let info = Matrix6::identity() * 100.0;
        for k in 0..3 {
            g.add_edge(Edge {
                i: k,
                j: k + 1,
                measured: step * bias,
                information: info,
                loop_closure: false,
            });
        }
        g.add_edge(Edge {
            i: 3,
            j: 0,
            measured: step,
            information: info,
            loop_closure: true,
        });
        let before = g.cost();
        let report = g.optimise(20);
        assert!(report.final_cost < before);
        assert_eq!(g.poses()[0], Pose::identity());
        // The loop is consistent with a square of side 1.1 (odometry) closing with
        // side 1 (loop): the optimum spreads the 0.1 m mismatch.
        let (_, err_before) = texel::pose::pose_difference(&drifted, &truth[3]);
        let (_, err_after) = texel::pose::pose_difference(&g.poses()[3], &truth[3]);
        assert!(err_after < err_before, "{err_after} vs {err_before}");
        assert!(g.poses().iter().all(se3::is_finite));
    }

    #[test]
    fn a_range_optimisation_moves_only_its_nodes_and_repeats_fuse() {
        // A chain of 6 poses 1 m apart with odometry 5 % long, and a loop edge 0-5
        // saying 5 m: optimising 3..6 leaves 0..3 where they were.
        let long = Pose::translation(1.05, 0.0, 0.0);
        let mut g = PoseGraph::new();
        let mut p = Pose::identity();
        g.add_node(p);
        for _ in 1..6 {
            p *= long;
            g.add_node(p);
        }
        let info = Matrix6::identity() * 100.0;
        for k in 0..5 {
            g.add_edge(Edge {
                i: k,
                j: k + 1,
                measured: long,
                information: info,
                loop_closure: false,
            });
        }
        let loop_edge = Edge {
            i: 0,
            j: 5,
            measured: Pose::translation(5.0, 0.0, 0.0),
            information: info,
            loop_closure: true,
        };
        assert!(g.upsert_edge(loop_edge.clone(), 8.0));
        let before: Vec<Pose> = g.poses().to_vec();
        let report = g.optimise_range(3..6, 10);
        assert!(report.final_cost < report.initial_cost);
        assert_eq!(&g.poses()[..3], &before[..3]);
        assert!(g.poses()[5].translation.x < before[5].translation.x - 0.05);
        // The same loop measured again fuses into the one edge (more information,
        // the same measurement); one the other way round replaces it.
        assert!(g.upsert_edge(loop_edge.clone(), 8.0));
        assert_eq!(g.edges().len(), 6);
        let fused = &g.edges()[5];
        assert!((fused.information[(0, 0)] - 200.0).abs() < 1e-9);
        assert!(texel::pose::pose_difference(&fused.measured, &loop_edge.measured).1 < 1e-12);
        let reversed = Edge {
            i: 5,
            j: 0,
            measured: loop_edge.measured.inverse(),
            ..loop_edge
        };
        assert!(g.upsert_edge(reversed, 8.0));
        assert_eq!(g.edges().len(), 6);
        assert_eq!(g.edges()[5].i, 5);
    }
}
