//! `--plot FILE.svg`: the runs of `scene`, `profile`, `life` and `accuracy` as SVG
//! charts (`plotters`, SVG backend only).
//!
//! * [`force_vs_depth`] (`scene`): the measured force against insertion depth, insertion
//!   and extraction in their own colours, the four contact phases shaded, the guard's
//!   envelope (the limit in force at each depth) and hard limit, and the events: the
//!   trip (first over-limit sample), rejected spikes, faults;
//! * [`profile`] (`profile`): N1–N4 against time with the phases shaded, for any rows of
//!   the `t_s,phase,n1_n,n2_n,n3_n,n4_n` CSV;
//! * [`wear_vs_cycles`] (`life`): the odometer's wear against cycles, Eq. 17, and with
//!   readings the readings, the estimate and its band;
//! * [`error_vs_rate`] (`accuracy`): the stroke-integral error against the sample rate.
//!
//! Text is written as SVG `<text>` (no font is read: the viewer renders it), so no
//! system library is needed, and the same inputs give the same bytes.

use std::error::Error;
use std::path::Path;

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use docking_logic::guard::{GuardConfig, OverloadGuard};
use docking_logic::profile::{BOUNDARY_UM, STROKE_UM};

use crate::scene::{SceneReport, TraceEvent, TraceEventKind, TraceSample, TraceStroke};

/// A chart's size, pixels.
pub const SIZE: (u32, u32) = (1100, 600);

/// Width kept right of the plotting area for the legend, pixels.
const LEGEND_W: u32 = 290;

/// A plot that could not be written: `path: reason`, one line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlotError(pub String);

impl std::fmt::Display for PlotError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl Error for PlotError {}

impl From<PlotError> for crate::cli::UsageError {
    fn from(e: PlotError) -> Self {
        crate::cli::UsageError(format!("--plot {e}"))
    }
}

type DrawResult = Result<(), Box<dyn Error>>;
type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// How a legend entry is drawn.
#[derive(Clone, Copy, Debug)]
enum Mark {
    /// A line of this colour and width.
    Line(RGBColor, u32),
    /// A dashed line.
    Dashed(RGBColor, u32),
    /// A circle, filled or not.
    Dot(RGBColor, bool),
    /// A cross (the trip).
    Cross(RGBColor),
    /// A triangle (a fault).
    Triangle(RGBColor),
    /// A shaded band.
    Band(RGBColor),
}

/// The legend, drawn right of the plotting area (never over the data).
#[derive(Default)]
struct Legend(Vec<(String, Mark)>);

impl Legend {
    fn add(&mut self, label: impl Into<String>, mark: Mark) {
        self.0.push((label.into(), mark));
    }

    fn draw(&self, area: &Area<'_>) -> DrawResult {
        let style = font(13).pos(Pos::new(HPos::Left, VPos::Center));
        for (i, (label, mark)) in self.0.iter().enumerate() {
            let (x, y) = (8, 24 + 24 * i as i32);
            match *mark {
                Mark::Line(c, w) => {
                    area.draw(&PathElement::new([(x, y), (x + 26, y)], c.stroke_width(w)))?
                }
                Mark::Dashed(c, w) => {
                    for k in 0..3 {
                        area.draw(&PathElement::new(
                            [(x + 10 * k, y), (x + 10 * k + 6, y)],
                            c.stroke_width(w),
                        ))?;
                    }
                }
                Mark::Dot(c, filled) => area.draw(&Circle::new(
                    (x + 13, y),
                    4,
                    if filled {
                        c.filled()
                    } else {
                        c.stroke_width(2)
                    },
                ))?,
                Mark::Cross(c) => area.draw(&Cross::new((x + 13, y), 6, c.stroke_width(3)))?,
                Mark::Triangle(c) => area.draw(&TriangleMarker::new((x + 13, y), 7, c.filled()))?,
                Mark::Band(c) => {
                    area.draw(&Rectangle::new([(x, y - 6), (x + 26, y + 6)], c.filled()))?
                }
            }
            area.draw(&Text::new(label.as_str(), (x + 36, y), style.clone()))?;
        }
        Ok(())
    }
}

/// Draw a chart titled `title` with `draw` (given the plotting side and the legend to
/// fill) on a white page of [`SIZE`], the legend on the right, and write the SVG to
/// `path`.
fn render(
    path: &Path,
    title: &str,
    draw: impl FnOnce(&Area<'_>, &mut Legend) -> DrawResult,
) -> Result<(), PlotError> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        let drawn = (|| -> DrawResult {
            root.fill(&WHITE)?;
            let body = root.titled(title, font(20))?;
            let (plot, side) = body.split_horizontally(SIZE.0 - LEGEND_W);
            let mut legend = Legend::default();
            draw(&plot, &mut legend)?;
            legend.draw(&side)?;
            root.present()?;
            Ok(())
        })();
        drawn.map_err(|e| PlotError(format!("{}: {}", path.display(), one_line(&e))))?;
    }
    std::fs::write(path, svg).map_err(|e| PlotError(format!("{}: {e}", path.display())))
}

fn one_line(e: &dyn std::fmt::Display) -> String {
    e.to_string().replace(['\n', '\r'], " ")
}

/// Phase shading, phases 1–4.
const PHASE_FILL: [RGBColor; 4] = [
    RGBColor(232, 240, 250),
    RGBColor(250, 243, 226),
    RGBColor(233, 246, 233),
    RGBColor(245, 234, 246),
];
const INSERTION: RGBColor = RGBColor(31, 119, 180);
const EXTRACTION: RGBColor = RGBColor(44, 160, 44);
const OTHER: RGBColor = RGBColor(140, 140, 140);
const ENVELOPE: RGBColor = RGBColor(214, 39, 40);
const HARD: RGBColor = RGBColor(120, 0, 0);
const TRIP: RGBColor = RGBColor(200, 0, 0);
const SPIKE: RGBColor = RGBColor(255, 127, 14);
const FAULT: RGBColor = RGBColor(118, 42, 131);
const N_COLOURS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
];
const MODEL: RGBColor = RGBColor(90, 90, 90);
const ODOMETER: RGBColor = RGBColor(31, 119, 180);
const ESTIMATE: RGBColor = RGBColor(214, 39, 40);
const BAND: RGBColor = RGBColor(248, 200, 200);
const READING: RGBColor = RGBColor(0, 0, 0);

fn font(size: u32) -> TextStyle<'static> {
    ("sans-serif", size).into_font().color(&BLACK)
}

/// A tick label: up to 6 significant decimals, no trailing zeros.
fn tick(v: f64) -> String {
    let s = format!("{v:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    match s {
        "" | "-0" => "0".into(),
        s => s.to_string(),
    }
}

/// `x` signed, to 3 significant digits (`+0.000263`, `-0.0152`, `+0.263`).
fn signed3(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let decimals = (2 - x.abs().log10().floor() as i32).clamp(0, 12) as usize;
    format!("{x:+.decimals$}")
}

/// The guard's envelope as a step line over the stroke, (depth mm, limit N): the limit
/// in force at each depth of the default configuration, as the controller uses it.
pub fn guard_envelope() -> Vec<(f64, f64)> {
    guard_envelope_of(&GuardConfig::DEFAULT)
}

/// [`guard_envelope`] of the configuration `cfg` (another machine's, commissioned).
pub fn guard_envelope_of(cfg: &GuardConfig) -> Vec<(f64, f64)> {
    let g = OverloadGuard::new(*cfg);
    let mut v: Vec<(f64, f64)> = Vec::new();
    let step = 100;
    let mut d = 0;
    while d < STROKE_UM {
        let l = g.limit_mn(Some(d)) as f64 / 1000.0;
        let (x0, x1) = (d as f64 / 1000.0, (d + step).min(STROKE_UM) as f64 / 1000.0);
        match v.last_mut() {
            // The same level: the step goes on.
            Some(last) if last.1 == l => last.0 = x1,
            // A new level: up or down at x0 (the last point is at x0), then along.
            _ => v.extend([(x0, l), (x1, l)]),
        }
        d += step;
    }
    v
}

/// The guard's hard limit (any state), N.
pub fn hard_limit_n() -> f64 {
    GuardConfig::DEFAULT.hard_limit_mn as f64 / 1000.0
}

/// Phase bands over depth, mm: `[start, end)` of phases 1–4.
fn depth_bands() -> [(f64, f64); 4] {
    let b = BOUNDARY_UM.map(|x| x as f64 / 1000.0);
    [
        (0.0, b[0]),
        (b[0], b[1]),
        (b[1], b[2]),
        (b[2], STROKE_UM as f64 / 1000.0),
    ]
}

/// Shade `bands` (x from–to, phase 1–4) over the full height, labelled at the top.
fn shade_phases<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    bands: &[(f64, f64, u8)],
    y: (f64, f64),
) -> DrawResult
where
    DB::ErrorType: 'static,
{
    let (y0, y1) = y;
    for &(x0, x1, p) in bands {
        let fill = PHASE_FILL[usize::from(p.clamp(1, 4) - 1)];
        chart.draw_series(std::iter::once(Rectangle::new(
            [(x0, y0), (x1, y1)],
            fill.filled(),
        )))?;
        chart.draw_series(std::iter::once(
            EmptyElement::at((x0, y1)) + Text::new(format!("phase {p}"), (4, 4), font(13)),
        ))?;
    }
    Ok(())
}

/// `items` cut into runs (each drawn as its own polyline) where `split(prev, next)`.
fn pieces<T: Copy>(items: &[T], split: impl Fn(&T, &T) -> bool) -> Vec<&[T]> {
    let mut out = Vec::new();
    let mut start = 0;
    for i in 1..items.len() {
        if split(&items[i - 1], &items[i]) {
            out.push(&items[start..i]);
            start = i;
        }
    }
    if start < items.len() {
        out.push(&items[start..]);
    }
    out
}

/// Force against insertion depth for a scene: the trace's samples as lines (insertion,
/// extraction, other states), the phases shaded, `envelope` ((depth mm, limit N), from
/// [`guard_envelope`]) and the hard limit, and the events as markers with labels. The
/// rejected spikes' legend entry reads `spike_label` when given (the counts behind the
/// markers), else the number of markers.
pub fn force_vs_depth(
    path: &Path,
    title: &str,
    trace: &[TraceSample],
    events: &[TraceEvent],
    envelope: &[(f64, f64)],
    hard_limit_n: f64,
    spike_label: Option<&str>,
) -> Result<(), PlotError> {
    let stroke_mm = STROKE_UM as f64 / 1000.0;
    let depths = trace
        .iter()
        .map(|s| s.depth_mm)
        .chain(events.iter().map(|e| e.depth_mm));
    let (dmin, dmax) = depths.fold((-2.0f64, stroke_mm + 1.0), |(a, b), d| {
        (a.min(d - 0.5), b.max(d + 0.5))
    });
    let forces = trace
        .iter()
        .map(|s| s.force_n)
        .chain(events.iter().map(|e| e.force_n));
    let (fmin, fmax) = forces.fold((0.0f64, hard_limit_n), |(a, b), f| (a.min(f), b.max(f)));
    let y = (
        fmin - 0.05 * (fmax - fmin),
        fmax + 0.12 * (fmax - fmin.min(0.0)),
    );
    render(path, title, |root, legend| {
        let mut chart = ChartBuilder::on(root)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(dmin..dmax, y.0..y.1)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("insertion depth (mm)")
            .y_desc("force (N)")
            .axis_desc_style(font(15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()?;
        let bands: Vec<(f64, f64, u8)> = depth_bands()
            .iter()
            .zip(1u8..)
            .map(|(&(a, b), p)| (a, b, p))
            .collect();
        shade_phases(&mut chart, &bands, y)?;
        chart.draw_series(LineSeries::new(
            envelope.iter().copied(),
            ENVELOPE.stroke_width(2),
        ))?;
        legend.add("guard envelope (limit in force)", Mark::Line(ENVELOPE, 2));
        chart.draw_series(DashedLineSeries::new(
            [(dmin, hard_limit_n), (dmax, hard_limit_n)],
            8,
            5,
            HARD.stroke_width(2),
        ))?;
        legend.add(
            format!("hard limit {} N", tick(hard_limit_n)),
            Mark::Dashed(HARD, 2),
        );
        let mut labelled = [false; 3];
        for piece in pieces(trace, |a, b| {
            a.stroke != b.stroke || (a.depth_mm - b.depth_mm).abs() > 0.5
        }) {
            let (i, colour, name) = match piece[0].stroke {
                TraceStroke::Insertion => (0, INSERTION, "insertion (measured)"),
                TraceStroke::Extraction => (1, EXTRACTION, "extraction (measured)"),
                TraceStroke::Other => (2, OTHER, "other states (hold, back-off)"),
            };
            let width = if i == 2 { 1 } else { 2 };
            chart.draw_series(LineSeries::new(
                piece.iter().map(|s| (s.depth_mm, s.force_n)),
                colour.stroke_width(width),
            ))?;
            if !labelled[i] {
                labelled[i] = true;
                legend.add(name, Mark::Line(colour, width));
            }
        }
        let spikes: Vec<&TraceEvent> = events
            .iter()
            .filter(|e| e.kind == TraceEventKind::SpikeRejected)
            .collect();
        if !spikes.is_empty() {
            chart.draw_series(
                spikes
                    .iter()
                    .map(|e| Circle::new((e.depth_mm, e.force_n), 4, SPIKE.stroke_width(2))),
            )?;
            legend.add(
                spike_label.map_or_else(
                    || format!("rejected spike ({})", spikes.len()),
                    str::to_string,
                ),
                Mark::Dot(SPIKE, false),
            );
        }
        // Labels run away from the nearer side of the chart.
        let right_half = |x: f64| x > (dmin + dmax) / 2.0;
        let label_side = |x: f64| {
            let h = if right_half(x) {
                HPos::Right
            } else {
                HPos::Left
            };
            Pos::new(h, VPos::Top)
        };
        let mut trip_labelled = false;
        let mut fault_labelled = false;
        for e in events {
            let at = (e.depth_mm, e.force_n);
            match e.kind {
                TraceEventKind::SpikeRejected => {}
                TraceEventKind::Trip => {
                    chart.draw_series(std::iter::once(
                        EmptyElement::at(at)
                            + Cross::new((0, 0), 9, TRIP.stroke_width(3))
                            + Text::new(
                                format!("trip: {:.1} N at {:.2} mm", e.force_n, e.depth_mm),
                                (0, -44),
                                font(14).color(&TRIP).pos(label_side(e.depth_mm)),
                            ),
                    ))?;
                    if !trip_labelled {
                        trip_labelled = true;
                        legend.add("trip (first over-limit sample)", Mark::Cross(TRIP));
                    }
                }
                TraceEventKind::Fault(kind) => {
                    chart.draw_series(std::iter::once(
                        EmptyElement::at(at)
                            + TriangleMarker::new((0, 0), 9, FAULT.filled())
                            + Text::new(
                                format!("fault: {kind} ({:.2} mm, {:.1} N)", e.depth_mm, e.force_n),
                                (if right_half(e.depth_mm) { -14 } else { 14 }, 10),
                                font(14).color(&FAULT).pos(label_side(e.depth_mm)),
                            ),
                    ))?;
                    if !fault_labelled {
                        fault_labelled = true;
                        legend.add("fault latched", Mark::Triangle(FAULT));
                    }
                }
            }
        }
        Ok(())
    })
}

/// [`force_vs_depth`] of a scene run ([`crate::scene::run_traced`]).
pub fn scene(
    path: &Path,
    report: &SceneReport,
    trace: &crate::scene::SceneTrace,
    guard: &GuardConfig,
    variant: &str,
) -> Result<(), PlotError> {
    let title = format!(
        "scene {}: force against insertion depth (cycle {}, {} SPS, seed {}; {variant})",
        report.scene, trace.cycle, report.rate_sps, report.seed
    );
    // The counts are the safety kernel's, as the report's `spikes_rejected`: the traced
    // cycle's and the run's (a marker is drawn for those in the traced depths).
    let drawn = trace
        .events
        .iter()
        .filter(|e| e.kind == TraceEventKind::SpikeRejected)
        .count() as u32;
    let spike_label = format!(
        "rejected spike ({}{} in cycle {}; {} in the run)",
        if drawn == trace.spikes_rejected_in_cycle {
            String::new()
        } else {
            format!("{drawn} drawn of ")
        },
        trace.spikes_rejected_in_cycle,
        trace.cycle,
        report.spikes_rejected
    );
    force_vs_depth(
        path,
        &title,
        &trace.samples,
        &trace.events,
        &guard_envelope_of(guard),
        guard.hard_limit_mn as f64 / 1000.0,
        Some(&spike_label),
    )
}

/// Most points drawn per force curve (more rows are thinned, keeping every phase
/// change: the jumps stay sharp).
const PROFILE_MAX_POINTS: usize = 4_000;

/// N1–N4 against `x` (`x_desc` names it, with its unit) from rows `(x, phase 1–4, [N1,
/// N2, N3, N4] in N)`, the phases shaded by the rows' own phase column.
pub fn profile(
    path: &Path,
    title: &str,
    x_desc: &str,
    rows: &[(f64, u8, [f64; 4])],
) -> Result<(), PlotError> {
    let stride = rows.len().div_ceil(PROFILE_MAX_POINTS).max(1);
    let kept: Vec<(f64, u8, [f64; 4])> = rows
        .iter()
        .enumerate()
        .filter(|&(i, r)| {
            i % stride == 0
                || i + 1 == rows.len()
                || rows.get(i.wrapping_sub(1)).is_some_and(|p| p.1 != r.1)
                || rows.get(i + 1).is_some_and(|n| n.1 != r.1)
        })
        .map(|(_, r)| *r)
        .collect();
    let (x0, x1) = match (kept.first(), kept.last()) {
        (Some(a), Some(b)) if b.0 > a.0 => (a.0, b.0),
        (Some(a), _) => (a.0, a.0 + 1.0),
        _ => (0.0, 1.0),
    };
    let (fmin, fmax) = kept
        .iter()
        .flat_map(|r| r.2)
        .fold((0.0f64, 1.0f64), |(a, b), f| (a.min(f), b.max(f)));
    let y = (fmin - 0.04 * (fmax - fmin), fmax + 0.12 * (fmax - fmin));
    let mut bands: Vec<(f64, f64, u8)> = Vec::new();
    for r in &kept {
        match bands.last_mut() {
            Some(b) if b.2 == r.1 => b.1 = r.0,
            Some(b) => {
                b.1 = r.0;
                bands.push((r.0, r.0, r.1));
            }
            None => bands.push((r.0, r.0, r.1)),
        }
    }
    render(path, title, |root, legend| {
        let mut chart = ChartBuilder::on(root)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y.0..y.1)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc(x_desc)
            .y_desc("force (N)")
            .axis_desc_style(font(15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()?;
        shade_phases(&mut chart, &bands, y)?;
        let names = [
            "N1 (support)",
            "N2 (support)",
            "N3 (rod–cone)",
            "N4 (second contact)",
        ];
        for (k, (name, colour)) in names.iter().zip(N_COLOURS).enumerate() {
            // One polyline per phase: a jump is drawn as a jump, not a slope.
            let mut first = true;
            for piece in pieces(&kept, |a, b| a.1 != b.1) {
                chart.draw_series(LineSeries::new(
                    piece.iter().map(|r| (r.0, r.2[k])),
                    colour.stroke_width(2),
                ))?;
                if first {
                    first = false;
                    legend.add(*name, Mark::Line(colour, 2));
                }
            }
        }
        Ok(())
    })
}

/// [`profile`] of `hil-sim profile`'s rows (Eq. 7 at `rate_hz`, one stroke).
pub fn eq7_profile(
    path: &Path,
    rate_hz: f64,
    stroke: crate::profile_cmd::Stroke,
) -> Result<(), PlotError> {
    use crate::profile_cmd::{row, sample_count, Stroke};
    let rows: Vec<(f64, u8, [f64; 4])> = (0..sample_count(rate_hz))
        .map(|k| {
            let (t, p, f) = row(k, rate_hz, stroke);
            (t, p.number(), [f.n1_n, f.n2_n, f.n3_n, f.n4_n])
        })
        .collect();
    let (which, x_desc) = match stroke {
        Stroke::Insert => ("insertion", "time from the start of compliant contact (s)"),
        Stroke::Extract => ("extraction", "time from the start of the extraction (s)"),
    };
    profile(
        path,
        &format!(
            "Eq. 7 contact forces, {which} stroke at v0 = 1.2 mm/s, {} Hz",
            tick(rate_hz)
        ),
        x_desc,
        &rows,
    )
}

/// [`profile`] of `hil-sim profile --model plant`'s rows.
pub fn plant_profile(
    path: &Path,
    plant: &crate::plant::Plant,
    rate_hz: f64,
    stroke: crate::profile_cmd::Stroke,
) -> Result<(), PlotError> {
    use crate::profile_cmd::{sample_count, Stroke};
    let rows: Vec<(f64, u8, [f64; 4])> = (0..sample_count(rate_hz))
        .map(|k| {
            let t = k as f64 / rate_hz;
            let t_ins = match stroke {
                Stroke::Insert => t,
                Stroke::Extract => docking_logic::profile::STROKE_S - t,
            };
            let p = plant.at_time(t_ins);
            (t, p.phase, [p.n1_n, p.n2_n, p.n3_n, p.n4_n])
        })
        .collect();
    let which = match stroke {
        Stroke::Insert => "insertion",
        Stroke::Extract => "extraction",
    };
    let p = plant.params();
    profile(
        path,
        &format!(
            "plant contact forces, {which} stroke: m {} kg, µ1 {}, µ2 {}, γ {}°, θ0 {}°, v_model {} mm/s",
            p.mass_kg, p.mu1, p.mu2, p.gamma_deg, p.theta0_deg, p.v_model_mm_s
        ),
        "time on Eq. 7's axis (s)",
        &rows,
    )
}

/// What [`wear_vs_cycles`] draws.
#[derive(Clone, Debug, Default)]
pub struct WearCurves {
    /// Title.
    pub title: String,
    /// Cycles of the run (the x axis ends there).
    pub cycles: u32,
    /// The odometer's wear, (cone cycle, mm).
    pub odometer: Vec<(f64, f64)>,
    /// The estimate, (cone cycle, estimate mm, band low mm, band high mm); empty without
    /// readings.
    pub estimate: Vec<(f64, f64, f64, f64)>,
    /// The micrometer readings, (cone cycle, wear mm = bore − baseline).
    pub readings: Vec<(f64, f64)>,
    /// The wear limit, mm.
    pub limit_mm: f64,
    /// The material's wear factor relative to ZQSn5-2 (Eq. 17's material): its model
    /// curve is Eq. 17 at `k·m`.
    pub wear_factor: f64,
    /// The material's name.
    pub material: String,
    /// The cycle at which the controller found the cone worn out and refused to dock it
    /// again (by the most worn of the model, the estimate's upper band and the last
    /// reading), if the run got there.
    pub limit_reached_at: Option<u32>,
}

/// Eq. 17 (He et al. 2025): wear depth after `m` cycles at nominal load, mm (negative
/// below ~2 cycles: it is a fit).
pub fn eq17_mm(m: f64) -> f64 {
    0.01372 * m.powf(0.3813) - 0.01774
}

/// Wear against cycles (`life`): the odometer's wear, Eq. 17, the wear limit, and with
/// readings the readings, the estimate and its band.
pub fn wear_vs_cycles(path: &Path, c: &WearCurves) -> Result<(), PlotError> {
    let n = c.cycles.max(2) as f64;
    // Eq. 17 from 2 cycles (where it turns positive), denser at the start.
    let model: Vec<(f64, f64)> = (0..=400)
        .map(|i| {
            let u = i as f64 / 400.0;
            let m = 2.0 + (n - 2.0) * u * u;
            (m, eq17_mm(m * c.wear_factor).max(0.0))
        })
        .collect();
    let ymax_data = c
        .odometer
        .iter()
        .map(|p| p.1)
        .chain(model.iter().map(|p| p.1))
        .chain(c.readings.iter().map(|p| p.1))
        .chain(c.estimate.iter().map(|p| p.3))
        .fold(0.0f64, f64::max);
    let show_limit = c.limit_mm <= ymax_data * 1.3;
    let ymax = if show_limit {
        ymax_data.max(c.limit_mm)
    } else {
        ymax_data
    } * 1.12
        + 1e-6;
    let ymin = c
        .readings
        .iter()
        .map(|p| p.1)
        .fold(0.0f64, f64::min)
        .min(0.0)
        - 0.02 * ymax;
    render(path, &c.title, |root, legend| {
        let mut chart = ChartBuilder::on(root)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..n, ymin..ymax)?;
        chart
            .configure_mesh()
            .light_line_style(WHITE.mix(0.0))
            .bold_line_style(BLACK.mix(0.08))
            .x_desc("cone cycles")
            .y_desc("wear depth (mm)")
            .axis_desc_style(font(15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()?;
        if !c.estimate.is_empty() {
            let band: Vec<(f64, f64)> = c
                .estimate
                .iter()
                .map(|p| (p.0, p.3))
                .chain(c.estimate.iter().rev().map(|p| (p.0, p.2)))
                .collect();
            chart.draw_series(std::iter::once(Polygon::new(band, BAND.filled())))?;
            legend.add("estimate band (≈ 95 %)", Mark::Band(BAND));
        }
        if show_limit {
            chart.draw_series(DashedLineSeries::new(
                [(0.0, c.limit_mm), (n, c.limit_mm)],
                8,
                5,
                HARD.stroke_width(2),
            ))?;
            legend.add(
                format!("wear limit {} mm", tick(c.limit_mm)),
                Mark::Dashed(HARD, 2),
            );
        }
        if let Some(at) = c.limit_reached_at {
            let x = at as f64;
            chart.draw_series(std::iter::once(PathElement::new(
                [(x, ymin), (x, ymax)],
                HARD.stroke_width(1),
            )))?;
            chart.draw_series(std::iter::once(
                EmptyElement::at((x, ymin))
                    + Text::new(
                        format!("worn out at cycle {at}"),
                        (-6, -22),
                        font(13).color(&HARD).pos(Pos::new(HPos::Right, VPos::Top)),
                    ),
            ))?;
            legend.add(
                format!("worn out: docking refused (cycle {at})"),
                Mark::Line(HARD, 1),
            );
        }
        let model_label = if (c.wear_factor - 1.0).abs() < 1e-9 {
            "Eq. 17: 0.01372·m^0.3813 − 0.01774 mm".to_string()
        } else {
            format!("Eq. 17 at k·m, k = {:.4} ({})", c.wear_factor, c.material)
        };
        chart.draw_series(DashedLineSeries::new(
            model.iter().copied(),
            6,
            4,
            MODEL.stroke_width(2),
        ))?;
        legend.add(model_label, Mark::Dashed(MODEL, 2));
        chart.draw_series(LineSeries::new(
            c.odometer.iter().copied(),
            ODOMETER.stroke_width(2),
        ))?;
        legend.add(
            format!("odometer ({})", c.material),
            Mark::Line(ODOMETER, 2),
        );
        if !c.estimate.is_empty() {
            chart.draw_series(LineSeries::new(
                c.estimate.iter().map(|p| (p.0, p.1)),
                ESTIMATE.stroke_width(2),
            ))?;
            legend.add(
                "estimate (model taught by the readings)",
                Mark::Line(ESTIMATE, 2),
            );
        }
        if !c.readings.is_empty() {
            chart.draw_series(
                c.readings
                    .iter()
                    .map(|&p| Circle::new(p, 4, READING.filled())),
            )?;
            legend.add(
                format!("micrometer readings ({})", c.readings.len()),
                Mark::Dot(READING, true),
            );
        }
        Ok(())
    })
}

/// [`wear_vs_cycles`] of a life run with its curve ([`crate::life::run_with_curve`]).
pub fn life(
    path: &Path,
    opts: &crate::life::LifeOptions,
    report: &crate::life::LifeReport,
    curve: &[crate::life::LifePoint],
) -> Result<(), PlotError> {
    use docking_logic::odometer::{wear_factor_q32, WearConfig};
    let mm = |nm: u32| nm as f64 / 1e6;
    let baseline = opts.readings.first().map_or(0, |r| r.1);
    let c = WearCurves {
        title: format!(
            "life: wear against cycles ({}, {} cycles run, {} SPS{})",
            report.material.name(),
            report.cycles_run,
            opts.rate_sps,
            if opts.readings.is_empty() {
                String::new()
            } else {
                format!(", {} readings", opts.readings.len())
            }
        ),
        cycles: opts.cycles,
        odometer: curve
            .iter()
            .map(|p| (p.cycle as f64, mm(p.wear_nm)))
            .collect(),
        estimate: curve
            .iter()
            .filter_map(|p| {
                let e = p.estimate?;
                Some((p.cycle as f64, mm(e.wear_nm), mm(e.low_nm), mm(e.high_nm)))
            })
            .collect(),
        readings: opts
            .readings
            .iter()
            .filter(|r| r.0 <= report.cycles_run)
            .map(|&(c, b)| (c as f64, (b as f64 - baseline as f64) / 1000.0))
            .collect(),
        limit_mm: WearConfig::DEFAULT.limit_nm as f64 / 1e6,
        wear_factor: wear_factor_q32(opts.material) as f64 / 4_294_967_296.0,
        material: opts.material.name().to_string(),
        limit_reached_at: report.limit_reached.then_some(report.life_cycles),
    };
    wear_vs_cycles(path, &c)
}

/// Stroke-integral error against sample rate (`accuracy`): each series is a name and
/// its (rate SPS, signed error %) points; drawn as |error| on log–log axes, each point
/// labelled with its signed value.
pub fn error_vs_rate(
    path: &Path,
    title: &str,
    series: &[(&str, Vec<(f64, f64)>)],
) -> Result<(), PlotError> {
    const FLOOR: f64 = 1e-5;
    let pts = || series.iter().flat_map(|s| s.1.iter());
    let (r0, r1) = pts().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (r0, r1) = if r0 <= r1 { (r0, r1) } else { (10.0, 1000.0) };
    let (e0, e1) = pts().fold((f64::MAX, f64::MIN), |(a, b), p| {
        let e = p.1.abs().max(FLOOR);
        (a.min(e), b.max(e))
    });
    let (e0, e1) = if e0 <= e1 { (e0, e1) } else { (0.001, 1.0) };
    render(path, title, |root, legend| {
        let mut chart = ChartBuilder::on(root)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(
                // Room on the right for the last rate's labels.
                (r0 / 1.6..r1 * 5.0).log_scale(),
                (e0 / 4.0..e1 * 4.0).log_scale(),
            )?;
        chart
            .configure_mesh()
            .light_line_style(WHITE.mix(0.0))
            .bold_line_style(BLACK.mix(0.08))
            .x_desc("load-cell sample rate (samples/s)")
            .y_desc("|stroke-integral error| vs exact Eq. 7 (%)")
            .axis_desc_style(font(15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()?;
        for (k, (name, pts)) in series.iter().enumerate() {
            let colour = N_COLOURS[k % N_COLOURS.len()];
            let dy = if k % 2 == 0 { -22 } else { 8 };
            let p: Vec<(f64, f64)> = pts.iter().map(|&(r, e)| (r, e.abs().max(FLOOR))).collect();
            chart.draw_series(LineSeries::new(p.iter().copied(), colour.stroke_width(2)))?;
            legend.add(*name, Mark::Line(colour, 2));
            chart.draw_series(pts.iter().zip(&p).map(|(&(r, e), &at)| {
                EmptyElement::at(at)
                    + Circle::new((0, 0), 4, colour.filled())
                    + Text::new(
                        format!("{} SPS: {} %", tick(r), signed3(e)),
                        (6, dy),
                        font(12).color(&colour),
                    )
            }))?;
        }
        Ok(())
    })
}

/// [`error_vs_rate`] of `hil-sim accuracy`'s rate table.
pub fn accuracy(path: &Path, r: &crate::accuracy::AccuracyReport) -> Result<(), PlotError> {
    let ins = r
        .rows
        .iter()
        .map(|row| (row.strokes.rate_sps as f64, row.strokes.insertion_err_pct()))
        .collect();
    let ext = r
        .rows
        .iter()
        .map(|row| {
            (
                row.strokes.rate_sps as f64,
                row.strokes.extraction_err_pct(),
            )
        })
        .collect();
    error_vs_rate(
        path,
        "accuracy: odometer stroke integral against the exact Eq. 7 stroke, by sample rate",
        &[("insertion stroke", ins), ("extraction stroke", ext)],
    )
}

/// `hil-sim plot-curve`: a `curve --json` dump (the firmware's, issue 34) against its
/// evaluation objects and, when given, its cone's reference (a `curve ref --json`
/// dump): force against insertion depth, the phases shaded, each bin's band as a box
/// (the phase bands), the entry window, the phase-4 plateau, the end force and the
/// extraction's peak as boxes, the insertion's and the extraction's bin means (and
/// peaks, thin), the reference's insertion, and the first failed object marked.
pub fn curve(
    path: &Path,
    dump: &crate::curvedump::CurveDump,
    reference: Option<&crate::curvedump::CurveDump>,
) -> Result<(), PlotError> {
    const BOX: RGBColor = RGBColor(214, 39, 40);
    const REFERENCE: RGBColor = RGBColor(90, 90, 90);
    let verdict = |k: usize| {
        let s = &dump.strokes[k];
        match (&s.verdict, &s.failed) {
            (Some(v), Some((o, _, _))) => format!("{v} ({o})"),
            (Some(v), None) => v.clone(),
            (None, _) => "not judged".into(),
        }
    };
    let title = match dump.which.as_str() {
        "ref" => "docking signature: the cone's reference".to_string(),
        w => format!(
            "docking signature ({w}): cycle {}, insertion {}, extraction {}",
            dump.cycle,
            verdict(0),
            verdict(1)
        ),
    };
    let n = dump.band_low_n.len();
    let centre = |i: usize| (dump.edge_mm(i) + dump.edge_mm(i + 1)) / 2.0;
    let all = dump
        .strokes
        .iter()
        .flat_map(|s| s.peak_n.iter().chain(s.mean_n.iter()))
        .filter_map(|x| *x)
        .chain(dump.band_high_n.iter().copied())
        .chain([dump.ext_peak.high_n]);
    let fmax = all.fold(0.0f64, f64::max);
    let y = (-5.0, fmax * 1.12 + 5.0);
    let x = (-0.5, dump.stroke_mm + 0.5);
    render(path, &title, |root, legend| {
        let mut chart = ChartBuilder::on(root)
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(x.0..x.1, y.0..y.1)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("insertion depth (mm)")
            .y_desc("force (N)")
            .axis_desc_style(font(15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()?;
        let mut edges = vec![0.0];
        edges.extend(dump.phases_mm.iter().copied());
        edges.push(dump.stroke_mm);
        let bands: Vec<(f64, f64, u8)> = edges
            .windows(2)
            .zip(1u8..)
            .map(|(w, p)| (w[0], w[1], p))
            .collect();
        shade_phases(&mut chart, &bands, y)?;
        // The phase bands: one box per bin.
        chart.draw_series((0..n).map(|i| {
            Rectangle::new(
                [
                    (dump.edge_mm(i), dump.band_low_n[i]),
                    (dump.edge_mm(i + 1), dump.band_high_n[i]),
                ],
                BOX.mix(0.12).filled(),
            )
        }))?;
        legend.add("phase bands (per bin)", Mark::Band(RGBColor(250, 215, 215)));
        // The boxes: entry window, plateau, end, extraction peak.
        let boxes = [
            (
                "entry",
                crate::curvedump::Box4 {
                    from_mm: 0.0,
                    to_mm: dump.entry.0,
                    low_n: dump.entry.1,
                    high_n: dump.band_high_n.first().copied().unwrap_or(dump.entry.1),
                },
            ),
            ("plateau", dump.plateau),
            ("end", dump.end),
            ("ext. peak", dump.ext_peak),
        ];
        for (name, b) in boxes {
            chart.draw_series(std::iter::once(Rectangle::new(
                [(b.from_mm, b.low_n), (b.to_mm, b.high_n)],
                BOX.stroke_width(2),
            )))?;
            chart.draw_series(std::iter::once(
                EmptyElement::at((b.from_mm, b.high_n))
                    + Text::new(name.to_string(), (2, -16), font(13).color(&BOX)),
            ))?;
        }
        legend.add(
            "objects (entry, plateau, end, extraction peak)",
            Mark::Line(BOX, 2),
        );
        for (k, colour, name) in [(0, INSERTION, "insertion"), (1, EXTRACTION, "extraction")] {
            let s = &dump.strokes[k];
            let series = |v: &[Option<f64>]| -> Vec<(f64, f64)> {
                (0..n)
                    .filter_map(|i| v.get(i).copied().flatten().map(|f| (centre(i), f)))
                    .collect()
            };
            chart.draw_series(LineSeries::new(
                series(&s.peak_n),
                colour.mix(0.4).stroke_width(1),
            ))?;
            chart.draw_series(LineSeries::new(series(&s.mean_n), colour.stroke_width(2)))?;
            legend.add(
                format!("{name}: bin mean (peak, thin)"),
                Mark::Line(colour, 2),
            );
            if let Some((object, figure, at)) = &s.failed {
                if figure.is_finite() && at.is_finite() && *figure > y.0 && *figure < y.1 {
                    chart.draw_series(std::iter::once(
                        EmptyElement::at((*at, *figure))
                            + Cross::new((0, 0), 9, TRIP.stroke_width(3))
                            + Text::new(
                                format!("{name} NOK: {object}"),
                                (10, -24),
                                font(14).color(&TRIP),
                            ),
                    ))?;
                }
            }
        }
        if let Some(r) = reference {
            let pts: Vec<(f64, f64)> = (0..n)
                .filter_map(|i| {
                    r.strokes[0]
                        .mean_n
                        .get(i)
                        .copied()
                        .flatten()
                        .map(|f| (centre(i), f))
                })
                .collect();
            chart.draw_series(DashedLineSeries::new(pts, 6, 4, REFERENCE.stroke_width(2)))?;
            legend.add("reference (insertion, mean)", Mark::Dashed(REFERENCE, 2));
        }
        if dump.strokes.iter().any(|s| s.failed.is_some()) {
            legend.add("first failed object", Mark::Cross(TRIP));
        }
        Ok(())
    })
}
