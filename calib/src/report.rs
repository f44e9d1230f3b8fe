//! The calibration report: a Markdown summary (estimates with standard deviations,
//! RMS and per-view residuals, refused views and why), a residual plot (SVG, via
//! plotters) and the detected corners drawn on a few EO and lidar images (PNG).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};
use plotters::prelude::*;
use thiserror::Error;

use crate::gray::GrayImage;
use crate::pipeline::{CalibInput, Calibration};

#[derive(Debug, Error)]
pub enum ReportError {
    #[error("cannot write {path}: {message}")]
    Write { path: String, message: String },
}

fn write_error(path: &Path, e: impl std::fmt::Display) -> ReportError {
    ReportError::Write {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}

/// The files a report consists of.
#[derive(Debug, Clone)]
pub struct ReportFiles {
    pub markdown: PathBuf,
    pub plot: PathBuf,
    pub images: Vec<PathBuf>,
}

/// Writes the report to `path` (Markdown) and its figures beside it.
pub fn write_report(
    calibration: &Calibration,
    input: &CalibInput,
    source: &str,
    path: &Path,
) -> Result<ReportFiles, ReportError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| write_error(dir, e))?;
    let stem = path.file_stem().map_or_else(
        || "report".to_string(),
        |s| s.to_string_lossy().into_owned(),
    );
    let plot = dir.join(format!("{stem}-residuals.svg"));
    residual_plot(calibration, &plot)?;
    let mut images = Vec::new();
    for view in chosen_views(calibration) {
        let eo_png = dir.join(format!("{stem}-view{view}-eo.png"));
        draw_eo(calibration, input, view, &eo_png)?;
        images.push(eo_png);
        let lidar_png = dir.join(format!("{stem}-view{view}-lidar.png"));
        if draw_lidar(calibration, input, view, &lidar_png)? {
            images.push(lidar_png);
        }
    }
    let text = markdown(calibration, input, source, &plot, &images);
    std::fs::write(path, text).map_err(|e| write_error(path, e))?;
    Ok(ReportFiles {
        markdown: path.to_path_buf(),
        plot,
        images,
    })
}

/// The first view, the worst-fitting view, and one in between.
fn chosen_views(c: &Calibration) -> Vec<usize> {
    let views: Vec<usize> = c.eo.per_view.iter().map(|v| v.view).collect();
    let mut out = Vec::new();
    if let Some(&first) = views.first() {
        out.push(first);
    }
    if let Some(worst) =
        c.eo.per_view
            .iter()
            .max_by(|a, b| a.rms_px.total_cmp(&b.rms_px))
            .map(|v| v.view)
        && !out.contains(&worst)
    {
        out.push(worst);
    }
    if let Some(&mid) = views.get(views.len() / 2)
        && !out.contains(&mid)
    {
        out.push(mid);
    }
    out
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
}

fn markdown(
    c: &Calibration,
    input: &CalibInput,
    source: &str,
    plot: &Path,
    images: &[PathBuf],
) -> String {
    let mut s = String::new();
    let k = &c.eo.intrinsics;
    let sd = &c.eo.intrinsics_std;
    let names = [
        "fx (px)", "fy (px)", "cx (px)", "cy (px)", "k1", "k2", "p1", "p2", "k3",
    ];
    let _ = writeln!(s, "# Texel camera calibration\n");
    let _ = writeln!(
        s,
        "Source: `{source}`: {} texel frames; the EO camera saw the whole board in {}, \
         the lidar in {}. Detection took {:.2} s, estimation {:.2} s.\n",
        c.detections.len(),
        c.eo.per_view.len(),
        c.lidar.per_view.len(),
        c.seconds_detect,
        c.seconds_solve
    );
    for w in &input.warnings {
        let _ = writeln!(s, "- warning: {w}");
    }
    let _ = writeln!(
        s,
        "## EO camera ({}x{})\n",
        c.eo.camera.width, c.eo.camera.height
    );
    let _ = writeln!(
        s,
        "| parameter | estimate | standard deviation |\n|---|---|---|"
    );
    for i in 0..9 {
        let _ = writeln!(s, "| {} | {:.6} | {:.6} |", names[i], k[i], sd[i]);
    }
    let _ = writeln!(
        s,
        "\nReprojection RMS {:.4} px over {} views ({} corners dropped as outliers); \
         EO-only solution before the joint refinement: fx {:.3}, fy {:.3}, cx {:.3}, \
         cy {:.3}, RMS {:.4} px.\n",
        c.eo.rms_px,
        c.eo.per_view.len(),
        c.eo.outliers_dropped,
        c.eo_only.intrinsics[0],
        c.eo_only.intrinsics[1],
        c.eo_only.intrinsics[2],
        c.eo_only.intrinsics[3],
        c.eo_only.rms_px
    );
    let l = &c.lidar;
    let (t, q) = texel::pose::pose_to_parts(&l.eo_from_lidar);
    let angles = l.eo_from_lidar.rotation.euler_angles();
    let _ = writeln!(s, "## Lidar and `eo_from_lidar`\n");
    let _ = writeln!(
        s,
        "| quantity | estimate | standard deviation |\n|---|---|---|"
    );
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        let _ = writeln!(
            s,
            "| translation {name} (mm) | {:.3} | {:.3} |",
            t[a] * 1e3,
            l.translation_std_m[a] * 1e3
        );
    }
    for (a, (name, v)) in ["x", "y", "z"]
        .iter()
        .zip([angles.0, angles.1, angles.2])
        .enumerate()
    {
        let _ = writeln!(
            s,
            "| rotation about {name} (deg) | {:.4} | {:.4} |",
            v.to_degrees(),
            l.rotation_std_deg[a]
        );
    }
    let _ = writeln!(
        s,
        "| range bias (mm) | {:+.3} | {:.3} |",
        l.range_bias_m * 1e3,
        l.range_bias_std_m * 1e3
    );
    if let Some(sd) = l.lidar_intrinsics_std {
        let lc = &l.lidar;
        for (name, v, e) in [
            ("lidar fx (px)", lc.fx, sd[0]),
            ("lidar fy (px)", lc.fy, sd[1]),
            ("lidar cx (px)", lc.cx, sd[2]),
            ("lidar cy (px)", lc.cy, sd[3]),
        ] {
            let _ = writeln!(s, "| {name} | {v:.4} | {e:.4} |");
        }
    } else {
        let _ = writeln!(
            s,
            "\nLidar intrinsics: taken from the capture's `/lidar/calibration` (fx {:.3}, fy \
             {:.3}, cx {:.3}, cy {:.3}).",
            l.lidar.fx, l.lidar.fy, l.lidar.cx, l.lidar.cy
        );
    }
    let _ = writeln!(
        s,
        "\nQuaternion (x, y, z, w): [{:.9}, {:.9}, {:.9}, {:.9}]. Board pixels lie {:.2} mm \
         RMS from the EO board planes; intensity corners were found in {} lidar views{}.\n",
        q[0],
        q[1],
        q[2],
        q[3],
        l.plane_rms_m * 1e3,
        l.corner_views,
        l.corner_rms_px
            .map(|v| format!(" and reproject with {v:.3} px RMS"))
            .unwrap_or_default()
    );
    let _ = writeln!(s, "## Per view\n");
    let _ = writeln!(
        s,
        "| frame | EO RMS (px) | EO max (px) | board tilt (deg) | lidar plane RMS (mm) | lidar mean offset (mm) | lidar corners RMS (px) |\n|---|---|---|---|---|---|---|"
    );
    for (n, v) in c.eo.per_view.iter().enumerate() {
        let lv = l.per_view.iter().find(|x| x.view == v.view);
        let _ = writeln!(
            s,
            "| {} | {:.4} | {:.4} | {:.1} | {} | {} | {} |",
            v.view,
            v.rms_px,
            v.max_px,
            c.eo.tilt_deg.get(n).copied().unwrap_or(f64::NAN),
            lv.map_or("-".into(), |x| format!("{:.2}", x.plane_rms_m * 1e3)),
            lv.map_or("-".into(), |x| format!("{:+.2}", x.plane_mean_m * 1e3)),
            lv.and_then(|x| x.corner_rms_px)
                .map_or("-".into(), |x| format!("{x:.3}"))
        );
    }
    let skipped: Vec<String> = c
        .detections
        .iter()
        .flat_map(|d| {
            let mut v = Vec::new();
            if let Err(e) = &d.eo {
                v.push(format!("- frame {} (EO): {e}", d.index));
            }
            if let Err(e) = &d.lidar {
                v.push(format!("- frame {} (lidar): {e}", d.index));
            }
            v
        })
        .collect();
    if !skipped.is_empty() {
        let _ = writeln!(s, "\n## Views not used\n");
        for line in skipped {
            let _ = writeln!(s, "{line}");
        }
    }
    let _ = writeln!(s, "\n## Figures\n");
    let _ = writeln!(
        s,
        "![EO reprojection residuals and per-view RMS]({})\n",
        file_name(plot)
    );
    for img in images {
        let _ = writeln!(s, "![{}]({})\n", file_name(img), file_name(img));
    }
    let _ = writeln!(
        s,
        "EO images: detected corners in green (corner (0, 0) in red), reprojected corners \
         in blue. Lidar images: intensity, the plate's pixels outlined in yellow, intensity \
         corners in green."
    );
    s
}

fn residual_plot(c: &Calibration, path: &Path) -> Result<(), ReportError> {
    let err = |e: &dyn std::fmt::Display| write_error(path, e);
    // The plot's text needs the shared chart font registered with plotters.
    texel_plots::ensure_font().map_err(|e| err(&e))?;
    let root = SVGBackend::new(path, (1000, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (left, right) = root.split_horizontally(430);
    let points: Vec<(f64, f64)> =
        c.eo.per_view
            .iter()
            .flat_map(|v| v.residuals.iter().map(|r| (r.2.x, r.2.y)))
            .collect();
    let extent = points
        .iter()
        .map(|p| p.0.abs().max(p.1.abs()))
        .fold(0.05f64, f64::max)
        .min(50.0)
        * 1.1;
    let mut chart = ChartBuilder::on(&left)
        .caption("EO reprojection residuals (px)", (texel_plots::FAMILY, 18))
        .margin(12)
        .x_label_area_size(30)
        .y_label_area_size(45)
        .build_cartesian_2d(-extent..extent, -extent..extent)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("du")
        .y_desc("dv")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(
            points
                .iter()
                .map(|p| Circle::new(*p, 2, BLUE.mix(0.5).filled())),
        )
        .map_err(|e| err(&e))?;
    let n = c.eo.per_view.len().max(1);
    let max_rms =
        c.eo.per_view
            .iter()
            .map(|v| v.rms_px)
            .chain(c.lidar.per_view.iter().map(|v| v.plane_rms_m * 10.0))
            .fold(0.01f64, f64::max)
            * 1.2;
    let mut chart = ChartBuilder::on(&right)
        .caption(
            "Per view: EO RMS (px, blue), lidar plane RMS (cm, red)",
            (texel_plots::FAMILY, 18),
        )
        .margin(12)
        .x_label_area_size(30)
        .y_label_area_size(45)
        .build_cartesian_2d(0usize..n, 0.0..max_rms)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("view (order used)")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new(
            c.eo.per_view.iter().enumerate().map(|(k, v)| (k, v.rms_px)),
            &BLUE,
        ))
        .map_err(|e| err(&e))?;
    let lidar_points: Vec<(usize, f64)> =
        c.eo.per_view
            .iter()
            .enumerate()
            .filter_map(|(k, v)| {
                c.lidar
                    .per_view
                    .iter()
                    .find(|l| l.view == v.view)
                    .map(|l| (k, l.plane_rms_m * 100.0))
            })
            .collect();
    chart
        .draw_series(
            lidar_points
                .iter()
                .map(|p| Circle::new(*p, 3, RED.filled())),
        )
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

fn cross(img: &mut RgbImage, x: f64, y: f64, r: i64, colour: Rgb<u8>) {
    if !(x.is_finite() && y.is_finite()) {
        return;
    }
    let (cx, cy) = (x.round() as i64, y.round() as i64);
    for d in -r..=r {
        for (px, py) in [(cx + d, cy), (cx, cy + d)] {
            if px >= 0 && py >= 0 && (px as u32) < img.width() && (py as u32) < img.height() {
                img.put_pixel(px as u32, py as u32, colour);
            }
        }
    }
}

fn draw_eo(
    c: &Calibration,
    input: &CalibInput,
    view: usize,
    path: &Path,
) -> Result<(), ReportError> {
    let Some(v) = input.views.get(view) else {
        return Ok(());
    };
    let eo = &v.pair.eo;
    let Some(mut img) = RgbImage::from_raw(eo.width, eo.height, eo.rgb.clone()) else {
        return Ok(());
    };
    if let Some(Ok(corners)) = c.detections.get(view).map(|d| &d.eo) {
        for (i, j, p) in corners.iter() {
            let colour = if (i, j) == (0, 0) {
                Rgb([255, 0, 0])
            } else {
                Rgb([0, 220, 0])
            };
            cross(&mut img, p.x, p.y, 4, colour);
        }
    }
    if let Some(r) = c.eo.per_view.iter().find(|r| r.view == view)
        && let Some(Ok(corners)) = c.detections.get(view).map(|d| &d.eo)
    {
        for (i, j, res) in &r.residuals {
            if let Some(p) = corners.get(*i, *j) {
                cross(&mut img, p.x + res.x, p.y + res.y, 1, Rgb([40, 80, 255]));
            }
        }
    }
    img.save(path).map_err(|e| write_error(path, e))
}

/// Draws the lidar view scaled 4x; false when the frame has no intensity.
fn draw_lidar(
    c: &Calibration,
    input: &CalibInput,
    view: usize,
    path: &Path,
) -> Result<bool, ReportError> {
    let Some(v) = input.views.get(view) else {
        return Ok(false);
    };
    let Some(g) = GrayImage::from_intensity(&v.pair.range) else {
        return Ok(false);
    };
    const S: u32 = 4;
    let (w, h) = (g.width as u32, g.height as u32);
    let mut img = RgbImage::new(w * S, h * S);
    for y in 0..h * S {
        for x in 0..w * S {
            let val = (g.at((x / S) as usize, (y / S) as usize).clamp(0.0, 1.0) * 255.0) as u8;
            img.put_pixel(x, y, Rgb([val, val, val]));
        }
    }
    if let Some(Ok(board)) = c.detections.get(view).map(|d| &d.lidar) {
        let on: std::collections::HashSet<(u32, u32)> = board.segment.iter().copied().collect();
        for &(u, vv) in &board.segment {
            let edge = [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)]
                .iter()
                .any(|(du, dv)| {
                    let (a, b) = (i64::from(u) + du, i64::from(vv) + dv);
                    a < 0 || b < 0 || !on.contains(&(a as u32, b as u32))
                });
            if edge {
                for dy in 0..S {
                    for dx in 0..S {
                        img.put_pixel(u * S + dx, vv * S + dy, Rgb([255, 220, 0]));
                    }
                }
            }
        }
        if let Some(corners) = &board.corners {
            for (_, _, p) in corners.iter() {
                let s = f64::from(S);
                cross(
                    &mut img,
                    (p.x + 0.5) * s - 0.5,
                    (p.y + 0.5) * s - 0.5,
                    3,
                    Rgb([0, 220, 0]),
                );
            }
        }
    }
    img.save(path).map_err(|e| write_error(path, e))?;
    Ok(true)
}
