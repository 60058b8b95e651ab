//! The report figures: line charts with a title, axes with round ticks, a grid and a legend,
//! drawn with the `plotters` crate into an in-memory RGB image (the caller writes the PNG).
//! Text is DejaVu Sans, embedded in the binary and rasterised by plotters' pure-Rust
//! `ab_glyph` path: no system fonts, no fontconfig. Only built with the `figures` feature.
//!
//! What plotters does not decide for us stays here: round ticks at a 1-2-5 step with labels
//! that never read "-0.00" ([`ticks`]), equal aspect for maps, the legend in the corner that
//! hides the fewest data points (raising the top of the y axis where every corner hides some),
//! and the plane a 3-D path is seen from ([`top_view_axes`]).

use duv_core::ImageRgb8;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use plotters::coord::ranged1d::{KeyPointHint, KeyPointWeight, NoDefaultFormatting, Ranged, ValueFormatter};
use plotters::coord::Shift;
use plotters::drawing::IntoDrawingArea;
use plotters::element::{Circle, DashedPathElement, MultiLineText, PathElement, Rectangle};
use plotters::prelude::{
    BitMapBackend, ChartBuilder, Color, DashedLineSeries, DrawingArea, FontStyle, IntoFont, LineSeries, RGBColor,
    SeriesLabelPosition, ShapeStyle, TextStyle,
};
use std::fmt::Display;
use std::ops::Range;
use std::sync::OnceLock;

pub type Rgb = [u8; 3];

pub const BLACK: Rgb = [20, 20, 20];
pub const GREY: Rgb = [110, 110, 110];
pub const GRID: Rgb = [228, 228, 228];
pub const WHITE: Rgb = [255, 255, 255];
pub const BLUE: Rgb = [31, 119, 180];
pub const ORANGE: Rgb = [255, 127, 14];
pub const GREEN: Rgb = [44, 160, 44];
pub const RED: Rgb = [214, 39, 40];

/// Errors of the `plot` module.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("chart {title:?}: {width}x{height} pixels is too small, a chart needs at least {min}x{min}")]
    TooSmall { title: String, width: usize, height: usize, min: usize },
    #[error("the embedded figure font {font} cannot be read")]
    Font { font: &'static str },
    #[error("chart {title:?}: drawing failed: {message}")]
    Draw { title: String, message: String },
}

/// How a series is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Style {
    Solid,
    Dashed,
    /// A filled dot at each point (width is the diameter).
    Dots,
}

/// One labelled polyline (or set of dots) in data coordinates; an empty label keeps it out of
/// the legend.
#[derive(Clone, Debug)]
pub struct Series {
    pub label: String,
    pub points: Vec<[f64; 2]>,
    pub color: Rgb,
    /// Line width (or dot diameter) in pixels.
    pub width_px: f32,
    pub style: Style,
}

impl Series {
    pub fn line(label: impl Into<String>, points: Vec<[f64; 2]>, color: Rgb, width_px: f32) -> Self {
        Series { label: label.into(), points, color, width_px, style: Style::Solid }
    }
    pub fn with_style(mut self, style: Style) -> Self {
        self.style = style;
        self
    }
}

/// A line chart.
#[derive(Clone, Debug, Default)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// One data unit is as long on both axes (maps, top views).
    pub equal_aspect: bool,
    /// Fixed axis ranges; fitted to the data (with a margin) when `None`.
    pub x_range: Option<(f64, f64)>,
    pub y_range: Option<(f64, f64)>,
}

/// The smallest chart side, pixels: room for the title, the axis labels and a plot area.
pub const MIN_SIDE_PX: usize = 160;

/// The family name the embedded font is registered under with plotters.
const FONT_FAMILY: &str = "duv-eval DejaVu Sans";
const FONT_FILE: &str = "DejaVuSans.ttf";
static FONT_TTF: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// Space above the title, pixels.
const TITLE_TOP_PX: i32 = 8;
/// Font sizes (pixels) of the title and of every other text.
const TITLE_PX: f64 = 22.0;
const LABEL_PX: f64 = 17.0;

/// Space around the chart body (below the title), pixels.
const MARGIN_TOP: i32 = 8;
const MARGIN_RIGHT: i32 = 28;
const MARGIN_BOTTOM: i32 = 10;
const MARGIN_LEFT: i32 = 12;
/// Tick marks, and the gap between a tick label and its tick.
const TICK_PX: i32 = 6;
/// Height of the x label area (tick labels and the axis label) below the plot.
const X_LABEL_AREA_PX: i32 = 62;
/// Width of the y label area beyond the widest tick label (the rotated axis label and gaps).
const Y_LABEL_AREA_EXTRA_PX: i32 = 48;

const LEGEND_INSET: i32 = 12;
const LEGEND_PAD: i32 = 10;
const LEGEND_SAMPLE_W: i32 = 34;
const LEGEND_GAP: i32 = 10;
/// Dash and gap lengths of dashed series, pixels.
const DASH_PX: i32 = 12;
const DASH_GAP_PX: i32 = 7;

/// Names the chart in a plotters error.
trait OrDraw<T> {
    fn or_draw(self, title: &str) -> Result<T, PlotError>;
}

impl<T, E: Display> OrDraw<T> for Result<T, E> {
    fn or_draw(self, title: &str) -> Result<T, PlotError> {
        self.map_err(|e| PlotError::Draw { title: title.to_string(), message: e.to_string() })
    }
}

/// Registers the embedded font with plotters, once per process.
fn register_font() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, FONT_TTF).is_ok());
    if ok {
        Ok(())
    } else {
        Err(PlotError::Font { font: FONT_FILE })
    }
}

fn color(c: Rgb) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

fn text_style(size_px: f64) -> TextStyle<'static> {
    (FONT_FAMILY, size_px).into_font().color(&color(BLACK))
}

/// Tick positions covering [lo, hi] at a 1-2-5 step, about `target` of them, and the decimals
/// their labels need.
pub fn ticks(lo: f64, hi: f64, target: usize) -> (Vec<f64>, usize) {
    let range = (hi - lo).abs();
    if !(range > 0.0 && range.is_finite()) {
        return (vec![lo], 2);
    }
    let raw = range / target.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let norm = raw / mag;
    let nice = if norm < 1.5 {
        1.0
    } else if norm < 3.0 {
        2.0
    } else if norm < 7.0 {
        5.0
    } else {
        10.0
    };
    let step = nice * mag;
    let decimals = (-(step.log10() + 1e-9).floor()).max(0.0) as usize;
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    if last.saturating_sub(first) > 100 {
        // A range far narrower than its magnitude (steps below f64 resolution): the ends only.
        return (vec![lo, hi], decimals.min(9));
    }
    let values = (first..=last).map(|k| k as f64 * step).collect();
    (values, decimals.min(9))
}

fn tick_label(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    // No "-0.00".
    if s.trim_start_matches('-').chars().all(|c| c == '0' || c == '.') {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

fn data_range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    (lo <= hi).then_some((lo, hi))
}

/// Pads a data range by 5% each side; a zero-width range gets a unit-sized window.
fn padded((lo, hi): (f64, f64)) -> (f64, f64) {
    let r = hi - lo;
    if r > 0.0 {
        (lo - 0.05 * r, hi + 0.05 * r)
    } else {
        let half = if lo.abs() > 0.0 { 0.1 * lo.abs() } else { 0.5 };
        (lo - half, hi + half)
    }
}

/// A linear axis for plotters whose grid lines and labels are [`ticks`] (no minor lines).
#[derive(Clone, Debug)]
struct Axis {
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
    decimals: usize,
}

impl Axis {
    fn new(lo: f64, hi: f64, target: usize) -> Self {
        let (ticks, decimals) = ticks(lo, hi, target);
        Axis { lo, hi, ticks, decimals }
    }
}

impl Ranged for Axis {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        let span = self.hi - self.lo;
        if !(span > 0.0 && span.is_finite()) {
            return (limit.0 + limit.1) / 2;
        }
        // `as` saturates: a far-off value lands at the edge of the backend's i32 range.
        (limit.0 as f64 + (v - self.lo) / span * (limit.1 - limit.0) as f64).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        match hint.weight() {
            KeyPointWeight::Bold => self.ticks.clone(),
            // The light (minor) grid: none.
            KeyPointWeight::Any => Vec::new(),
        }
    }

    fn range(&self) -> Range<f64> {
        self.lo..self.hi
    }
}

impl ValueFormatter<f64> for Axis {
    fn format_ext(&self, v: &f64) -> String {
        tick_label(*v, self.decimals)
    }
}

/// Axis ranges and the size of the plot area they map onto, pixels (the legend is placed in
/// plot-area pixels, origin top-left).
#[derive(Clone, Copy, Debug)]
struct Frame {
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
    pw: i32,
    ph: i32,
    /// Width of the y label area that gives this plot area.
    y_area_w: i32,
}

impl Frame {
    fn to_px(self, p: [f64; 2]) -> [f64; 2] {
        [(p[0] - self.x0) / (self.x1 - self.x0) * self.pw as f64, self.ph as f64 - (p[1] - self.y0) / (self.y1 - self.y0) * self.ph as f64]
    }
    fn x_ticks_target(self) -> usize {
        (self.pw / 110).max(2) as usize
    }
    fn y_ticks_target(ph: i32) -> usize {
        (ph / 70).max(2) as usize
    }
}

/// Where the plot area of a drawn chart is: its ranges and size, and its top-left pixel (what
/// the tests check drawn pixels against).
#[derive(Clone, Copy, Debug)]
#[cfg_attr(not(test), allow(dead_code))]
struct Layout {
    frame: Frame,
    left: i32,
    top: i32,
}

impl Layout {
    /// Image pixel of a data point.
    #[cfg(test)]
    fn pixel(&self, p: [f64; 2]) -> (usize, usize) {
        let q = self.frame.to_px(p);
        ((self.left as f64 + q[0]).round() as usize, (self.top as f64 + q[1]).round() as usize)
    }
}

/// A chart builder with the fixed margins and label areas of every chart.
fn builder<'a, 'b>(body: &'a DrawingArea<BitMapBackend<'b>, Shift>, y_area_w: i32) -> ChartBuilder<'a, 'b, BitMapBackend<'b>> {
    let mut b = ChartBuilder::on(body);
    b.margin_top(MARGIN_TOP)
        .margin_right(MARGIN_RIGHT)
        .margin_bottom(MARGIN_BOTTOM)
        .margin_left(MARGIN_LEFT)
        .x_label_area_size(X_LABEL_AREA_PX)
        .y_label_area_size(y_area_w);
    b
}

impl Chart {
    /// Draws the chart into a `width` x `height` image.
    pub fn render(&self, width: usize, height: usize) -> Result<ImageRgb8, PlotError> {
        self.render_with_layout(width, height).map(|(img, _)| img)
    }

    /// The image, and where the plot area landed in it.
    fn render_with_layout(&self, width: usize, height: usize) -> Result<(ImageRgb8, Layout), PlotError> {
        if width < MIN_SIDE_PX || height < MIN_SIDE_PX {
            return Err(PlotError::TooSmall { title: self.title.clone(), width, height, min: MIN_SIDE_PX });
        }
        register_font()?;
        let mut buf = vec![255u8; width * height * 3];
        let layout = {
            let root = BitMapBackend::with_buffer(&mut buf, (width as u32, height as u32)).into_drawing_area();
            let layout = self.draw(&root)?;
            root.present().or_draw(&self.title)?;
            layout
        };
        Ok((ImageRgb8 { width, height, data: buf }, layout))
    }

    fn draw(&self, root: &DrawingArea<BitMapBackend<'_>, Shift>) -> Result<Layout, PlotError> {
        root.fill(&color(WHITE)).or_draw(&self.title)?;
        let label_font = text_style(LABEL_PX);
        let body = root.margin(TITLE_TOP_PX, 0, 0, 0).titled(&self.title, text_style(TITLE_PX)).or_draw(&self.title)?;

        let all_x = self.series.iter().flat_map(|se| se.points.iter().map(|p| p[0]));
        let all_y = self.series.iter().flat_map(|se| se.points.iter().map(|p| p[1]));
        let x_range = self.x_range.unwrap_or_else(|| padded(data_range(all_x).unwrap_or((0.0, 1.0))));
        let mut y_range = self.y_range.unwrap_or_else(|| padded(data_range(all_y.clone()).unwrap_or((0.0, 1.0))));

        // Fit the axes; where the legend would hide data in every corner, raise the top of the
        // y range until the data passes below the legend (a few rounds: with equal aspect the
        // scale changes as the range grows).
        let legend = self.legend_size(&label_font)?;
        let mut frame = self.fit(&body, &label_font, x_range, y_range)?;
        if let (Some((box_w, box_h)), Some((_, y_max))) = (legend, data_range(all_y)) {
            for _ in 0..4 {
                let (_, hidden) = self.legend_corner(&frame, box_w, box_h);
                if hidden == 0 {
                    break;
                }
                let need_px = (LEGEND_INSET + box_h + 8) as f64;
                let ph = frame.ph as f64;
                if need_px >= 0.8 * ph {
                    break;
                }
                let (y0, y1) = (frame.y0, frame.y1);
                let new_y1 = (y_max * ph - need_px * y0) / (ph - need_px);
                if new_y1.is_nan() || new_y1 <= y1 {
                    break;
                }
                y_range = (y_range.0, y_range.1 + (new_y1 - y1));
                frame = self.fit(&body, &label_font, x_range, y_range)?;
            }
        }

        let x_axis = Axis::new(frame.x0, frame.x1, frame.x_ticks_target());
        let y_axis = Axis::new(frame.y0, frame.y1, Frame::y_ticks_target(frame.ph));
        let mut chart = builder(&body, frame.y_area_w).build_cartesian_2d(x_axis, y_axis).or_draw(&self.title)?;
        chart
            .configure_mesh()
            .bold_line_style(color(GRID))
            .axis_style(color(BLACK))
            .set_all_tick_mark_size(TICK_PX)
            .label_style(label_font.clone())
            .axis_desc_style(label_font.clone())
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .draw().or_draw(&self.title)?;

        for se in &self.series {
            let pts: Vec<(f64, f64)> = se.points.iter().filter(|p| p[0].is_finite() && p[1].is_finite()).map(|p| (p[0], p[1])).collect();
            if pts.is_empty() {
                continue;
            }
            let c = color(se.color);
            let line = ShapeStyle { color: c.to_rgba(), filled: false, stroke_width: se.width_px.round().max(1.0) as u32 };
            let sample = ShapeStyle { stroke_width: line.stroke_width.max(2), ..line };
            let radius = (0.5 * se.width_px).round().max(1.0) as i32;
            let anno = match se.style {
                Style::Solid => chart.draw_series(LineSeries::new(pts, line)).or_draw(&self.title)?,
                Style::Dashed => chart.draw_series(DashedLineSeries::new(pts, DASH_PX, DASH_GAP_PX, line)).or_draw(&self.title)?,
                Style::Dots => chart.draw_series(pts.into_iter().map(|p| Circle::new(p, radius, c.filled()))).or_draw(&self.title)?,
            };
            if se.label.is_empty() {
                continue;
            }
            anno.label(se.label.as_str());
            match se.style {
                Style::Solid => anno.legend(move |(x, y)| PathElement::new(vec![(x, y), (x + LEGEND_SAMPLE_W, y)], sample)),
                Style::Dashed => anno.legend(move |(x, y)| DashedPathElement::new(vec![(x, y), (x + LEGEND_SAMPLE_W, y)], DASH_PX, DASH_GAP_PX, sample)),
                Style::Dots => anno.legend(move |(x, y)| Circle::new((x + LEGEND_SAMPLE_W / 2, y), radius, c.filled())),
            };
        }

        // A frame round the plot area.
        chart.plotting_area().draw(&Rectangle::new([(frame.x0, frame.y0), (frame.x1, frame.y1)], color(BLACK))).or_draw(&self.title)?;

        if let Some((box_w, box_h)) = legend {
            let ((bx, by), _) = self.legend_corner(&frame, box_w, box_h);
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::Coordinate(bx, by))
                .margin(LEGEND_PAD)
                .legend_area_size(LEGEND_SAMPLE_W + LEGEND_GAP)
                .label_font(label_font.clone())
                .background_style(color(WHITE).filled())
                .border_style(color(GREY))
                .draw().or_draw(&self.title)?;
        }
        let (xs, ys) = chart.plotting_area().get_pixel_range();
        Ok(Layout { frame, left: xs.start, top: ys.start })
    }

    /// The axis ranges and plot area: the y label area is as wide as the widest y tick label
    /// needs; with equal aspect, the ranges widen about their centres until a unit is as long
    /// on both axes.
    fn fit(&self, body: &DrawingArea<BitMapBackend<'_>, Shift>, font: &TextStyle, (x0, x1): (f64, f64), (y0, y1): (f64, f64)) -> Result<Frame, PlotError> {
        let mut y_area_w = Y_LABEL_AREA_EXTRA_PX;
        let mut frame = None;
        // The plot area depends on the label width, the label width on the ticks of the final
        // range: settle in a few rounds.
        for _ in 0..4 {
            let probe = builder(body, y_area_w).build_cartesian_2d(0.0..1.0, 0.0..1.0).or_draw(&self.title)?;
            let (xs, ys) = probe.plotting_area().get_pixel_range();
            let (pw, ph) = ((xs.end - xs.start).max(1), (ys.end - ys.start).max(1));
            let (mut fx0, mut fx1, mut fy0, mut fy1) = (x0, x1, y0, y1);
            if self.equal_aspect {
                let px_per_unit = (pw as f64 / (x1 - x0)).min(ph as f64 / (y1 - y0));
                let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
                let (hx, hy) = (0.5 * pw as f64 / px_per_unit, 0.5 * ph as f64 / px_per_unit);
                (fx0, fx1, fy0, fy1) = (cx - hx, cx + hx, cy - hy, cy + hy);
            }
            let f = Frame { x0: fx0, x1: fx1, y0: fy0, y1: fy1, pw, ph, y_area_w };
            let y_axis = Axis::new(fy0, fy1, Frame::y_ticks_target(ph));
            let mut label_w = 0;
            for v in &y_axis.ticks {
                label_w = label_w.max(body.estimate_text_size(&tick_label(*v, y_axis.decimals), font).or_draw(&self.title)?.0 as i32);
            }
            let need = label_w + TICK_PX + Y_LABEL_AREA_EXTRA_PX;
            frame = Some(f);
            if need == y_area_w {
                break;
            }
            y_area_w = need;
        }
        // The loop runs at least once.
        Ok(frame.unwrap_or(Frame { x0, x1, y0, y1, pw: 1, ph: 1, y_area_w }))
    }

    /// Size of the legend box in pixels, as plotters lays it out; `None` without labelled
    /// series.
    fn legend_size(&self, font: &TextStyle) -> Result<Option<(i32, i32)>, PlotError> {
        let labels: Vec<&str> = self.series.iter().filter(|se| !se.label.is_empty()).map(|se| se.label.as_str()).collect();
        if labels.is_empty() {
            return Ok(None);
        }
        let mut text = MultiLineText::<(i32, i32), &str>::new((0, 0), font.clone());
        for l in labels {
            text.push_line(l);
        }
        let (w, h) = text.estimate_dimension().or_draw(&self.title)?;
        Ok(Some((w + LEGEND_SAMPLE_W + LEGEND_GAP + 2 * LEGEND_PAD, h + 2 * LEGEND_PAD)))
    }

    /// The corner (top-left of the box, plot-area pixels) where the legend hides the fewest
    /// data points, and how many it hides there. Top corners first.
    fn legend_corner(&self, frame: &Frame, box_w: i32, box_h: i32) -> ((i32, i32), usize) {
        let (pr, pb) = (frame.pw, frame.ph);
        let corners = [
            (pr - LEGEND_INSET - box_w, LEGEND_INSET),
            (LEGEND_INSET, LEGEND_INSET),
            (pr - LEGEND_INSET - box_w, pb - LEGEND_INSET - box_h),
            (LEGEND_INSET, pb - LEGEND_INSET - box_h),
        ];
        let hidden = |(bx, by): (i32, i32)| -> usize {
            self.series
                .iter()
                .flat_map(|se| se.points.iter())
                .map(|&p| frame.to_px(p))
                .filter(|q| q[0] >= (bx - 4) as f64 && q[0] <= (bx + box_w + 4) as f64 && q[1] >= (by - 4) as f64 && q[1] <= (by + box_h + 4) as f64)
                .count()
        };
        corners.iter().map(|&c| (c, hidden(c))).min_by_key(|&(_, h)| h).unwrap_or((corners[0], 0))
    }
}

/// Axes of a top view of 3-D points: their mean and the unit directions of the two largest
/// principal axes (the plane the motion mostly lies in). Signs are fixed so that each axis's
/// largest component is positive, and degenerate clouds fall back to x and y.
pub fn top_view_axes(points: &[Vector3<f64>]) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    if points.is_empty() {
        return (Vector3::zeros(), Vector3::x(), Vector3::y());
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p - mean;
        cov += d * d.transpose();
    }
    cov /= n;
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let fix_sign = |v: Vector3<f64>| {
        let i = v.iamax();
        if v[i] < 0.0 {
            -v
        } else {
            v
        }
    };
    let e1 = fix_sign(eig.eigenvectors.column(order[0]).into_owned());
    let e2 = fix_sign(eig.eigenvectors.column(order[1]).into_owned());
    if !(e1.iter().all(|v| v.is_finite()) && e2.iter().all(|v| v.is_finite())) {
        return (mean, Vector3::x(), Vector3::y());
    }
    (mean, e1, e2)
}

/// Projects points onto the plane of [`top_view_axes`].
pub fn project(points: &[Vector3<f64>], axes: &(Vector3<f64>, Vector3<f64>, Vector3<f64>)) -> Vec<[f64; 2]> {
    let (mean, e1, e2) = axes;
    points.iter().map(|p| [(p - mean).dot(e1), (p - mean).dot(e2)]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        let (t, d) = ticks(0.0, 1.0, 5);
        assert_eq!(t, vec![0.0, 0.2, 0.4, 0.6000000000000001, 0.8, 1.0]);
        assert_eq!(d, 1);
        let (t, d) = ticks(-0.013, 0.021, 6);
        assert_eq!(d, 3);
        assert!(t.iter().all(|v| (-0.013..=0.021).contains(v)));
        assert_eq!(tick_label(-0.0000001, 2), "0.00");
        assert_eq!(tick_label(-1.5, 1), "-1.5");
        assert_eq!(ticks(3.0, 3.0, 5).0, vec![3.0]);
    }

    #[test]
    fn chart_draws_series_inside_the_frame() {
        let chart = Chart {
            title: "t".into(),
            x_label: "x (m)".into(),
            y_label: "y (m)".into(),
            series: vec![Series::line("a", vec![[0.0, 0.0], [1.0, 1.0]], RED, 3.0)],
            ..Default::default()
        };
        let img = chart.render(400, 300).unwrap();
        assert_eq!((img.width, img.height), (400, 300));
        let red = img.data.chunks_exact(3).filter(|p| p[0] > 180 && p[1] < 80 && p[2] < 80).count();
        assert!(red > 300, "{red}");
    }

    /// Pixels of `img` within `r` of (x, y) whose colour is within 10 of `c` in every channel.
    fn near(img: &ImageRgb8, (x, y): (usize, usize), r: usize, c: Rgb) -> usize {
        let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
        let (x1, y1) = ((x + r).min(img.width - 1), (y + r).min(img.height - 1));
        (y0..=y1).flat_map(|yy| (x0..=x1).map(move |xx| (xx, yy))).filter(|&(xx, yy)| img.pixel(xx, yy).iter().zip(&c).all(|(a, b)| a.abs_diff(*b) <= 10)).count()
    }

    #[test]
    fn series_land_where_their_data_is() {
        // A rising solid line, a dashed level, a dot: fixed ranges so every position is known.
        let rising: Vec<[f64; 2]> = (0..=50).map(|i| [i as f64 * 0.2, 2.0 + i as f64 * 0.12]).collect();
        let chart = Chart {
            title: "Pixel check".into(),
            x_label: "x (m)".into(),
            y_label: "y (m)".into(),
            series: vec![
                Series::line("rising", rising.clone(), BLUE, 3.0),
                Series::line("level", vec![[0.0, 5.0], [10.0, 5.0]], RED, 2.0).with_style(Style::Dashed),
                Series { label: String::new(), points: vec![[8.0, 2.0]], color: GREEN, width_px: 11.0, style: Style::Dots },
            ],
            x_range: Some((0.0, 10.0)),
            y_range: Some((0.0, 10.0)),
            ..Default::default()
        };
        let (img, layout) = chart.render_with_layout(640, 480).unwrap();
        assert_eq!((img.width, img.height, img.data.len()), (640, 480, 640 * 480 * 3));
        let f = layout.frame;
        assert_eq!((f.x0, f.x1, f.y0, f.y1), (0.0, 10.0, 0.0, 10.0));
        assert!(f.pw > 400 && f.ph > 280 && layout.left > 40 && layout.top > 20, "{layout:?}");

        // The blue line passes through each of its points (the middle third, clear of any legend).
        for p in &rising[17..34] {
            let at = layout.pixel(*p);
            assert!(near(&img, at, 1, BLUE) > 0, "no blue near {at:?} for {p:?}");
        }
        // ...and nowhere near a point off the line.
        assert_eq!(near(&img, layout.pixel([2.0, 8.0]), 6, BLUE), 0);
        // The dashed level: red dashes with gaps along y = 5.
        let y5 = layout.pixel([0.0, 5.0]).1;
        let along: Vec<bool> = (layout.pixel([3.0, 5.0]).0..layout.pixel([7.0, 5.0]).0).map(|x| near(&img, (x, y5), 1, RED) > 0).collect();
        let red = along.iter().filter(|&&r| r).count();
        assert!(red > along.len() / 2 && red < along.len(), "{red} of {} pixels red: dashes and gaps", along.len());
        // The dot: a filled disc of about 11 pixels across.
        let dot = near(&img, layout.pixel([8.0, 2.0]), 7, GREEN);
        assert!((60..=160).contains(&dot), "{dot} green pixels");
        // Below and left of the plot area: white margin and black text (tick labels, axis labels).
        let dark = |x0: usize, x1: usize, y0: usize, y1: usize| (y0..y1).flat_map(|y| (x0..x1).map(move |x| (x, y))).filter(|&(x, y)| img.pixel(x, y).iter().all(|&v| v < 100)).count();
        let (left, bottom) = (layout.left as usize, layout.top as usize + f.ph as usize);
        assert!(dark(0, left - 8, 0, 480) > 150, "no y labels");
        assert!(dark(left, 640, bottom + 8, 480) > 150, "no x labels");
        assert!(dark(0, 640, 0, layout.top as usize - 4) > 100, "no title");
    }

    #[test]
    fn a_chart_too_small_is_an_error_naming_it() {
        let chart = Chart { title: "tiny".into(), ..Default::default() };
        let e = chart.render(100, 40).unwrap_err().to_string();
        assert!(e.contains("tiny") && e.contains("100x40"), "{e}");
        // No data at all still draws (empty axes).
        assert!(chart.render(MIN_SIDE_PX, MIN_SIDE_PX).is_ok());
    }

    #[test]
    fn top_view_finds_the_plane_of_motion() {
        // Points on a tilted ellipse: the axes span its plane.
        let normal = Vector3::new(0.0, 1.0, 1.0).normalize();
        let u = Vector3::x();
        let v = normal.cross(&u);
        let pts: Vec<_> = (0..100).map(|i| {
            let a = i as f64 * 0.0628;
            u * 3.0 * a.cos() + v * a.sin() + Vector3::new(1.0, 2.0, 3.0)
        }).collect();
        let axes = top_view_axes(&pts);
        assert!(axes.1.dot(&normal).abs() < 1e-9 && axes.2.dot(&normal).abs() < 1e-9);
        assert!((axes.1.dot(&u).abs() - 1.0).abs() < 1e-9);
    }
}
