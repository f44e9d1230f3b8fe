//! `texeld register`: the command line around `texel_register::capture`, with a
//! progress bar on a terminal and a printed summary.

use std::path::Path;

use indicatif::{ProgressBar, ProgressStyle};
use texel_register::RegistrationConfig;
use texel_register::capture::{Progress, register_capture};

/// The `texeld register` command: prints a summary, returns the exit code.
pub fn run(
    capture: &Path,
    out: &Path,
    config: Option<&Path>,
    report: Option<&Path>,
) -> std::process::ExitCode {
    let config = match config.map(RegistrationConfig::load).transpose() {
        Ok(c) => c.unwrap_or_default(),
        Err(e) => {
            eprintln!("texeld register: {e}");
            // A bad configuration, as for every command (docs/daemon.md).
            return std::process::ExitCode::from(2);
        }
    };
    let bar = if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        ProgressBar::new(0)
    } else {
        ProgressBar::hidden()
    };
    let mut progress = |p: Progress| match p {
        Progress::Started { frames } => {
            bar.set_length(frames as u64);
            if let Ok(style) = ProgressStyle::with_template(
                "{msg} [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta})",
            ) {
                bar.set_style(style.progress_chars("=> "));
            }
            bar.set_message("registering");
        }
        Progress::Frame => bar.inc(1),
        Progress::Finished => bar.finish_and_clear(),
    };
    match register_capture(capture, out, config, report, &mut progress) {
        Ok(r) => {
            println!(
                "registered {} of {} frames ({} failed, {} recovered, {} keyframes, {} loop closures); registration time per frame (without fusion) median {:.2} ms, p95 {:.2} ms; CPU median {:.2} ms, p95 {:.2} ms -> {}",
                r.registered,
                r.frames,
                r.failed,
                r.recovered,
                r.keyframes,
                r.loop_closures,
                r.time_median_ms,
                r.time_p95_ms,
                r.cpu_median_ms,
                r.cpu_p95_ms,
                out.display()
            );
            if let (Some(ate), Some(drift)) = (r.ate_rmse_mm, r.drift_percent) {
                println!(
                    "against /truth/pose: ATE RMSE {ate:.2} mm, end drift {drift:.3} % of {:.2} m, mean RPE {:.4} deg {:.2} mm",
                    r.path_length_m.unwrap_or(0.0),
                    r.rpe_rotation_mean_deg.unwrap_or(0.0),
                    r.rpe_translation_mean_mm.unwrap_or(0.0)
                );
            }
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("texeld register: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
