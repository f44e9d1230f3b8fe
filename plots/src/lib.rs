//! Charts for Texel's reports: Pareto plots of accuracy against time (one series per
//! scene or configuration, each setting a point, the Pareto front of each series
//! joined by a line and labelled), written as SVG and PNG; and the TrueType font their
//! text needs, loaded at run time (Debian's `fonts-dejavu-core`, installed by
//! `scripts/setup.sh`). Every crate that draws text with plotters calls
//! [`ensure_font`] first: plotters keeps one font registry per process.

mod lines;
pub use lines::{Line, write_lines};

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use thiserror::Error;

/// Font files tried in order.
const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/local/share/fonts/DejaVuSans.ttf",
];

/// The family name every chart uses for its text.
pub const FAMILY: &str = "sans-serif";

/// Why a chart could not be written.
#[derive(Debug, Clone, Error)]
pub enum PlotError {
    #[error("{0}")]
    Font(String),
    #[error("drawing {path}: {message}")]
    Draw { path: String, message: String },
}

/// One series: points `(x, y, label)`.
#[derive(Debug, Clone)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64, String)>,
}

/// Indices of the points no other point beats in both `x` and `y` (smaller is
/// better in both), sorted by `x`.
pub fn pareto_front(points: &[(f64, f64, String)]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    order.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[a].1.total_cmp(&points[b].1))
    });
    let mut front = Vec::new();
    let mut best_y = f64::INFINITY;
    for i in order {
        if points[i].1 < best_y {
            best_y = points[i].1;
            front.push(i);
        }
    }
    front
}

/// Registers the TrueType font under [`FAMILY`] once per process.
pub fn ensure_font() -> Result<(), PlotError> {
    static LOADED: OnceLock<Result<(), String>> = OnceLock::new();
    let outcome = LOADED.get_or_init(|| {
        let bytes = FONT_PATHS
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .ok_or_else(|| {
                format!(
                    "no TrueType font for the plots' text (looked for {}; Debian's \
                     fonts-dejavu-core provides it, scripts/setup.sh installs it)",
                    FONT_PATHS.join(", ")
                )
            })?;
        // plotters keeps fonts for the life of the process.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font(FAMILY, FontStyle::Normal, bytes)
            .map_err(|_| "the font file is not a usable TrueType font".to_string())
    });
    outcome.clone().map_err(PlotError::Font)
}

/// Writes the plot as `stem.svg` and `stem.png`.
pub fn write_pareto(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
) -> Result<(), PlotError> {
    struct Pareto<'a>(&'a str, &'a str, &'a str, &'a [Series]);
    impl Chart for Pareto<'_> {
        fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>
        where
            DB::ErrorType: 'static,
        {
            draw(root, self.0, self.1, self.2, self.3)
        }
    }
    write_svg_and_png(stem, (1100, 700), &Pareto(title, x_label, y_label, series))
}

/// A chart that can draw itself on any plotters backend.
pub(crate) trait Chart {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>
    where
        DB::ErrorType: 'static;
}

/// Draws `chart` into `stem.svg` and `stem.png`, with the font loaded.
pub(crate) fn write_svg_and_png(
    stem: &Path,
    size: (u32, u32),
    chart: &impl Chart,
) -> Result<(), PlotError> {
    ensure_font()?;
    let svg = stem.with_extension("svg");
    let png = stem.with_extension("png");
    {
        let root = SVGBackend::new(&svg, size).into_drawing_area();
        chart
            .draw(&root)
            .and_then(|()| root.present().map_err(|e| format!("{e}")))
            .map_err(|message| draw_error(&svg, message))?;
    }
    {
        let root = BitMapBackend::new(&png, size).into_drawing_area();
        chart
            .draw(&root)
            .and_then(|()| root.present().map_err(|e| format!("{e}")))
            .map_err(|message| draw_error(&png, message))?;
    }
    Ok(())
}

fn draw_error(path: &Path, message: String) -> PlotError {
    PlotError::Draw {
        path: path.display().to_string(),
        message,
    }
}

const COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
];

/// The range of a logarithmic axis for values in `[lo, hi]` (positive): some room on
/// both sides, and the bottom taken down to a power of ten. The axis labels only the
/// decades whose power of ten lies in its range, so without that an axis within one
/// decade (errors of 12 to 30, say) would carry no labels at all.
fn log_axis_range(lo: f64, hi: f64) -> (f64, f64) {
    let bottom = lo / 1.5;
    let decade = 10f64.powf(bottom.log10().floor());
    let bottom = if decade.is_finite() && decade > 0.0 {
        decade
    } else {
        bottom
    };
    (bottom, hi * 1.5)
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| format!("{e:?}");
    root.fill(&WHITE).map_err(err)?;
    let all = || series.iter().flat_map(|s| s.points.iter());
    let positive = |v: f64| v.is_finite() && v > 0.0;
    let (mut x1, mut y0, mut y1) = (f64::MIN, f64::MAX, f64::MIN);
    for (x, y, _) in all() {
        if positive(*x) && positive(*y) {
            x1 = x1.max(*x);
            y0 = y0.min(*y);
            y1 = y1.max(*y);
        }
    }
    if y0 >= f64::MAX {
        (x1, y0, y1) = (10.0, 0.1, 10.0);
    }
    // A linear time axis from 0 (costs compare by difference) and a logarithmic error
    // axis, with some room.
    let (x0, x1) = (0.0, x1 * 1.1);
    let (y0, y1) = log_axis_range(y0, y1);
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FAMILY, 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .label_style((FAMILY, 14))
        .axis_desc_style((FAMILY, 16))
        .draw()
        .map_err(err)?;
    for (k, s) in series.iter().enumerate() {
        let colour = COLOURS[k % COLOURS.len()];
        let points: Vec<(f64, f64)> = s
            .points
            .iter()
            .filter(|(x, y, _)| positive(*x) && positive(*y))
            .map(|(x, y, _)| (*x, *y))
            .collect();
        chart
            .draw_series(
                points
                    .iter()
                    .map(|&(x, y)| Circle::new((x, y), 4, colour.filled())),
            )
            .map_err(err)?
            .label(s.name.clone())
            .legend(move |(x, y)| Circle::new((x, y), 5, colour.filled()));
        let front: Vec<(f64, f64, String)> = pareto_front(&s.points)
            .into_iter()
            .map(|i| s.points[i].clone())
            .filter(|(x, y, _)| positive(*x) && positive(*y))
            .collect();
        chart
            .draw_series(LineSeries::new(
                front.iter().map(|(x, y, _)| (*x, *y)),
                colour.stroke_width(2),
            ))
            .map_err(err)?;
        chart
            .draw_series(front.iter().map(|(x, y, label)| {
                Text::new(
                    label.clone(),
                    (*x, *y),
                    (FAMILY, 12).into_font().color(&colour),
                )
            }))
            .map_err(err)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FAMILY, 15))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_log_axis_reaches_down_to_a_power_of_ten() {
        for (lo, hi) in [(12.0, 30.0), (2.3, 52.0), (0.04, 0.07), (1.0e-5, 3.0)] {
            let (bottom, top) = log_axis_range(lo, hi);
            let power = bottom.log10();
            assert!((power - power.round()).abs() < 1e-9, "{bottom} for {lo}");
            assert!(
                bottom <= lo / 1.5 && bottom > lo / 15.0,
                "{bottom} for {lo}"
            );
            assert!(top >= hi);
        }
    }

    #[test]
    fn the_front_keeps_only_unbeaten_points() {
        let p = |x: f64, y: f64| (x, y, String::new());
        let points = vec![
            p(1.0, 5.0),
            p(2.0, 3.0),
            p(3.0, 4.0),
            p(4.0, 1.0),
            p(f64::NAN, 0.1),
        ];
        assert_eq!(pareto_front(&points), vec![0, 1, 3]);
    }
}
