//! The benchmark report's charts: scatter and line plots with a legend and an optional Pareto
//! front, written with plotters as SVG and PNG.
//!
//! Text is drawn with DejaVu Sans embedded in the binary (`apps/sos/assets`), so no system
//! fonts are needed at run time. The PNG is rendered into memory and encoded with the `image`
//! crate the workspace already links, rather than plotters' own encoder, which would pull in a
//! second, older `image`.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{bail, Context, Result};
use plotters::coord::ranged1d::{KeyPointHint, NoDefaultFormatting, Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::{CoordTranslate, Shift};
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{register_font, FontStyle, Palette};

use crate::commands::{write_atomic, write_atomic_bytes};

/// One named set of points (x, y).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Series {
    /// The legend entry.
    pub label: String,
    /// The points; NaN or infinite coordinates are skipped when drawing.
    pub points: Vec<(f64, f64)>,
}

/// A chart of one or more series.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Chart {
    /// Drawn above the plot.
    pub title: String,
    /// The x axis description.
    pub x_label: String,
    /// The y axis description.
    pub y_label: String,
    /// Category names for the x axis: point x values are then indices 0..n into this list (for
    /// sweeps over kinds or booleans). `None` (or an empty list) gives a numeric x axis.
    pub x_categories: Option<Vec<String>>,
    /// The series, each in its own colour, in legend order.
    pub series: Vec<Series>,
    /// Join each series' points (sorted by x) with lines; otherwise markers only.
    pub lines: bool,
    /// Mark the Pareto front over all points of all series: the points no other point beats on
    /// both lower x and higher y (e.g. less wall time, higher mIoU); drawn as a dashed step line
    /// through the front plus a legend entry "Pareto front".
    pub pareto: bool,
}

/// The size of both images, in pixels (SVG user units).
const SIZE: (u32, u32) = (800, 500);
/// The family every text element asks for; the embedded font is registered under it.
const FONT: &str = "sans-serif";
const DEJAVU_SANS: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");

const TITLE_SIZE: u32 = 22;
const AXIS_DESC_SIZE: u32 = 15;
const TICK_LABEL_SIZE: u32 = 13;
const LEGEND_SIZE: u32 = 13;
const MARGIN: u32 = 15;
const X_LABEL_AREA: u32 = 45;
const Y_LABEL_AREA: u32 = 70;
const MARKER_RADIUS: i32 = 4;

/// A position in backend pixels (plotters' `BackendCoord`, which it does not re-export).
type Pixel = (i32, i32);

/// Writes `<stem>.svg` and `<stem>.png` (800x500 px), each atomically (a run killed meanwhile
/// leaves the old chart or the new one). The extensions are appended, so a stem such as
/// `lr_0.1` keeps its dot. The folder is made where missing. Errors name the file.
pub fn write_chart(chart: &Chart, stem: &Path) -> Result<()> {
    ensure_font()?;

    let svg_path = with_suffix(stem, "svg");
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        draw(&root, chart).with_context(|| format!("drawing {}", svg_path.display()))?;
        root.present().with_context(|| format!("drawing {}", svg_path.display()))?;
    }
    write_atomic(&svg_path, &svg)?;

    let png_path = with_suffix(stem, "png");
    let (w, h) = SIZE;
    let mut pixels = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, SIZE).into_drawing_area();
        draw(&root, chart).with_context(|| format!("drawing {}", png_path.display()))?;
        root.present().with_context(|| format!("drawing {}", png_path.display()))?;
    }
    let mut png = std::io::Cursor::new(Vec::new());
    image::write_buffer_with_format(&mut png, &pixels, w, h, image::ExtendedColorType::Rgb8, image::ImageFormat::Png)
        .with_context(|| format!("encoding {}", png_path.display()))?;
    write_atomic_bytes(&png_path, png.get_ref())
}

/// The Pareto front of `points` for minimising x and maximising y: the indices of the points
/// that no other point dominates (no other point has x <= and y >= with one of them strict),
/// in increasing x. Exact duplicates of a front point are all on the front; points with a NaN
/// or infinite coordinate are never on it.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut order: Vec<usize> =
        (0..points.len()).filter(|&i| points[i].0.is_finite() && points[i].1.is_finite()).collect();
    // By x, and within one x best y first, so a single sweep keeping the best y so far finds
    // the front.
    order.sort_by(|&a, &b| {
        let (pa, pb) = (points[a], points[b]);
        pa.0.total_cmp(&pb.0).then(pb.1.total_cmp(&pa.1))
    });
    let mut front = Vec::new();
    let mut best_y = f64::NEG_INFINITY;
    let mut last: Option<(f64, f64)> = None;
    for i in order {
        let p = points[i];
        if p.1 > best_y {
            front.push(i);
            best_y = p.1;
            last = Some(p);
        } else if last == Some(p) {
            front.push(i);
        }
    }
    front
}

/// Registers the embedded font with plotters once per process (its font table is global).
fn ensure_font() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| register_font(FONT, FontStyle::Normal, DEJAVU_SANS).is_ok());
    if !ok {
        bail!("the embedded DejaVu Sans font could not be loaded");
    }
    Ok(())
}

/// `stem` with `.ext` appended (not replacing anything after a dot in the stem).
fn with_suffix(stem: &Path, ext: &str) -> PathBuf {
    let mut name = stem.as_os_str().to_owned();
    name.push(".");
    name.push(ext);
    PathBuf::from(name)
}

/// The Tableau 10 colours: distinct, and all readable on white (plotters' `Palette99` has a
/// pale yellow third).
struct Tableau10;

impl Palette for Tableau10 {
    const COLORS: &'static [(u8, u8, u8)] = &[
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
}

/// Whether a coordinate can be drawn. Beyond 1e300 the padded axis span itself would overflow.
fn plottable(v: f64) -> bool {
    v.is_finite() && v.abs() <= 1e300
}

/// One series as drawn: its plottable points, sorted by x when joined by lines.
struct Prepared<'a> {
    label: &'a str,
    points: Vec<(f64, f64)>,
}

fn prepare(chart: &Chart) -> Vec<Prepared<'_>> {
    chart
        .series
        .iter()
        .map(|s| {
            let mut points: Vec<(f64, f64)> =
                s.points.iter().copied().filter(|&(x, y)| plottable(x) && plottable(y)).collect();
            if chart.lines {
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
            }
            Prepared { label: &s.label, points }
        })
        .collect()
}

/// The range spanned by `values` with a 5% margin each side. All-equal values get a margin
/// of 5% of their magnitude (or 1 around zero) so the axis never has zero span.
fn padded_range(values: impl Iterator<Item = f64>) -> Option<Range<f64>> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if lo > hi {
        return None;
    }
    let span = hi - lo;
    let pad = if span > 0.0 { span * 0.05 } else { lo.abs() * 0.05 };
    let (a, b) = (lo - pad, hi + pad);
    // A pad that rounds away (subnormal values, or zero) falls back to a unit margin.
    if b - a > 0.0 && (b - a).is_finite() {
        Some(a..b)
    } else {
        Some(lo - 1.0..hi + 1.0)
    }
}

/// An x axis of named categories at 0, 1, 2, ...: ticks and grid lines only at the categories,
/// each labelled with its name.
#[derive(Clone)]
struct CategoryAxis {
    names: Vec<String>,
    range: Range<f64>,
}

impl Ranged for CategoryAxis {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let t = (value - self.range.start) / (self.range.end - self.range.start);
        limit.0 + (t * f64::from(limit.1 - limit.0)).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        // Light grid lines between categories would mean nothing.
        if hint.weight().allow_light_points() {
            return Vec::new();
        }
        // Only the named slots: an axis widened by stray indices gets no extra ticks.
        let first = self.range.start.ceil().max(0.0);
        let last = self.range.end.floor().min(self.names.len() as f64 - 1.0);
        if first > last {
            return Vec::new();
        }
        let (first, last) = (first as usize, last as usize);
        let stride = (last - first + 1).div_ceil(hint.max_num_points().max(1));
        (first..=last).step_by(stride).map(|i| i as f64).collect()
    }

    fn range(&self) -> Range<f64> {
        self.range.clone()
    }
}

impl ValueFormatter<f64> for CategoryAxis {
    fn format_ext(&self, value: &f64) -> String {
        let i = value.round();
        if i >= 0.0 && (i as usize) < self.names.len() {
            self.names[i as usize].clone()
        } else {
            // Not reached through the key points above; a number beats a panic all the same.
            format!("{value}")
        }
    }
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let data = prepare(chart);
    let all = || data.iter().flat_map(|s| s.points.iter().copied());
    let (Some(x_range), Some(y_range)) = (padded_range(all().map(|p| p.0)), padded_range(all().map(|p| p.1))) else {
        return draw_no_data(root, chart);
    };
    match chart.x_categories.as_deref() {
        Some(names) if !names.is_empty() => {
            // Half a slot either side of the first and last category; indices outside the
            // list widen the axis so their points stay visible.
            let (lo, hi) =
                all().fold((-0.5_f64, names.len() as f64 - 0.5), |(lo, hi), p| (lo.min(p.0 - 0.5), hi.max(p.0 + 0.5)));
            // Sparser labels when long names would collide.
            let longest = names.iter().map(|n| n.chars().count()).max().unwrap_or(1);
            let plot_width = SIZE.0 - 2 * MARGIN - Y_LABEL_AREA;
            let fit = (plot_width as usize / (longest * 8 + 12)).max(1);
            let axis = CategoryAxis { names: names.to_vec(), range: lo..hi };
            draw_plot(root, chart, &data, axis, y_range, fit)
        }
        _ => {
            let axis: RangedCoordf64 = x_range.into();
            draw_plot(root, chart, &data, axis, y_range, 10)
        }
    }
}

/// The title, axes, series, Pareto front and legend, over the x axis `x_axis`.
fn draw_plot<DB, X>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
    data: &[Prepared<'_>],
    x_axis: X,
    y_range: Range<f64>,
    x_labels: usize,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB: DrawingBackend,
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let body = root.margin(MARGIN, MARGIN, MARGIN, MARGIN).titled(&chart.title, (FONT, TITLE_SIZE))?;
    let front: Vec<(f64, f64)> = if chart.pareto {
        let all: Vec<(f64, f64)> = data.iter().flat_map(|s| s.points.iter().copied()).collect();
        pareto_front(&all).into_iter().map(|i| all[i]).collect()
    } else {
        Vec::new()
    };

    let mut legend = Legend::new(root, chart, data, !front.is_empty())?;
    let (body_w, body_h) = body.dim_in_pixel();
    let (body_w, body_h) = (body_w as i32, body_h as i32);
    let (legend_w, legend_h) = legend.size();
    // A legend that would hide much of the plot (many series, long labels) gets a panel of
    // its own on the right instead.
    let inside = legend_w * 5 <= (body_w - Y_LABEL_AREA as i32) * 2 && legend_h * 2 <= body_h - X_LABEL_AREA as i32;
    let (plot_area, panel) = if inside {
        (body.clone(), None)
    } else {
        let panel_w = legend.fit_panel(root, LEGEND_PANEL_MAX_WIDTH, body_h)?;
        let (plot, panel) = body.split_horizontally(body_w - panel_w);
        (plot, Some(panel))
    };

    let mut ctx = ChartBuilder::on(&plot_area)
        .x_label_area_size(X_LABEL_AREA)
        .y_label_area_size(Y_LABEL_AREA)
        .build_cartesian_2d(x_axis, y_range)?;
    ctx.configure_mesh()
        .x_desc(chart.x_label.as_str())
        .y_desc(chart.y_label.as_str())
        .x_labels(x_labels)
        .y_labels(8)
        .label_style((FONT, TICK_LABEL_SIZE))
        .axis_desc_style((FONT, AXIS_DESC_SIZE))
        .draw()?;

    if front.len() > 1 {
        // The staircase of the best y reachable within each x: across, then up to the next
        // front point. Drawn first so the markers stay on top.
        let mut steps = vec![front[0]];
        for pair in front.windows(2) {
            steps.push((pair[1].0, pair[0].1));
            steps.push(pair[1]);
        }
        ctx.draw_series(DashedLineSeries::new(steps, 6, 4, front_style()))?;
    }
    for (i, series) in data.iter().enumerate() {
        let (colour, shape) = series_look(i);
        if chart.lines && series.points.len() > 1 {
            ctx.draw_series(LineSeries::new(series.points.iter().copied(), colour.stroke_width(2)))?;
        }
        draw_markers(ctx.plotting_area(), &series.points, shape, colour)?;
    }
    ctx.draw_series(front.iter().map(|&p| Circle::new(p, MARKER_RADIUS + 3, front_style())))?;

    // Legend positions are in backend pixels, so it is drawn on `root` (origin 0, 0).
    let top_left = match panel {
        Some(panel) => {
            let (x, y) = panel.get_base_pixel();
            (x + LEGEND_GAP, y)
        }
        None => {
            let points: Vec<Pixel> = data.iter().flat_map(|s| s.points.iter()).map(|p| ctx.backend_coord(p)).collect();
            let (xr, yr) = ctx.plotting_area().get_pixel_range();
            legend_corner(&points, xr, yr, (legend_w, legend_h))
        }
    };
    legend.draw(root, top_left)
}

/// The top-left pixel of the legend box in the corner of the plotting area (`xr` x `yr`)
/// where it covers the fewest of `points`, so the legend hides as little data as possible
/// (ties go to the upper right, then upper left, lower right, lower left).
fn legend_corner(points: &[Pixel], xr: Range<i32>, yr: Range<i32>, (w, h): (i32, i32)) -> Pixel {
    let (left, right) = (xr.start + LEGEND_INSET, xr.end - LEGEND_INSET - w);
    let (top, bottom) = (yr.start + LEGEND_INSET, yr.end - LEGEND_INSET - h);
    let covered = |&(x0, y0): &Pixel| {
        let r = MARKER_RADIUS;
        points.iter().filter(|&&(x, y)| x + r >= x0 && x - r <= x0 + w && y + r >= y0 && y - r <= y0 + h).count()
    };
    [(right, top), (left, top), (right, bottom), (left, bottom)].into_iter().min_by_key(covered).unwrap_or((right, top))
}

/// Series `i`'s colour and marker: ten colours, then the next marker shape.
fn series_look(i: usize) -> (RGBAColor, Shape) {
    let n = Tableau10::COLORS.len();
    let shape = [Shape::Circle, Shape::Triangle, Shape::Square][(i / n) % 3];
    (Tableau10::pick(i).to_rgba(), shape)
}

/// The dashed line and rings of the Pareto front.
fn front_style() -> ShapeStyle {
    ShapeStyle::from(&BLACK.mix(0.7)).stroke_width(2)
}

/// A marker's shape; they tell series apart once the colours repeat.
#[derive(Clone, Copy)]
enum Shape {
    Circle,
    Triangle,
    Square,
}

/// Filled markers of `shape` at `points`, in the area's own coordinates (chart values or
/// pixels).
fn draw_markers<DB, CT>(
    area: &DrawingArea<DB, CT>,
    points: &[CT::From],
    shape: Shape,
    colour: RGBAColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB: DrawingBackend,
    CT: CoordTranslate,
    CT::From: Clone + 'static,
{
    let style = colour.filled();
    let r = MARKER_RADIUS;
    for p in points {
        match shape {
            Shape::Circle => area.draw(&Circle::new(p.clone(), r, style))?,
            Shape::Triangle => area.draw(&TriangleMarker::new(p.clone(), r + 1, style))?,
            Shape::Square => area.draw(&(EmptyElement::at(p.clone()) + Rectangle::new([(-r, -r), (r, r)], style)))?,
        }
    }
    Ok(())
}

/// What a legend row shows left of its text.
#[derive(Clone, Copy)]
enum Glyph {
    Series { colour: RGBAColor, shape: Shape, line: bool },
    Front,
    Nothing,
}

const LEGEND_ROW: i32 = 18;
const LEGEND_PAD: i32 = 8;
const LEGEND_GLYPH: i32 = 24;
const LEGEND_GAP: i32 = 8;
const LEGEND_INSET: i32 = 8;
const LEGEND_PANEL_MAX_WIDTH: i32 = 240;

/// The legend, drawn by hand rather than by plotters so it can also sit in a side panel.
struct Legend {
    rows: Vec<(String, Glyph)>,
    text_w: i32,
}

impl Legend {
    fn new<DB: DrawingBackend>(
        root: &DrawingArea<DB, Shift>,
        chart: &Chart,
        data: &[Prepared<'_>],
        front: bool,
    ) -> Result<Self, DrawingAreaErrorKind<DB::ErrorType>> {
        let mut rows: Vec<(String, Glyph)> = data
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let (colour, shape) = series_look(i);
                let label = if s.points.is_empty() { format!("{} (no data)", s.label) } else { s.label.to_string() };
                let line = chart.lines;
                (label, Glyph::Series { colour, shape, line })
            })
            .collect();
        if front {
            rows.push(("Pareto front".to_string(), Glyph::Front));
        }
        let mut text_w = 0;
        for (label, _) in &rows {
            text_w = text_w.max(text_width(root, label)?);
        }
        Ok(Self { rows, text_w })
    }

    fn size(&self) -> (i32, i32) {
        (2 * LEGEND_PAD + LEGEND_GLYPH + LEGEND_GAP + self.text_w, 2 * LEGEND_PAD + LEGEND_ROW * self.rows.len() as i32)
    }

    /// Shortens labels to fit a side panel at most `max_w` wide and rows to fit `max_h`;
    /// returns the panel's width.
    fn fit_panel<DB: DrawingBackend>(
        &mut self,
        root: &DrawingArea<DB, Shift>,
        max_w: i32,
        max_h: i32,
    ) -> Result<i32, DrawingAreaErrorKind<DB::ErrorType>> {
        let max_text = max_w - LEGEND_GAP - 2 * LEGEND_PAD - LEGEND_GLYPH - LEGEND_GAP;
        let max_rows = ((max_h - 2 * LEGEND_PAD) / LEGEND_ROW).max(1) as usize;
        if self.rows.len() > max_rows {
            // The Pareto front's row stays: it explains the dashed line.
            let front = match self.rows.last() {
                Some((_, Glyph::Front)) => self.rows.pop(),
                _ => None,
            };
            let keep = max_rows.saturating_sub(1 + usize::from(front.is_some()));
            let hidden = self.rows.len() - keep;
            self.rows.truncate(keep);
            self.rows.push((format!("\u{2026} and {hidden} more"), Glyph::Nothing));
            self.rows.extend(front);
        }
        self.text_w = 0;
        for (label, _) in &mut self.rows {
            if text_width(root, label)? > max_text {
                // Drop characters until the rest and an ellipsis fit.
                let mut chars: Vec<char> = label.chars().collect();
                loop {
                    chars.pop();
                    let shortened: String = chars.iter().chain(['\u{2026}'].iter()).collect();
                    if chars.is_empty() || text_width(root, &shortened)? <= max_text {
                        *label = shortened;
                        break;
                    }
                }
            }
            self.text_w = self.text_w.max(text_width(root, label)?);
        }
        Ok(LEGEND_GAP + self.size().0)
    }

    /// Draws the box, glyphs and labels with the box's top-left corner at `(x, y)`.
    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        (x, y): Pixel,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        let (w, h) = self.size();
        root.draw(&Rectangle::new([(x, y), (x + w, y + h)], WHITE.mix(0.85).filled()))?;
        root.draw(&Rectangle::new([(x, y), (x + w, y + h)], BLACK.mix(0.4)))?;
        let style = legend_style().pos(Pos::new(HPos::Left, VPos::Center));
        for (row, (label, glyph)) in self.rows.iter().enumerate() {
            let cy = y + LEGEND_PAD + LEGEND_ROW * row as i32 + LEGEND_ROW / 2;
            let cx = x + LEGEND_PAD + LEGEND_GLYPH / 2;
            let half = LEGEND_GLYPH / 2 - 1;
            match *glyph {
                Glyph::Series { colour, shape, line } => {
                    if line {
                        let ends = vec![(cx - half, cy), (cx + half, cy)];
                        root.draw(&PathElement::new(ends, colour.stroke_width(2)))?;
                    }
                    draw_markers(root, &[(cx, cy)], shape, colour)?;
                }
                Glyph::Front => {
                    let ends = vec![(cx - half, cy), (cx + half, cy)];
                    root.draw(&DashedPathElement::new(ends, 6, 4, front_style()))?;
                    root.draw(&Circle::new((cx, cy), MARKER_RADIUS + 3, front_style()))?;
                }
                Glyph::Nothing => {}
            }
            let tx = x + LEGEND_PAD + LEGEND_GLYPH + LEGEND_GAP;
            root.draw(&Text::new(label.as_str(), (tx, cy), style.clone()))?;
        }
        Ok(())
    }
}

fn legend_style() -> TextStyle<'static> {
    TextStyle::from((FONT, LEGEND_SIZE)).color(&BLACK)
}

/// The width of `text` in the legend's font, in pixels.
fn text_width<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    text: &str,
) -> Result<i32, DrawingAreaErrorKind<DB::ErrorType>> {
    Ok(root.estimate_text_size(text, &legend_style())?.0 as i32)
}

/// The title and a centred "no data" note, for a chart with no finite point at all.
fn draw_no_data<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let area = root.margin(MARGIN, MARGIN, MARGIN, MARGIN).titled(&chart.title, (FONT, TITLE_SIZE))?;
    let (w, h) = area.dim_in_pixel();
    let grey = BLACK.mix(0.6);
    let style = TextStyle::from((FONT, 18)).color(&grey).pos(Pos::new(HPos::Center, VPos::Center));
    area.draw(&Text::new("no data (no finite points)", (w as i32 / 2, h as i32 / 2), style))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh folder under the system temp dir, unique to this process and test.
    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-plot-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Writes `chart`, checks both files, and returns the SVG text and the decoded PNG.
    fn write_and_read(chart: &Chart, stem: &Path) -> (String, image::RgbImage) {
        write_chart(chart, stem).unwrap();
        let svg = std::fs::read_to_string(with_suffix(stem, "svg")).unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        let png = image::open(with_suffix(stem, "png")).unwrap().to_rgb8();
        assert_eq!(png.dimensions(), SIZE);
        (svg, png)
    }

    /// Pixels clearly darker than the white background: text, axes and markers.
    fn dark_pixels(png: &image::RgbImage) -> usize {
        png.pixels().filter(|p| p.0.iter().all(|&c| c < 100)).count()
    }

    #[test]
    fn pareto_front_of_a_hand_made_set() {
        let points = [
            (1.0, 0.5),      // 0: front
            (2.0, 0.7),      // 1: beaten by 5 (same x, higher y)
            (1.5, 0.4),      // 2: beaten by 0
            (3.0, 0.7),      // 3: beaten by 1 and 5
            (0.5, 0.2),      // 4: front (fastest)
            (2.0, 0.9),      // 5: front (best y)
            (f64::NAN, 1.0), // 6: skipped
            (4.0, f64::INFINITY),
            (2.5, 0.9), // 8: beaten by 5 (same y, lower x)
        ];
        assert_eq!(pareto_front(&points), vec![4, 0, 5]);
    }

    #[test]
    fn pareto_front_edge_cases() {
        assert!(pareto_front(&[]).is_empty());
        assert!(pareto_front(&[(f64::NAN, f64::NAN)]).is_empty());
        assert_eq!(pareto_front(&[(1.0, 1.0)]), vec![0]);
        // Exact duplicates of a front point are all kept; one below them is not.
        assert_eq!(pareto_front(&[(1.0, 1.0), (1.0, 1.0), (1.0, 0.5)]), vec![0, 1]);
        // A strictly better point beats everything else.
        assert_eq!(pareto_front(&[(2.0, 1.0), (0.0, 3.0), (1.0, 2.0)]), vec![1]);
    }

    #[test]
    fn writes_svg_and_png_with_categories_nans_and_a_single_point() {
        let dir = temp_dir("categories");
        let chart = Chart {
            title: "mIoU by extractor".into(),
            x_label: "extractor".into(),
            y_label: "mIoU".into(),
            x_categories: Some(vec!["dino-vit".into(), "onnx".into(), "colour".into()]),
            series: vec![
                Series {
                    label: "synthetic".into(),
                    points: vec![(0.0, 0.8), (1.0, f64::NAN), (2.0, 0.6), (1.0, 0.75)],
                },
                Series { label: "flower & co".into(), points: vec![(1.0, 0.5)] },
            ],
            lines: true,
            pareto: true,
        };
        let stem = dir.join("by_extractor");
        let (svg, png) = write_and_read(&chart, &stem);
        assert!(svg.contains("synthetic"));
        // Labels are XML-escaped in the SVG.
        assert!(svg.contains("flower &amp; co"));
        assert!(svg.contains("Pareto front"));
        assert!(svg.contains("dino-vit") && svg.contains("colour"));
        // The embedded font drew text into the bitmap.
        assert!(dark_pixels(&png) > 1000, "too few dark pixels in the PNG");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn degenerate_inputs_never_panic() {
        let dir = temp_dir("degenerate");
        let series = |label: &str, points: Vec<(f64, f64)>| Series { label: label.into(), points };
        let charts = [
            // Nothing finite at all: a "no data" chart.
            Chart {
                title: "empty".into(),
                series: vec![series("nan", vec![(f64::NAN, 1.0), (2.0, f64::NEG_INFINITY)]), series("none", vec![])],
                pareto: true,
                lines: true,
                ..Chart::default()
            },
            Chart::default(),
            // One point, all-equal x and all-equal y.
            Chart { series: vec![series("one", vec![(3.0, 0.5)])], pareto: true, ..Chart::default() },
            Chart {
                series: vec![series("flat", vec![(0.0, 0.0), (0.0, 0.0), (0.0, 0.0)])],
                lines: true,
                pareto: true,
                ..Chart::default()
            },
            Chart {
                series: vec![series("tiny", vec![(1e10, 5e-324), (1e10 + 1e-5, 5e-324)])],
                lines: true,
                ..Chart::default()
            },
            Chart {
                series: vec![series("huge", vec![(-1e300, 1e300), (1e300, -1e300), (1e308, 0.0)])],
                ..Chart::default()
            },
            // Category indices past the list, and an empty list (numeric axis).
            Chart {
                x_categories: Some(vec!["a".into()]),
                series: vec![series("out", vec![(-2.0, 1.0), (4.0, 2.0), (1e300, 3.0)])],
                ..Chart::default()
            },
            Chart {
                x_categories: Some(vec![]),
                series: vec![series("numeric", vec![(0.0, 1.0), (1.0, 2.0)])],
                ..Chart::default()
            },
        ];
        for (i, chart) in charts.iter().enumerate() {
            let (svg, _) = write_and_read(chart, &dir.join(format!("chart{i}")));
            if i == 0 {
                assert!(svg.contains("no data"));
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn many_series_get_a_side_legend_that_keeps_the_front() {
        let dir = temp_dir("many");
        let chart = Chart {
            title: "synthetic: mIoU against run time".into(),
            x_label: "run time (s)".into(),
            y_label: "mIoU".into(),
            series: (0..40)
                .map(|i| Series {
                    label: if i == 1 {
                        "a variant label far too long for the legend panel to hold".into()
                    } else {
                        format!("variant {i}")
                    },
                    points: vec![(f64::from(i), f64::from((i * 37) % 17))],
                })
                .collect(),
            pareto: true,
            ..Chart::default()
        };
        let (svg, _) = write_and_read(&chart, &dir.join("many"));
        assert!(svg.contains("variant 0") && svg.contains("Pareto front"));
        assert!(svg.contains("a variant label far") && !svg.contains("panel to hold"));
        assert!(svg.contains("more") && !svg.contains("variant 39"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn stem_keeps_its_dot_the_folder_is_made_and_errors_name_the_file() {
        let dir = temp_dir("paths");
        let chart = Chart {
            title: "lr sweep".into(),
            x_label: "wall time (s)".into(),
            y_label: "mIoU".into(),
            series: (0..12)
                .map(|i| Series { label: format!("run {i}"), points: vec![(f64::from(i), f64::from(i % 5) / 5.0)] })
                .collect(),
            pareto: true,
            ..Chart::default()
        };
        write_and_read(&chart, &dir.join("lr_0.1"));
        assert!(dir.join("lr_0.1.svg").is_file() && dir.join("lr_0.1.png").is_file());

        write_chart(&chart, &dir.join("new-folder").join("chart")).unwrap();
        assert!(dir.join("new-folder/chart.svg").is_file(), "the folder is made");
        std::fs::write(dir.join("a-file"), "").unwrap();
        let err = format!("{:#}", write_chart(&chart, &dir.join("a-file").join("chart")).unwrap_err());
        assert!(err.contains("chart.svg"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
