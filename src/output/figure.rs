//! Pictures of results, drawn one way everywhere: the bundled font (DejaVu Sans), matplotlib's
//! viridis for magnitudes and RdBu for signed values, signed-error heat maps with a labelled
//! colour bar, the envmap as a lat-long picture with its cell grid and the lights marked, and
//! charts written as SVG beside PNG from one drawing ([`Chart`]).

use std::path::Path;

use glam::Vec3;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::envmap::Envmap;
use crate::envmap::grid;
use crate::error::{Error, Result};
use crate::imageio;

/// The font of every figure, bundled so that a figure looks the same on every machine (its
/// licence is beside it in `assets/fonts/`).
pub const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// The family name figures ask for: SVG files name it, so a viewer with DejaVu Sans draws them
/// as the PNG shows them.
pub const FAMILY: &str = "DejaVu Sans";

/// Registers [`FONT`] with plotters under [`FAMILY`] (once per process).
pub fn font() -> Result<()> {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        Err(Error::Invalid(
            "the bundled figure font does not load".into(),
        ))
    }
}

/// A figure's text style: [`FAMILY`] at `size` pixels.
pub fn text(size: u32) -> TextStyle<'static> {
    (FAMILY, size).into_font().color(&BLACK)
}

fn lerp_stops(stops: &[[f32; 3]], t: f32) -> [u8; 3] {
    // ±∞ clamp to the ends; NaN (no value) takes the top colour, callers grey it first.
    let t = if t.is_nan() { 1.0 } else { t.clamp(0.0, 1.0) } * (stops.len() - 1) as f32;
    let i = (t as usize).min(stops.len() - 2);
    let c = Vec3::from(stops[i]).lerp(Vec3::from(stops[i + 1]), t - i as f32);
    (c * 255.0 + 0.5).to_array().map(|v| v as u8)
}

/// matplotlib's viridis (perceptually uniform, dark to bright) at `t` in [0, 1], from 17 of
/// its stops.
pub fn viridis(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 17] = [
        [0.2670, 0.0049, 0.3294],
        [0.2823, 0.0950, 0.4173],
        [0.2788, 0.1755, 0.4834],
        [0.2590, 0.2515, 0.5247],
        [0.2297, 0.3224, 0.5457],
        [0.1994, 0.3876, 0.5546],
        [0.1727, 0.4488, 0.5579],
        [0.1490, 0.5081, 0.5573],
        [0.1276, 0.5669, 0.5506],
        [0.1206, 0.6258, 0.5335],
        [0.1579, 0.6838, 0.5017],
        [0.2461, 0.7389, 0.4520],
        [0.3692, 0.7889, 0.3829],
        [0.5160, 0.8312, 0.2943],
        [0.6785, 0.8637, 0.1895],
        [0.8456, 0.8873, 0.0997],
        [0.9932, 0.9062, 0.1439],
    ];
    lerp_stops(&STOPS, t)
}

/// matplotlib's RdBu reversed (ColorBrewer's diverging map: blue below zero, white at zero,
/// red above) at `t` in [−1, 1], from 17 of its stops.
pub fn diverging(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 17] = [
        [0.0196, 0.1882, 0.3804],
        [0.0885, 0.3211, 0.5649],
        [0.1634, 0.4450, 0.6975],
        [0.2471, 0.5557, 0.7541],
        [0.4207, 0.6764, 0.8187],
        [0.6065, 0.7898, 0.8803],
        [0.7615, 0.8685, 0.9246],
        [0.8780, 0.9257, 0.9519],
        [0.9691, 0.9665, 0.9649],
        [0.9839, 0.8976, 0.8468],
        [0.9825, 0.8007, 0.7061],
        [0.9603, 0.6678, 0.5363],
        [0.8946, 0.5038, 0.3998],
        [0.8171, 0.3322, 0.2810],
        [0.7285, 0.1550, 0.1974],
        [0.5769, 0.0554, 0.1493],
        [0.4039, 0.0000, 0.1216],
    ];
    lerp_stops(&STOPS, 0.5 * (t + 1.0))
}

/// Colour of series `i` of `n` in a chart: evenly spaced along viridis, its bright yellow end
/// left out (it vanishes on white).
pub fn series_colour(i: usize, n: usize) -> RGBColor {
    let t = if n <= 1 {
        0.0
    } else {
        0.85 * i as f32 / (n - 1) as f32
    };
    let [r, g, b] = viridis(t);
    RGBColor(r, g, b)
}

/// Ticks of a log axis from 10^`lo` to 10^`hi`: the 1-2-5 steps of every decade inside,
/// or every integer step of the decade (1, 2, …, 9) when the range holds fewer than three.
pub fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    // An axis of more than 30 decades (or without ends) is not one a chart draws.
    if !(lo.is_finite() && hi.is_finite() && hi - lo <= 30.0) {
        return Vec::new();
    }
    let ticks = |mantissas: &[f64]| -> Vec<f64> {
        let mut v = Vec::new();
        for decade in lo.floor() as i32..=hi.ceil() as i32 {
            for m in mantissas {
                let t = m * 10f64.powi(decade);
                let l = t.log10();
                if l >= lo - 1e-9 && l <= hi + 1e-9 {
                    v.push(t);
                }
            }
        }
        v
    };
    let v = ticks(&[1.0, 2.0, 5.0]);
    if v.len() >= 3 {
        v
    } else {
        ticks(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0])
    }
}

/// A tick value as written on an axis: no trailing zeros (0.2, 5, 10, 0.05).
pub fn tick_label(t: f64) -> String {
    let r = (t * 1e6).round() / 1e6;
    format!("{r}")
}

/// Grey of pixels a heat map leaves out (masked out: background, saturated, or no scene).
pub const MASKED: [u8; 3] = [128, 128, 128];

/// Per pixel, the signed error of `image` against `reference` as a fraction of the
/// reference's mean radiance over the mask: the channels' mean of (image − reference) over the
/// channels' mean of the reference. The mean of its magnitude is the view's relMAE when the
/// channels err the same way. NaN outside the mask; all NaN when the reference is black there.
pub fn signed_error(image: &imageio::Image, reference: &imageio::Image, mask: &[bool]) -> Vec<f32> {
    let (sum, n) = reference
        .rgb
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .fold((0.0f64, 0usize), |(s, n), (c, _)| {
            (s + c.element_sum() as f64 / 3.0, n + 1)
        });
    let mean = (sum / n.max(1) as f64) as f32;
    image
        .rgb
        .iter()
        .zip(&reference.rgb)
        .zip(mask)
        .map(|((x, r), &m)| {
            if m && mean > 0.0 {
                (*x - *r).element_sum() / 3.0 / mean
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// The colour bar's half-range shared by `errors` (maps of [`signed_error`], taken one at a
/// time so that only their magnitudes are held at once): the 99th percentile of their
/// magnitudes, so one pixel's outlier does not wash out the rest; 1 when nothing is finite
/// and non-zero.
pub fn shared_scale<E: AsRef<[f32]>>(errors: impl IntoIterator<Item = E>) -> f32 {
    let mut v: Vec<f32> = Vec::new();
    for e in errors {
        v.extend(e.as_ref().iter().filter(|e| e.is_finite()).map(|e| e.abs()));
    }
    if v.is_empty() {
        return 1.0;
    }
    let k = ((v.len() - 1) as f32 * 0.99) as usize;
    let (_, p, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    if *p > 0.0 { *p } else { 1.0 }
}

/// Where a heat map's pixels go in its PNG: its map starts at (`left`, `top`); each image
/// pixel is a `zoom × zoom` block of it, or each of its pixels the mean of a `block × block`
/// block of the image (one of the two is 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeatMapLayout {
    pub left: u32,
    pub top: u32,
    pub zoom: u32,
    pub block: u32,
}

impl HeatMapLayout {
    /// The layout of a `width × height` image: small images enlarged by the largest whole
    /// factor (at most 8) that keeps their longer side within 400 pixels, large ones reduced
    /// by block means to at most 640.
    pub fn of(width: u32, height: u32) -> Self {
        let long = width.max(height).max(1);
        HeatMapLayout {
            left: 10,
            top: 34,
            zoom: (400 / long).clamp(1, 8),
            block: long.div_ceil(640),
        }
    }

    /// The map's size in the PNG, pixels.
    pub fn map_size(&self, width: u32, height: u32) -> (u32, u32) {
        (
            width.div_ceil(self.block) * self.zoom,
            height.div_ceil(self.block) * self.zoom,
        )
    }

    /// The value of the map's pixel (`x`, `y`): the image pixel under it, or the mean of the
    /// finite values of the block under it (NaN when it has none).
    fn value(&self, err: &[f32], width: u32, height: u32, x: u32, y: u32) -> f32 {
        if self.block == 1 {
            return err[((y / self.zoom) * width + x / self.zoom) as usize];
        }
        let (x0, y0) = (x * self.block, y * self.block);
        let (mut sum, mut n) = (0.0f64, 0u32);
        for yy in y0..(y0 + self.block).min(height) {
            for xx in x0..(x0 + self.block).min(width) {
                let e = err[(yy * width + xx) as usize];
                if e.is_finite() {
                    sum += e as f64;
                    n += 1;
                }
            }
        }
        if n == 0 {
            f32::NAN
        } else {
            (sum / n as f64) as f32
        }
    }
}

/// Writes a signed-error heat map (`err` from [`signed_error`], `width × height`) as a PNG:
/// `title` above, the map through [`diverging`] from −`scale` to +`scale` (grey where NaN),
/// and beside it a colour bar labelled in percent of the reference's mean radiance.
pub fn write_error_map(
    path: &Path,
    title: &str,
    size: (u32, u32),
    err: &[f32],
    scale: f32,
) -> Result<HeatMapLayout> {
    write_signed_map(path, title, size, err, scale, "error / mean reference")
}

/// [`write_error_map`] of any signed fraction, its colour bar labelled `bar_label`.
pub fn write_signed_map(
    path: &Path,
    title: &str,
    (width, height): (u32, u32),
    err: &[f32],
    scale: f32,
    bar_label: &str,
) -> Result<HeatMapLayout> {
    font()?;
    let layout = HeatMapLayout::of(width, height);
    let (iw, ih) = layout.map_size(width, height);
    let bar = 150;
    // Wide enough for the title (DejaVu Sans at 15 px: under 9 px a character).
    let title_width = 9 * title.chars().count() as u32 + 2 * layout.left;
    let size = (
        (layout.left + iw + bar).max(title_width),
        (layout.top + ih + 12).max(layout.top + 200),
    );
    draw_png(path, size, |root| {
        for y in 0..ih {
            for x in 0..iw {
                let e = layout.value(err, width, height, x, y);
                let [r, g, b] = if e.is_nan() {
                    MASKED
                } else {
                    diverging(e / scale)
                };
                root.draw_pixel(
                    ((layout.left + x) as i32, (layout.top + y) as i32),
                    &RGBColor(r, g, b),
                )?;
            }
        }
        root.draw(&Text::new(
            title.to_string(),
            (layout.left as i32, 10),
            text(15),
        ))?;
        // The colour bar: +scale at the top, −scale at the bottom, ticks at quarters.
        let (bx, by0) = ((layout.left + iw + 16) as i32, layout.top as i32 + 8);
        let by1 = (layout.top + ih.max(200)) as i32 - 22;
        for y in by0..=by1 {
            let t = 1.0 - 2.0 * (y - by0) as f32 / (by1 - by0) as f32;
            let [r, g, b] = diverging(t);
            root.draw(&Rectangle::new(
                [(bx, y), (bx + 14, y + 1)],
                RGBColor(r, g, b).filled(),
            ))?;
        }
        root.draw(&Rectangle::new([(bx, by0), (bx + 14, by1 + 1)], BLACK))?;
        for k in 0..=4 {
            let v = scale * (1.0 - 0.5 * k as f32);
            let y = by0 + (by1 - by0) * k / 4;
            root.draw(&PathElement::new([(bx + 14, y), (bx + 18, y)], BLACK))?;
            root.draw(&Text::new(
                percent_label(v, scale),
                (bx + 21, y),
                text(12).pos(Pos::new(HPos::Left, VPos::Center)),
            ))?;
        }
        root.draw(&Text::new(
            bar_label.to_string(),
            (bx - 6, by1 + 8),
            text(11),
        ))?;
        Ok(())
    })?;
    Ok(layout)
}

/// `v` (a fraction) in percent, signed, with as many decimals as the ticks of `scale` need
/// to differ (ticks at quarters of ±`scale`).
fn percent_label(v: f32, scale: f32) -> String {
    let step = 50.0 * scale; // percent between ticks
    let decimals = if step > 0.0 && step.is_finite() {
        (1.0 - step.log10().floor()).clamp(0.0, 6.0) as usize
    } else {
        2
    };
    if v == 0.0 {
        format!("{:.*}%", decimals, 0.0)
    } else {
        format!("{:+.*}%", decimals, 100.0 * v)
    }
}

/// What a mark on the envmap picture stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarkKind {
    /// A light of the scene (the truth): an open circle.
    True,
    /// A light the estimate recovered: a cross.
    Estimated,
}

/// A direction marked on the envmap picture, with its label.
#[derive(Debug, Clone)]
pub struct Mark {
    /// Unit direction, glTF frame (+Y up).
    pub direction: Vec3,
    pub kind: MarkKind,
    pub label: String,
}

/// Size of the envmap picture, pixels.
const ENVMAP_SIZE: (u32, u32) = (1100, 640);

/// Writes the envmap as a lat-long picture (azimuth φ = atan2(x, −z) across, elevation above
/// the horizon up; the glTF frame, +Y up): its radiance tone-mapped (exposure putting the
/// brightest cell's luminance at 3, then x/(1+x) per channel and the sRGB curve), the ring
/// grid's cells outlined, and `marks` with their labels.
pub fn write_envmap_figure(path: &Path, title: &str, env: &Envmap, marks: &[Mark]) -> Result<()> {
    font()?;
    let exposure = {
        let top = env
            .radiance()
            .iter()
            .map(|c| imageio::luminance(*c))
            .fold(0.0f32, f32::max);
        if top > 0.0 { 3.0 / top } else { 1.0 }
    };
    let tone = |c: Vec3| {
        let c = c * exposure;
        (c / (Vec3::ONE + c))
            .to_array()
            .map(|v| (imageio::linear_to_srgb(v) * 255.0 + 0.5) as u8)
    };
    draw_png(path, ENVMAP_SIZE, |root| {
        let mut ch = ChartBuilder::on(root)
            .caption(title, text(18))
            .margin(12)
            .x_label_area_size(44)
            .y_label_area_size(52)
            .build_cartesian_2d(0f64..360f64, -90f64..90f64)?;
        ch.configure_mesh()
            .disable_mesh()
            .x_labels(9)
            .y_labels(7)
            .x_label_formatter(&|x| format!("{x:.0}°"))
            .y_label_formatter(&|y| format!("{y:.0}°"))
            .x_desc("azimuth φ = atan2(x, −z)  (0° = −Z, 90° = +X)")
            .y_desc("elevation above the horizon (+Y up)")
            .label_style(text(13))
            .axis_desc_style(text(14))
            .draw()?;
        let (xs, ys) = ch.plotting_area().get_pixel_range();
        let (w, h) = ((xs.end - xs.start) as f64, (ys.end - ys.start) as f64);
        for py in ys.clone() {
            let theta = ((py - ys.start) as f64 + 0.5) / h * std::f64::consts::PI;
            for px in xs.clone() {
                let phi = ((px - xs.start) as f64 + 0.5) / w * std::f64::consts::TAU;
                let d = grid::direction(theta, phi).as_vec3();
                let [r, g, b] = tone(env.radiance()[env.grid.lookup(d) as usize]);
                root.draw_pixel((px, py), &RGBColor(r, g, b))?;
            }
        }
        // Cell outlines: each band's top edge, and each cell's first azimuth edge.
        let line = WHITE.mix(0.35);
        let elevation = |theta: f64| 90.0 - theta.to_degrees();
        for cell in 0..env.grid.cell_count() as u32 {
            let b = env.grid.bounds(cell);
            let (top, bottom) = (elevation(b.theta_min), elevation(b.theta_max));
            let (ring, index) = env.grid.ring_of(cell);
            if index == 0 && b.theta_min > 0.0 {
                ch.draw_series([PathElement::new([(0.0, top), (360.0, top)], line)])?;
            }
            if env.grid.ring_len(ring) > 1 {
                let x = b.phi_min.rem_euclid(std::f64::consts::TAU).to_degrees();
                ch.draw_series([PathElement::new([(x, top), (x, bottom)], line)])?;
            }
        }
        // Labels go where they cover no mark and no other label.
        let at: Vec<(i32, i32)> = marks
            .iter()
            .map(|m| {
                let (theta, phi) = grid::angles(m.direction);
                ch.backend_coord(&(phi.to_degrees(), elevation(theta)))
            })
            .collect();
        let mut placed: Vec<(i32, i32, i32, i32)> = at
            .iter()
            .map(|&(x, y)| (x - 10, y - 10, x + 11, y + 11))
            .collect();
        for (m, &c) in marks.iter().zip(&at) {
            match m.kind {
                MarkKind::True => {
                    root.draw(&Circle::new(c, 9, WHITE.stroke_width(3)))?;
                    root.draw(&Circle::new(c, 9, BLACK.stroke_width(1)))?;
                }
                MarkKind::Estimated => {
                    for (dx, dy) in [(7, 7), (7, -7)] {
                        let seg = [(c.0 - dx, c.1 - dy), (c.0 + dx, c.1 + dy)];
                        root.draw(&PathElement::new(seg, WHITE.stroke_width(4)))?;
                        root.draw(&PathElement::new(seg, RED.stroke_width(2)))?;
                    }
                }
            }
            let style = text(13);
            let (tw, th) = root.estimate_text_size(&m.label, &style)?;
            let (tw, th) = (tw as i32 + 6, th as i32 + 4);
            let spot = label_spot(c, (tw, th), &placed, (xs.clone(), ys.clone()));
            placed.push(spot);
            root.draw(&Rectangle::new(
                [(spot.0, spot.1), (spot.2, spot.3)],
                WHITE.mix(0.8).filled(),
            ))?;
            root.draw(&Text::new(m.label.clone(), (spot.0 + 3, spot.1 + 2), style))?;
        }
        Ok(())
    })
}

/// Where a label box of `size` goes beside the point `at`: the first of eight spots around it
/// that overlaps no box already `placed` and stays inside the plot (when none does, the one
/// that covers least). Boxes are (left, top, right, bottom) in pixels.
pub fn label_spot(
    at: (i32, i32),
    (w, h): (i32, i32),
    placed: &[(i32, i32, i32, i32)],
    (xs, ys): (std::ops::Range<i32>, std::ops::Range<i32>),
) -> (i32, i32, i32, i32) {
    let (x, y) = at;
    let spots = [
        (x + 12, y - h - 4),
        (x + 12, y + 4),
        (x - 12 - w, y - h - 4),
        (x - 12 - w, y + 4),
        (x + 12, y - h / 2),
        (x - 12 - w, y - h / 2),
        (x - w / 2, y - h - 12),
        (x - w / 2, y + 12),
    ];
    let boxes = spots.map(|(l, t)| (l, t, l + w, t + h));
    // Pixels of `b` covered by placed boxes, and outside the plot (counted double).
    let cost = |b: &(i32, i32, i32, i32)| -> i64 {
        let covered: i64 = placed
            .iter()
            .map(|p| {
                let dx = (b.2.min(p.2) - b.0.max(p.0)).max(0) as i64;
                let dy = (b.3.min(p.3) - b.1.max(p.1)).max(0) as i64;
                dx * dy
            })
            .sum();
        let inside = (b.2.min(xs.end) - b.0.max(xs.start)).max(0) as i64
            * (b.3.min(ys.end) - b.1.max(ys.start)).max(0) as i64;
        covered + 2 * (w as i64 * h as i64 - inside)
    };
    // The first free spot; when none is, the one that covers least.
    boxes.iter().copied().min_by_key(cost).unwrap_or(boxes[0])
}

/// What drawing a figure returns: plotters' errors, boxed (the caller names the file).
pub type Drawn = std::result::Result<(), Box<dyn std::error::Error>>;

/// Draws with `draw` into a white RGB canvas of `size` and writes it as a PNG, atomically.
fn draw_png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Drawn,
) -> Result<()> {
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        draw(&root)
            .and_then(|_| Ok(root.present()?))
            .map_err(|e| Error::file(path, format!("cannot draw the figure: {e}")))?;
    }
    imageio::write_rgb8_png(path, size.0, size.1, buf)
}

/// A chart: drawn by the same code on any plotters backend, so that its SVG and its PNG are
/// one drawing.
pub trait Chart {
    /// Pixel size of the chart.
    fn size(&self) -> (u32, u32) {
        (900, 600)
    }
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static;
}

/// Writes `chart` as `path` (a `.png`) and the same drawing as SVG beside it (`.svg`).
pub fn write_chart(path: &Path, chart: &impl Chart) -> Result<()> {
    font()?;
    let size = chart.size();
    let fail =
        |e: Box<dyn std::error::Error>| Error::file(path, format!("cannot draw the chart: {e}"));
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        let drawn: Drawn = (|| {
            root.fill(&WHITE)?;
            chart.draw(&root)?;
            Ok(root.present()?)
        })();
        drawn.map_err(fail)?;
    }
    draw_png(path, size, |root| {
        root.fill(&WHITE)?;
        chart.draw(root)
    })?;
    imageio::write_bytes(&path.with_extension("svg"), svg.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lum(c: [u8; 3]) -> f32 {
        0.2126 * c[0] as f32 + 0.7152 * c[1] as f32 + 0.0722 * c[2] as f32
    }

    #[test]
    fn viridis_grows_in_brightness() {
        let mut last = -1.0;
        for i in 0..=100 {
            let l = lum(viridis(i as f32 / 100.0));
            assert!(l > last, "{i}");
            last = l;
        }
    }

    #[test]
    fn diverging_is_white_at_zero_and_darkens_both_ways() {
        let mid = diverging(0.0);
        assert!(mid.iter().all(|&c| c >= 240), "{mid:?}");
        let (mut up, mut down) = (lum(mid), lum(mid));
        for i in 1..=50 {
            let (u, d) = (
                lum(diverging(i as f32 / 50.0)),
                lum(diverging(-i as f32 / 50.0)),
            );
            assert!(u < up + 0.5 && d < down + 0.5, "{i}");
            (up, down) = (u, d);
        }
        let (red, blue) = (diverging(1.0), diverging(-1.0));
        assert!(red[0] > red[2] && blue[2] > blue[0]);
    }

    #[test]
    fn signed_error_is_relative_to_the_mean_reference() {
        let img = |v: &[f32]| imageio::Image {
            width: v.len() as u32,
            height: 1,
            rgb: v.iter().map(|&x| Vec3::splat(x)).collect(),
            alpha: None,
        };
        let e = signed_error(
            &img(&[1.5, 2.0, 9.0]),
            &img(&[1.0, 3.0, 0.0]),
            &[true, true, false],
        );
        assert_eq!(e[0], 0.25);
        assert_eq!(e[1], -0.5);
        assert!(e[2].is_nan());
        // The 99th percentile of the magnitudes over every map, NaN left out.
        let ramp: Vec<f32> = (0..=100).map(|i| -(i as f32) / 100.0).collect();
        assert_eq!(shared_scale([e, ramp]), 0.98);
    }

    #[test]
    fn log_ticks_step_1_2_5() {
        assert_eq!(
            log_ticks(-1.2, 1.1),
            vec![0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
        );
        // Less than a decade: every integer step.
        assert_eq!(log_ticks(0.35, 0.8), vec![3.0, 4.0, 5.0, 6.0]);
        assert_eq!(tick_label(0.1 * 2.0), "0.2");
        assert_eq!(tick_label(10.0), "10");
    }

    #[test]
    fn labels_find_free_spots() {
        let area = (0..400, 0..300);
        let a = label_spot((100, 100), (40, 14), &[], area.clone());
        let b = label_spot((100, 100), (40, 14), &[a], area.clone());
        assert_ne!(a, b);
        let disjoint = |p: (i32, i32, i32, i32), q: (i32, i32, i32, i32)| {
            p.2 <= q.0 || q.2 <= p.0 || p.3 <= q.1 || q.3 <= p.1
        };
        assert!(disjoint(a, b));
        // Near the right edge, the label goes left of the point.
        let c = label_spot((395, 100), (40, 14), &[], area);
        assert!(c.2 <= 400 && c.0 < 395);
    }
}
