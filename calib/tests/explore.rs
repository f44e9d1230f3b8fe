#![allow(clippy::unwrap_used, clippy::expect_used)]
use calib::config::{SolverConfig, TargetConfig};
use calib::detect::{DetectParams, detect_board};
use calib::eo::{EoObservation, calibrate_eo};
use calib::gray::GrayImage;
use std::path::Path;

#[test]
fn explore() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = sims::Scene::load(&root.join("configs/scenes/calib-target.toml")).unwrap();
    let sim = sims::Simulator::new(scene, 1).unwrap();
    let t = TargetConfig::default();
    let mut obs = Vec::new();
    for i in 0..sim.frame_count() {
        let f = sim.frame(i).unwrap();
        let g = GrayImage::from_eo(&f.pair.eo).unwrap();
        if let Ok(b) = detect_board(&g, &t, &DetectParams::eo(g.width, g.height)) {
            obs.push(EoObservation { view: i, corners: b });
        }
    }
    let t0 = std::time::Instant::now();
    let sol = calibrate_eo(&obs, &t, 640, 480, &SolverConfig::default()).unwrap();
    println!("{:?}", t0.elapsed());
    println!("truth {:?}", sim.sensor_model().eo);
    println!("est {:?}\nstd {:?}\nrms {} it {} conv {} dropped {} tilts {:?}", sol.intrinsics, sol.intrinsics_std, sol.rms_px, sol.iterations, sol.converged, sol.outliers_dropped, sol.tilt_deg);
}
