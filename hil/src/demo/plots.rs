//! The demo's plots, each as PNG and SVG: the top view of every trajectory with ground
//! truth (`trajectories`), each robot's error over time (`error`), and the bytes every
//! robot's team link sent over time (`bytes`).
//!
//! PNG text needs a font file: DejaVu Sans from Debian's `fonts-dejavu-core` (installed by
//! `deploy/setup`), or the file `$DOORSLAM_FONT` names. SVG text needs none.

use std::collections::BTreeMap;
use std::path::Path;

use doorslam_backend::eval::{umeyama, Trajectory};
use plotters::coord::Shift;
use plotters::prelude::*;

use super::config::World;
use super::RunLog;
use crate::flights::robot_name;

type PlotResult<T> = Result<T, String>;

const FONT_PATHS: [&str; 2] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

/// Registers the PNG font once.
fn register_font() -> PlotResult<()> {
    static DONE: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    DONE.get_or_init(|| {
        let path = std::env::var("DOORSLAM_FONT")
            .ok()
            .or_else(|| FONT_PATHS.iter().find(|p| Path::new(p).is_file()).map(|p| p.to_string()))
            .ok_or_else(|| {
                format!(
                    "no font for the PNG plots: install fonts-dejavu-core (deploy/setup does) or set DOORSLAM_FONT (looked in {})",
                    FONT_PATHS.join(", ")
                )
            })?;
        let bytes = std::fs::read(&path).map_err(|e| format!("{path}: {e}"))?;
        // The registry keeps the bytes for the process's lifetime.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| format!("{path}: not a font plotters can read"))
    })
    .clone()
}

/// One colour per robot.
fn colour(r: usize) -> RGBColor {
    const C: [RGBColor; 8] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(23, 190, 207),
    ];
    C[r % C.len()]
}

/// A colour faded towards white (ground truth under the estimate).
fn light(c: RGBColor) -> RGBColor {
    let f = |v: u8| 255 - ((255 - u16::from(v)) * 2 / 5) as u8;
    RGBColor(f(c.0), f(c.1), f(c.2))
}

/// Lines of one plot: (label, colour, dashed, points).
type Lines = Vec<(String, RGBColor, bool, Vec<(f64, f64)>)>;

struct Plot {
    title: String,
    x: String,
    y: String,
    lines: Lines,
    /// Same scale on both axes (a map).
    equal: bool,
}

fn range(lines: &Lines, axis: impl Fn(&(f64, f64)) -> f64) -> (f64, f64) {
    let (lo, hi) = lines
        .iter()
        .flat_map(|l| l.3.iter().map(&axis))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if lo.is_finite() && hi > lo {
        let pad = (hi - lo) * 0.05;
        (lo - pad, hi + pad)
    } else if lo.is_finite() {
        (lo - 1.0, lo + 1.0)
    } else {
        (0.0, 1.0)
    }
}

fn draw_on<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, p: &Plot) -> PlotResult<()>
where
    DB::ErrorType: 'static,
{
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let (mut x0, mut x1) = range(&p.lines, |q| q.0);
    let (mut y0, mut y1) = range(&p.lines, |q| q.1);
    if p.equal {
        let (w, h) = root.dim_in_pixel();
        let scale = ((x1 - x0) / f64::from(w)).max((y1 - y0) / f64::from(h));
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        (x0, x1) = (
            cx - scale * f64::from(w) / 2.0,
            cx + scale * f64::from(w) / 2.0,
        );
        (y0, y1) = (
            cy - scale * f64::from(h) / 2.0,
            cy + scale * f64::from(h) / 2.0,
        );
    }
    let mut chart = ChartBuilder::on(&root)
        .caption(&p.title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(&p.x)
        .y_desc(&p.y)
        .light_line_style(RGBColor(245, 245, 245))
        .bold_line_style(RGBColor(215, 215, 215))
        .label_style(("sans-serif", 14))
        .draw()
        .map_err(e)?;
    for (label, c, dashed, points) in &p.lines {
        let style = ShapeStyle::from(c).stroke_width(if *dashed { 1 } else { 2 });
        let series = if *dashed {
            // Every other segment: a dashed line in both backends.
            let segments: Vec<Vec<(f64, f64)>> = points.chunks(2).map(|s| s.to_vec()).collect();
            chart
                .draw_series(segments.into_iter().map(|s| PathElement::new(s, style)))
                .map_err(e)?
        } else {
            chart
                .draw_series(LineSeries::new(points.iter().copied(), style))
                .map_err(e)?
        };
        let c = *c;
        series
            .label(label.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(e)?;
    root.present().map_err(e)
}

/// Writes `<name>.png` and `<name>.svg`; their file names.
fn save(out: &Path, name: &str, p: &Plot) -> PlotResult<Vec<String>> {
    let size = (960, 720);
    let png = out.join(format!("{name}.png"));
    let svg = out.join(format!("{name}.svg"));
    draw_on(BitMapBackend::new(&png, size).into_drawing_area(), p)?;
    draw_on(SVGBackend::new(&svg, size).into_drawing_area(), p)?;
    Ok(vec![format!("{name}.png"), format!("{name}.svg")])
}

/// Draws the three plots into `out`; the files written.
pub fn draw(
    out: &Path,
    world: &World,
    truth: &[Option<Trajectory>],
    team_errors: &Option<BTreeMap<usize, Vec<(f64, f64)>>>,
    team_pairs: &BTreeMap<usize, (Trajectory, Trajectory)>,
    log: &RunLog,
) -> PlotResult<Vec<String>> {
    register_font()?;
    let mut files = Vec::new();
    let n = world.robots();

    // Top view: ground truth (thin) and the team estimate in the team's frame, aligned
    // once to the ground truth.
    let mut lines: Lines = Vec::new();
    for (r, gt) in truth.iter().enumerate() {
        if let Some(gt) = gt {
            let pts = gt.positions().iter().map(|p| (p.x, p.y)).collect();
            lines.push((
                format!("{} truth", robot_name(r)),
                light(colour(r)),
                true,
                pts,
            ));
        }
    }
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for (gt, est) in team_pairs.values() {
        src.extend(est.positions());
        dst.extend(gt.positions());
    }
    if let Ok(t) = umeyama(&src, &dst, false) {
        for (&r, (_, est)) in team_pairs {
            let pts = est
                .positions()
                .iter()
                .map(|p| {
                    let q = t * p;
                    (q.x, q.y)
                })
                .collect();
            lines.push((
                format!("{} team estimate", robot_name(r)),
                colour(r),
                false,
                pts,
            ));
        }
    }
    files.extend(save(
        out,
        "trajectories",
        &Plot {
            title: "Top view: team estimate (one alignment) and ground truth".into(),
            x: "x (m)".into(),
            y: "y (m)".into(),
            lines,
            equal: true,
        },
    )?);

    // Error over time, in the team's frame.
    let mut lines: Lines = Vec::new();
    if let Some(errors) = team_errors {
        for (&r, e) in errors {
            let t0 = truth
                .get(r)
                .and_then(|t| t.as_ref())
                .and_then(|t| t.timestamps().first().copied())
                .unwrap_or(0.0);
            lines.push((
                robot_name(r).to_string(),
                colour(r),
                false,
                e.iter().map(|(t, v)| (t - t0, *v)).collect(),
            ));
        }
    }
    files.extend(save(
        out,
        "error",
        &Plot {
            title: "Position error of the team estimate (team frame)".into(),
            x: "flight time (s)".into(),
            y: "error (m)".into(),
            lines,
            equal: false,
        },
    )?);

    // Bytes over time.
    let lines: Lines = (0..n)
        .map(|r| {
            (
                robot_name(r).to_string(),
                colour(r),
                false,
                log.bytes_over_time
                    .iter()
                    .map(|(t, b)| (*t, b.get(r).copied().unwrap_or(0) as f64 / 1e3))
                    .collect(),
            )
        })
        .collect();
    files.extend(save(
        out,
        "bytes",
        &Plot {
            title: "Bytes sent by each robot's team link".into(),
            x: "flight time (s)".into(),
            y: "kB sent (payload, cumulative)".into(),
            lines,
            equal: false,
        },
    )?);
    Ok(files)
}
