//! Calibration measured against the simulator: simulated views of the target, the
//! lab check (fusion and registration with a calibrated sensor) and their commands.

pub mod commands;
pub mod lab_check;
pub mod simulate;
