//! A small plotting module for the report figures: line charts with axes, tick labels, grid,
//! legend and title, drawn into an RGB image with anti-aliased lines and the built-in bitmap
//! font. No plotting crate, no font files.

use super::font::{self, CELL_H, CELL_W};
use duv_core::ImageRgb8;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

pub type Rgb = [u8; 3];

pub const BLACK: Rgb = [20, 20, 20];
pub const GREY: Rgb = [110, 110, 110];
pub const GRID: Rgb = [228, 228, 228];
pub const WHITE: Rgb = [255, 255, 255];
pub const BLUE: Rgb = [31, 119, 180];
pub const ORANGE: Rgb = [255, 127, 14];
pub const GREEN: Rgb = [44, 160, 44];
pub const RED: Rgb = [214, 39, 40];

/// Text scale (font pixels to image pixels) of every label.
const TEXT_SCALE: usize = 2;

/// How a series is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Style {
    Solid,
    Dashed,
    /// A filled dot at each point (width is the diameter).
    Dots,
}

/// One labelled polyline (or set of dots) in data coordinates.
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

/// An RGB canvas with alpha blending.
struct Canvas {
    img: ImageRgb8,
}

impl Canvas {
    fn new(width: usize, height: usize) -> Self {
        Canvas { img: ImageRgb8::filled(width, height, WHITE) }
    }

    fn blend(&mut self, x: i64, y: i64, c: Rgb, alpha: f32) {
        if x < 0 || y < 0 || x >= self.img.width as i64 || y >= self.img.height as i64 || alpha <= 0.0 {
            return;
        }
        let i = self.img.index(x as usize, y as usize);
        let a = alpha.min(1.0);
        for (dst, &src) in self.img.data[i..i + 3].iter_mut().zip(&c) {
            let old = *dst as f32;
            *dst = (old + (src as f32 - old) * a).round().clamp(0.0, 255.0) as u8;
        }
    }

    fn fill_rect(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        for y in y0..y1 {
            for x in x0..x1 {
                self.blend(x, y, c, 1.0);
            }
        }
    }

    fn rect_outline(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        self.fill_rect(x0, y0, x1, y0 + 1, c);
        self.fill_rect(x0, y1 - 1, x1, y1, c);
        self.fill_rect(x0, y0, x0 + 1, y1, c);
        self.fill_rect(x1 - 1, y0, x1, y1, c);
    }

    /// Text with its top-left corner at (x, y).
    fn text(&mut self, x: i64, y: i64, s: &str, scale: usize, c: Rgb) {
        let mut pen = x;
        for ch in s.chars() {
            let rows = font::glyph(ch);
            for (gy, bits) in rows.iter().enumerate() {
                for gx in 0..CELL_W {
                    if bits & (1 << (CELL_W - 1 - gx)) != 0 {
                        let (px, py) = (pen + (gx * scale) as i64, y + (gy * scale) as i64);
                        self.fill_rect(px, py, px + scale as i64, py + scale as i64, c);
                    }
                }
            }
            pen += ((CELL_W + 1) * scale) as i64;
        }
    }

    /// Text rotated a quarter turn anticlockwise (reading upwards), its bounding box's top-left
    /// corner at (x, y).
    fn text_vertical(&mut self, x: i64, y: i64, s: &str, scale: usize, c: Rgb) {
        let w = font::text_width(s, scale) as i64;
        let mut pen = 0i64;
        for ch in s.chars() {
            let rows = font::glyph(ch);
            for (gy, bits) in rows.iter().enumerate() {
                for gx in 0..CELL_W {
                    if bits & (1 << (CELL_W - 1 - gx)) != 0 {
                        let tx = pen + (gx * scale) as i64;
                        let ty = (gy * scale) as i64;
                        let (px, py) = (x + ty, y + w - tx - scale as i64);
                        self.fill_rect(px, py, px + scale as i64, py + scale as i64, c);
                    }
                }
            }
            pen += ((CELL_W + 1) * scale) as i64;
        }
    }

    fn composite(&mut self, mask: &Mask, c: Rgb) {
        for y in mask.y0..mask.y1 {
            for x in mask.x0..mask.x1 {
                let a = mask.alpha[(y - mask.y0) * mask.width() + (x - mask.x0)];
                if a > 0.0 {
                    self.blend(x as i64, y as i64, c, a);
                }
            }
        }
    }
}

/// Coverage of one series over a clip rectangle; overlapping segments take the maximum so that
/// joints are not drawn twice.
struct Mask {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
    alpha: Vec<f32>,
}

impl Mask {
    /// A mask over `[x0, x1) x [y0, y1)`; negative or inverted bounds give an empty mask.
    fn new(x0: i64, y0: i64, x1: i64, y1: i64) -> Self {
        let (x0, y0) = (x0.max(0) as usize, y0.max(0) as usize);
        let (x1, y1) = ((x1.max(0) as usize).max(x0), (y1.max(0) as usize).max(y0));
        Mask { x0, y0, x1, y1, alpha: vec![0.0; (x1 - x0) * (y1 - y0)] }
    }
    fn width(&self) -> usize {
        self.x1 - self.x0
    }

    /// An anti-aliased segment of width `2 * half` between pixel-space points.
    fn segment(&mut self, a: [f64; 2], b: [f64; 2], half: f64) {
        let pad = half + 1.0;
        let bx0 = ((a[0].min(b[0]) - pad).floor().max(self.x0 as f64)) as usize;
        let by0 = ((a[1].min(b[1]) - pad).floor().max(self.y0 as f64)) as usize;
        let bx1 = ((a[0].max(b[0]) + pad).ceil().min(self.x1 as f64)).max(bx0 as f64) as usize;
        let by1 = ((a[1].max(b[1]) + pad).ceil().min(self.y1 as f64)).max(by0 as f64) as usize;
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len2 = dx * dx + dy * dy;
        let w = self.width();
        for y in by0..by1 {
            for x in bx0..bx1 {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let t = if len2 > 0.0 { (((px - a[0]) * dx + (py - a[1]) * dy) / len2).clamp(0.0, 1.0) } else { 0.0 };
                let (cx, cy) = (a[0] + t * dx, a[1] + t * dy);
                let d = ((px - cx).powi(2) + (py - cy).powi(2)).sqrt();
                let cover = (half + 0.5 - d).clamp(0.0, 1.0) as f32;
                let slot = &mut self.alpha[(y - self.y0) * w + (x - self.x0)];
                *slot = slot.max(cover);
            }
        }
    }

    fn polyline(&mut self, pts: &[[f64; 2]], half: f64) {
        if pts.len() == 1 {
            self.segment(pts[0], pts[0], half);
        }
        for w in pts.windows(2) {
            self.segment(w[0], w[1], half);
        }
    }

    /// Dashes of `on` pixels separated by `off` pixels, continuing across vertices.
    fn dashed(&mut self, pts: &[[f64; 2]], half: f64, on: f64, off: f64) {
        let period = on + off;
        let mut phase = 0.0; // distance travelled modulo the period
        for w in pts.windows(2) {
            let (a, b) = (w[0], w[1]);
            let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            let mut s = 0.0;
            while s < len {
                let in_on = phase < on;
                let step = if in_on { on - phase } else { period - phase }.min(len - s);
                if in_on && step > 0.0 {
                    let p = |u: f64| [a[0] + (b[0] - a[0]) * u / len, a[1] + (b[1] - a[1]) * u / len];
                    self.segment(p(s), p(s + step), half);
                }
                s += step;
                phase = (phase + step) % period;
                if step <= 0.0 {
                    break;
                }
            }
        }
    }
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

const LEGEND_INSET: i64 = 12;
const LEGEND_PAD: i64 = 10;
const LEGEND_SAMPLE_W: i64 = 34;

fn legend_row_h() -> i64 {
    (CELL_H * TEXT_SCALE + 8) as i64
}

/// Axis ranges and the plot area they map onto.
#[derive(Clone, Copy, Debug)]
struct Frame {
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
    /// Left and top of the plot area, its width and height, pixels.
    pl: usize,
    pt: usize,
    pw: usize,
    ph: usize,
}

impl Frame {
    /// Margins for title, tick labels and axis labels around the plot area; with equal
    /// aspect, the ranges widen about their centres until a unit is as long on both axes.
    fn fit((mut x0, mut x1): (f64, f64), (mut y0, mut y1): (f64, f64), width: usize, height: usize, equal_aspect: bool) -> Frame {
        let s = TEXT_SCALE;
        let line_h = CELL_H * s;
        let top = 20 + line_h + 16;
        let bottom_margin = 8 + 6 + line_h + 14 + line_h + 14;
        let ph = height.saturating_sub(top + bottom_margin).max(10);
        // The y tick labels' width decides the left margin.
        let (y_ticks, y_dec) = ticks(y0, y1, (ph / 70).max(2));
        let label_w = y_ticks.iter().map(|v| font::text_width(&tick_label(*v, y_dec), s)).max().unwrap_or(0);
        let pl = 14 + line_h + 14 + label_w + 8 + 6;
        let pw = width.saturating_sub(pl + 28).max(10);
        if equal_aspect {
            let px_per_unit = (pw as f64 / (x1 - x0)).min(ph as f64 / (y1 - y0));
            let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
            let (hx, hy) = (0.5 * pw as f64 / px_per_unit, 0.5 * ph as f64 / px_per_unit);
            (x0, x1, y0, y1) = (cx - hx, cx + hx, cy - hy, cy + hy);
        }
        Frame { x0, x1, y0, y1, pl, pt: top, pw, ph }
    }

    fn to_px(self, p: [f64; 2]) -> [f64; 2] {
        [
            self.pl as f64 + (p[0] - self.x0) / (self.x1 - self.x0) * self.pw as f64,
            (self.pt + self.ph) as f64 - (p[1] - self.y0) / (self.y1 - self.y0) * self.ph as f64,
        ]
    }
}

impl Chart {
    /// Draws the chart into a `width` x `height` image.
    pub fn render(&self, width: usize, height: usize) -> ImageRgb8 {
        let s = TEXT_SCALE;
        let line_h = CELL_H * s;
        let mut canvas = Canvas::new(width, height);

        let all_x = self.series.iter().flat_map(|se| se.points.iter().map(|p| p[0]));
        let all_y = self.series.iter().flat_map(|se| se.points.iter().map(|p| p[1]));
        let x_range = self.x_range.unwrap_or_else(|| padded(data_range(all_x).unwrap_or((0.0, 1.0))));
        let mut y_range = self.y_range.unwrap_or_else(|| padded(data_range(all_y.clone()).unwrap_or((0.0, 1.0))));

        // Fit the axes; where the legend would hide data in every corner, raise the top of the
        // y range until the data passes below the legend (a few rounds: with equal aspect the
        // scale changes as the range grows).
        let mut frame = Frame::fit(x_range, y_range, width, height, self.equal_aspect);
        if let (Some((box_w, box_h)), Some((_, y_max))) = (self.legend_size(), data_range(all_y)) {
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
                frame = Frame::fit(x_range, y_range, width, height, self.equal_aspect);
            }
        }
        let Frame { x0, x1, y0, y1, pl, pt, pw: plot_w, ph: plot_h } = frame;
        let (pr, pb) = (pl + plot_w, pt + plot_h);
        let to_px = |p: [f64; 2]| frame.to_px(p);

        // Grid and ticks.
        let (x_ticks, x_dec) = ticks(x0, x1, (plot_w / 110).max(2));
        let (y_ticks, y_dec) = ticks(y0, y1, (plot_h / 70).max(2));
        for &v in &x_ticks {
            let x = to_px([v, y0])[0].round() as i64;
            canvas.fill_rect(x, pt as i64, x + 1, pb as i64, GRID);
        }
        for &v in &y_ticks {
            let y = to_px([x0, v])[1].round() as i64;
            canvas.fill_rect(pl as i64, y, pr as i64, y + 1, GRID);
        }

        // Series, clipped to the plot area.
        for se in &self.series {
            let pts: Vec<[f64; 2]> = se.points.iter().filter(|p| p[0].is_finite() && p[1].is_finite()).map(|&p| to_px(p)).collect();
            if pts.is_empty() {
                continue;
            }
            let mut mask = Mask::new(pl as i64, pt as i64, pr as i64, pb as i64);
            let half = 0.5 * se.width_px as f64;
            match se.style {
                Style::Solid => mask.polyline(&pts, half),
                Style::Dashed => mask.dashed(&pts, half, 12.0, 7.0),
                Style::Dots => pts.iter().for_each(|&p| mask.segment(p, p, half)),
            }
            canvas.composite(&mask, se.color);
        }

        // Frame, tick marks and labels.
        canvas.rect_outline(pl as i64 - 1, pt as i64 - 1, pr as i64 + 1, pb as i64 + 1, BLACK);
        for &v in &x_ticks {
            let x = to_px([v, y0])[0].round() as i64;
            canvas.fill_rect(x, pb as i64, x + 1, pb as i64 + 6, BLACK);
            let label = tick_label(v, x_dec);
            let tw = font::text_width(&label, s) as i64;
            canvas.text(x - tw / 2, pb as i64 + 6 + 8, &label, s, BLACK);
        }
        for &v in &y_ticks {
            let y = to_px([x0, v])[1].round() as i64;
            canvas.fill_rect(pl as i64 - 6, y, pl as i64, y + 1, BLACK);
            let label = tick_label(v, y_dec);
            let tw = font::text_width(&label, s) as i64;
            canvas.text(pl as i64 - 6 - 8 - tw, y - (7 * s as i64) / 2, &label, s, BLACK);
        }

        // Axis labels and title.
        let xl_w = font::text_width(&self.x_label, s) as i64;
        canvas.text((pl + pr) as i64 / 2 - xl_w / 2, (pb + 8 + 6 + line_h + 14) as i64, &self.x_label, s, BLACK);
        let yl_w = font::text_width(&self.y_label, s) as i64;
        canvas.text_vertical(14, (pt + pb) as i64 / 2 - yl_w / 2, &self.y_label, s, BLACK);
        let t_w = font::text_width(&self.title, s) as i64;
        let tx = ((pl + pr) as i64 / 2 - t_w / 2).max(4);
        // Bold by a one-pixel double strike.
        canvas.text(tx, 20, &self.title, s, BLACK);
        canvas.text(tx + 1, 20, &self.title, s, BLACK);

        self.legend(&mut canvas, &frame);
        canvas.img
    }

    /// Size of the legend box in pixels; `None` without labelled series.
    fn legend_size(&self) -> Option<(i64, i64)> {
        let entries = self.series.iter().filter(|se| !se.label.is_empty()).count();
        if entries == 0 {
            return None;
        }
        let s = TEXT_SCALE;
        let text_w = self.series.iter().map(|se| font::text_width(&se.label, s)).max().unwrap_or(0) as i64;
        let box_w = LEGEND_PAD + LEGEND_SAMPLE_W + 10 + text_w + LEGEND_PAD;
        let box_h = LEGEND_PAD + legend_row_h() * entries as i64 - 8 + LEGEND_PAD;
        Some((box_w, box_h))
    }

    /// The corner (top-left of the box) of the plot area where the legend hides the fewest data
    /// points, and how many it hides there. Top corners first.
    fn legend_corner(&self, frame: &Frame, box_w: i64, box_h: i64) -> ((i64, i64), usize) {
        let (pl, pt) = (frame.pl as i64, frame.pt as i64);
        let (pr, pb) = (pl + frame.pw as i64, pt + frame.ph as i64);
        let corners = [
            (pr - LEGEND_INSET - box_w, pt + LEGEND_INSET),
            (pl + LEGEND_INSET, pt + LEGEND_INSET),
            (pr - LEGEND_INSET - box_w, pb - LEGEND_INSET - box_h),
            (pl + LEGEND_INSET, pb - LEGEND_INSET - box_h),
        ];
        let hidden = |(bx, by): (i64, i64)| -> usize {
            self.series
                .iter()
                .flat_map(|se| se.points.iter())
                .map(|&p| frame.to_px(p))
                .filter(|q| q[0] >= (bx - 4) as f64 && q[0] <= (bx + box_w + 4) as f64 && q[1] >= (by - 4) as f64 && q[1] <= (by + box_h + 4) as f64)
                .count()
        };
        corners.iter().map(|&c| (c, hidden(c))).min_by_key(|&(_, h)| h).unwrap_or((corners[0], 0))
    }

    /// Draws the legend box in the best corner.
    fn legend(&self, canvas: &mut Canvas, frame: &Frame) {
        let Some((box_w, box_h)) = self.legend_size() else { return };
        let entries: Vec<&Series> = self.series.iter().filter(|se| !se.label.is_empty()).collect();
        let s = TEXT_SCALE;
        let (row_h, pad, sample_w) = (legend_row_h(), LEGEND_PAD, LEGEND_SAMPLE_W);
        let ((bx, by), _) = self.legend_corner(frame, box_w, box_h);
        canvas.fill_rect(bx, by, bx + box_w, by + box_h, WHITE);
        canvas.rect_outline(bx, by, bx + box_w, by + box_h, GREY);
        for (i, se) in entries.iter().enumerate() {
            let ty = by + pad + row_h * i as i64;
            let cy = ty as f64 + 7.0 * s as f64 / 2.0;
            let mut mask = Mask::new(bx, by, bx + box_w, by + box_h);
            let x_a = (bx + pad) as f64;
            let x_b = (bx + pad + sample_w) as f64;
            let half = 0.5 * se.width_px.max(2.0) as f64;
            match se.style {
                Style::Solid => mask.segment([x_a, cy], [x_b, cy], half),
                Style::Dashed => mask.dashed(&[[x_a, cy], [x_b, cy]], half, 12.0, 7.0),
                Style::Dots => mask.segment([0.5 * (x_a + x_b), cy], [0.5 * (x_a + x_b), cy], half),
            }
            canvas.composite(&mask, se.color);
            canvas.text(bx + pad + sample_w + 10, ty, &se.label, s, BLACK);
        }
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
        let img = chart.render(400, 300);
        assert_eq!((img.width, img.height), (400, 300));
        let red = img.data.chunks_exact(3).filter(|p| p[0] > 180 && p[1] < 80 && p[2] < 80).count();
        assert!(red > 300, "{red}");
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
