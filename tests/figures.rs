//! The charts of `report` as a reader sees them: on the committed experiments' trials, every
//! chart has its SVG beside its PNG, and no two texts of a chart overlap — each text's box is
//! measured with the bundled font's own glyph advances at the size and anchor the SVG gives
//! it, at the size of the PNG's rasterised text (so two ring labels drawn into one "33" fail).

use std::path::Path;

use ab_glyph::{Font, FontRef};

/// A text's box, pixels: (left, top, right, bottom), and its text.
type TextBox = ([f64; 4], String);

/// How an SVG's text is drawn in its PNG.
#[derive(Clone, Copy)]
enum Raster {
    /// plotters' PNG beside it: the same text, rasterised larger (see [`text_boxes`]).
    Plotters,
    /// The SVG itself, rasterised as a browser draws it (`rsvg-convert`).
    AsWritten,
}

/// The boxes of every `<text>` in an SVG: `x`, `y`, `dy` (in em or ex), `text-anchor`,
/// `font-size` (its own or an ancestor's) and a `rotate(θ, x, y)` transform.
fn text_boxes(svg: &str, font: &FontRef, raster: Raster) -> Vec<TextBox> {
    let doc = roxmltree::Document::parse(svg).unwrap();
    let em = font.units_per_em().unwrap() as f64;
    let height_em = (font.ascent_unscaled() - font.descent_unscaled()) as f64 / em;
    let scale = match raster {
        Raster::Plotters => 1.24 / height_em,
        Raster::AsWritten => 1.0,
    };
    let mut boxes = Vec::new();
    for t in doc.descendants().filter(|n| n.has_tag_name("text")) {
        let text = t.text().unwrap_or("").trim().to_string();
        if text.is_empty() {
            continue;
        }
        let num = |a: &str| t.attribute(a).unwrap().parse::<f64>().unwrap();
        // plotters rasterises its PNG's text at its own size (the SVG's font-size is that
        // over 1.24, and ab_glyph scales glyphs by ascent − descent, not the em): the larger
        // of the two drawings is measured.
        let font_size = t
            .ancestors()
            .find_map(|n| n.attribute("font-size"))
            .unwrap()
            .parse::<f64>()
            .unwrap();
        let size = font_size * scale;
        let (x, y) = (num("x"), num("y"));
        let width: f64 = text
            .chars()
            .map(|c| font.h_advance_unscaled(font.glyph_id(c)) as f64 / em * size)
            .sum();
        // Baseline from dy; DejaVu's x-height is 0.55 em.
        let dy = t.attribute("dy").unwrap_or("0");
        let shift = if let Some(v) = dy.strip_suffix("em") {
            v.parse::<f64>().unwrap() * size
        } else if let Some(v) = dy.strip_suffix("ex") {
            v.parse::<f64>().unwrap() * 0.55 * size
        } else {
            dy.parse::<f64>().unwrap_or(0.0)
        };
        let (left, right) = match t.attribute("text-anchor").unwrap_or("start") {
            "middle" => (-width / 2.0, width / 2.0),
            "end" => (-width, 0.0),
            _ => (0.0, width),
        };
        // Digits and capitals rise 0.73 em above the baseline; descenders reach 0.24 em below.
        let (top, bottom) = (shift - 0.73 * size, shift + 0.24 * size);
        // rotate(θ, x, y) or rotate(θ x y) about the text's own anchor.
        let angle = t.attribute("transform").map(|tr| {
            let args = tr
                .strip_prefix("rotate(")
                .unwrap_or_else(|| panic!("a transform the test does not know: {tr}"));
            let a: f64 = args.split([',', ' ', ')']).next().unwrap().parse().unwrap();
            a.rem_euclid(360.0)
        });
        let b = match angle {
            Some(270.0) => [x + top, y - right, x + bottom, y - left],
            Some(90.0) => [x - bottom, y + left, x - top, y + right],
            Some(0.0) | None => [x + left, y + top, x + right, y + bottom],
            Some(a) => panic!("a rotation the test does not know: {a}°"),
        };
        boxes.push((b, text));
    }
    boxes
}

/// The overlapping pairs among `boxes` (by more than half a pixel each way).
fn overlaps(boxes: &[TextBox]) -> Vec<String> {
    let mut found = Vec::new();
    for (i, (a, ta)) in boxes.iter().enumerate() {
        for (b, tb) in &boxes[i + 1..] {
            let dx = a[2].min(b[2]) - a[0].max(b[0]);
            let dy = a[3].min(b[3]) - a[1].max(b[1]);
            if dx > 0.5 && dy > 0.5 {
                found.push(format!("{ta:?} {a:.0?} and {tb:?} {b:.0?}"));
            }
        }
    }
    found
}

fn font() -> FontRef<'static> {
    FontRef::try_from_slice(lightprobe::output::figure::FONT).unwrap()
}

#[test]
fn the_overlap_test_sees_two_labels_drawn_into_one() {
    let font = font();
    let svg = r#"<svg xmlns="http://www.w3.org/2000/svg">
        <text x="100" y="50" dy="0.76em" text-anchor="start" font-size="10">3</text>
        <text x="104" y="50" dy="0.76em" text-anchor="start" font-size="10">3</text>
        <text x="200" y="50" dy="0.76em" text-anchor="start" font-size="10">21</text>
        <text x="30" y="300" dy="0.76em" text-anchor="middle" font-size="12"
              transform="rotate(270, 30, 300)">relMAE (%)</text>
        <text x="30" y="340" dy="0.76em" text-anchor="start" font-size="12">x</text>
    </svg>"#;
    let boxes = text_boxes(svg, &font, Raster::Plotters);
    // A digit of DejaVu Sans is 0.636 em wide; font-size 10 in the SVG is drawn in the PNG
    // with an em of 10 × 1.24 / 1.164 (DejaVu's ascent − descent is 1.164 em).
    let want = 0.636 * 10.0 * 1.24 / (2384.0 / 2048.0);
    assert!((boxes[0].0[2] - boxes[0].0[0] - want).abs() < 0.01);
    let found = overlaps(&boxes);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(found[0].starts_with("\"3\""));
    // The rotated label spans y = 300 ± half its width (33 px): it misses "x" at y = 340.
    let rotated = &boxes[3].0;
    assert!(rotated[2] - rotated[0] < 15.0 && rotated[3] - rotated[1] > 50.0);
}

#[test]
fn report_charts_have_svgs_and_no_overlapping_text() {
    let font = font();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/experiment");
    let mut charts = 0;
    for study in ["solvers", "albedo", "spheres", "sweep"] {
        let tmp = tempfile::tempdir().unwrap();
        for entry in std::fs::read_dir(root.join(study)).unwrap().flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.ends_with(".jsonl") {
                std::fs::copy(entry.path(), tmp.path().join(&name)).unwrap();
            }
        }
        let summary = lightprobe::experiment::report::report(tmp.path()).unwrap();
        assert!(!summary.charts.is_empty(), "{study}");
        for png in &summary.charts {
            let svg = png.with_extension("svg");
            let text = std::fs::read_to_string(&svg)
                .unwrap_or_else(|e| panic!("{study}: {}: {e}", svg.display()));
            let boxes = text_boxes(&text, &font, Raster::Plotters);
            assert!(boxes.len() > 5, "{study}: {} has no labels", svg.display());
            let found = overlaps(&boxes);
            assert!(
                found.is_empty(),
                "{study}: {}: texts overlap: {found:#?}",
                svg.display()
            );
            assert!(png.is_file());
            charts += 1;
        }
        // The page shows every chart's SVG.
        let html = std::fs::read_to_string(tmp.path().join("index.html")).unwrap();
        for png in &summary.charts {
            let svg = png
                .file_name()
                .unwrap()
                .to_string_lossy()
                .replace(".png", ".svg");
            assert!(html.contains(&format!("src=\"{svg}\"")), "{study}: {svg}");
        }
    }
    assert!(charts >= 10, "{charts} charts");
}

#[test]
fn the_scaling_benchmark_chart_has_no_overlapping_text() {
    // `scripts/plot_scaling.py` writes its SVG by hand (the matplotlib charts draw text as
    // paths: `scripts/figure_check.py` measures those).
    let font = font();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/bench/scaling.svg");
    let boxes = text_boxes(
        &std::fs::read_to_string(&path).unwrap(),
        &font,
        Raster::AsWritten,
    );
    assert!(boxes.len() > 10, "{} texts", boxes.len());
    let found = overlaps(&boxes);
    assert!(found.is_empty(), "texts overlap: {found:#?}");
}
