//! `index.html`: an estimate's results page, self-contained (no script, no network; its images
//! are files of the output folder, linked relatively). Every number it shows is read from the
//! report's JSON by path and carries that path and the value (`data-json`, `data-value`,
//! `data-format`), so a test can check the page against report.json.

use std::fmt::Write as _;
use std::path::Path;

use serde_json::Value;

use super::figure::{self, Mark, MarkKind};
use crate::error::Result;
use crate::estimate::job::Estimate;
use crate::estimate::pipeline::SeenViews;
use crate::imageio;
use crate::scene::Scene;

/// How a number is shown. The same rules are in `scripts/check_page.py`, which checks them.
#[derive(Debug, Clone, Copy)]
pub enum Format {
    /// A fraction as percent, 2 decimals: `9.36%`.
    Percent,
    /// Seconds, 2 decimals: `4.21 s`.
    Seconds,
    /// A ratio, 2 decimals: `×1.18`.
    Ratio,
    /// Degrees, 2 decimals: `13.00°`.
    Degrees,
    /// Metres, 3 decimals: `0.011 m`.
    Metres,
    /// Bytes as MiB, no decimals: `179 MiB`.
    MiB,
    /// 3 significant digits in scientific notation: `4.34e-4`.
    Scientific,
    /// 4 significant digits: `5.611`, `0.01235`, `1235`.
    Significant,
    /// An integer: `2637`.
    Integer,
}

impl Format {
    fn name(self) -> &'static str {
        match self {
            Format::Percent => "percent",
            Format::Seconds => "seconds",
            Format::Ratio => "ratio",
            Format::Degrees => "degrees",
            Format::Metres => "metres",
            Format::MiB => "mib",
            Format::Scientific => "scientific",
            Format::Significant => "significant",
            Format::Integer => "integer",
        }
    }

    fn show(self, v: f64) -> String {
        match self {
            Format::Percent => format!("{:.2}%", 100.0 * v),
            Format::Seconds => format!("{v:.2} s"),
            Format::Ratio => format!("×{v:.2}"),
            Format::Degrees => format!("{v:.2}°"),
            Format::Metres => format!("{v:.3} m"),
            Format::MiB => format!("{:.0} MiB", v / (1024.0 * 1024.0)),
            Format::Scientific => format!("{v:.2e}"),
            Format::Significant => {
                let digits = if v == 0.0 || !v.is_finite() {
                    0
                } else {
                    (3 - v.abs().log10().floor() as i32).max(0) as usize
                };
                format!("{v:.digits$}")
            }
            Format::Integer => format!("{v:.0}"),
        }
    }
}

/// The value at `path` (keys and indices joined by dots) in `json`.
fn at<'a>(json: &'a Value, path: &str) -> Option<&'a Value> {
    path.split('.')
        .try_fold(json, |v, key| match key.parse::<usize>() {
            Ok(i) => v.get(i),
            Err(_) => v.get(key),
        })
}

/// A table cell showing the number at `path` of the report, tagged for the page's test; "—"
/// when the report has none there.
fn cell(report: &Value, path: &str, format: Format) -> String {
    tagged("td class=\"num\"", "td", report, path, format)
}

/// The number at `path` inline, tagged as [`cell`]'s.
fn span(report: &Value, path: &str, format: Format) -> String {
    tagged("span", "span", report, path, format)
}

/// The number at `path` in an element opened by `open` and closed by `close`, carrying its
/// path, its value as report.json writes it, and its format.
fn tagged(open: &str, close: &str, report: &Value, path: &str, format: Format) -> String {
    let value = at(report, path).unwrap_or(&Value::Null);
    let shown = value
        .as_f64()
        .map_or_else(|| "—".to_string(), |v| format.show(v));
    format!(
        "<{open} data-json=\"{path}\" data-value=\"{}\" data-format=\"{}\">{}</{close}>",
        escape(&value.to_string()),
        format.name(),
        escape(&shown)
    )
}

/// A relative path (of `/`-separated names) as a URL: every byte but unreserved ones and
/// `/` percent-encoded, so that a view named `cam#1` or `50%` links its own file.
pub fn url(path: &str) -> String {
    let mut out = String::new();
    for b in path.bytes() {
        match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' | b'/' => {
                out.push(b as char)
            }
            _ => out.push_str(&format!("%{b:02X}")),
        }
    }
    out
}

/// Text made safe inside HTML elements and quoted attributes.
pub fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// What the page calls the scene's own lights: the truth when the references were rendered
/// from them, else only what the scene file says.
fn truth_word(rendered_references: bool) -> &'static str {
    if rendered_references {
        "true light"
    } else {
        "scene light"
    }
}

/// The page's style: one light theme; previews at 288 pixels wide, error maps at their own
/// size up to 560 (their colour bar's labels stay legible), 1400 pixels in all.
const STYLE: &str = "body{font-family:'DejaVu Sans',sans-serif;margin:24px auto;max-width:1400px;\
color:#222;padding:0 16px}h1{font-size:24px}h2{font-size:19px;margin-top:32px;border-bottom:1px \
solid #ccc}table{border-collapse:collapse;margin:8px 0}td,th{padding:3px 10px;border-bottom:1px \
solid #eee;text-align:left;vertical-align:top}td.num{text-align:right;font-variant-numeric:\
tabular-nums}.views img{width:288px;image-rendering:pixelated}.views img.err{width:auto;max-width:560px}.wide{max-width:100%}\
.note{color:#555;font-size:14px}.warn{background:#fff3cd;border:1px solid #e0c060;padding:8px}\
.chosen{font-weight:bold}figure{margin:8px 0}.swatch{display:inline-block;width:28px;height:14px;\
border:1px solid #999}";

/// Writes `dir/index.html` and the pictures only it shows (`dir/figures/`): reference
/// previews, and the envmap as a lat-long picture with the lights marked. `report` is the
/// report's JSON as written to report.json; the scene, when given, marks its own lights.
pub fn write(
    dir: &Path,
    report: &Value,
    estimate: &Estimate,
    seen: &SeenViews,
    scene: Option<&Scene>,
    rendered_references: bool,
) -> Result<()> {
    let figures = dir.join("figures");
    super::create_dir(&figures)?;
    let mut h = String::new();
    let scene_name = report["scene"].as_str().unwrap_or("");
    let model = report["model"].as_str().unwrap_or("envmap");
    let _ = writeln!(
        h,
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>lightprobe: {}</title><style>{STYLE}</style></head><body>\n\
         <h1>Lighting estimate of <code>{}</code></h1>\n<p class=\"note\">lightprobe {} · \
         model <b>{}</b> · {}-ring envmap ({} cells), {} solver, {} transport samples per \
         pixel · references {}</p>",
        escape(scene_name),
        escape(scene_name),
        escape(report["lightprobe_version"].as_str().unwrap_or("")),
        escape(model),
        span(report, "rings", Format::Integer),
        span(report, "cells", Format::Integer),
        escape(report["solver"].as_str().unwrap_or("")),
        span(report, "transport_spp", Format::Integer),
        if rendered_references {
            "rendered from the scene's lights"
        } else {
            "given"
        }
    );
    if report["fit_test"]["misfit"].as_bool() == Some(true) {
        let causes: Vec<String> = report["fit_test"]["causes"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|c| c.as_str())
            .map(escape)
            .collect();
        let _ = writeln!(
            h,
            "<p class=\"warn\">The model <b>{}</b> does not explain the images: its residual \
             is far above what their noise explains. Check, most likely first: {}</p>",
            escape(model),
            causes.join("; ")
        );
    }
    key_figures(&mut h, report);
    views(&mut h, dir, report, estimate, seen)?;
    // The rows of `spheres.lights` (every fitted light) that are the model's lights: those
    // the recoveries' `estimated` counts.
    let kept: Vec<usize> = estimate.spheres.as_ref().map_or_else(Vec::new, |so| {
        (0..so.fit.fitted.len())
            .filter(|&k| so.fit.fitted[k].kept())
            .collect()
    });
    envmap_section(
        &mut h,
        dir,
        report,
        estimate,
        &kept,
        scene,
        rendered_references,
    )?;
    spheres_section(&mut h, report, &kept, truth_word(rendered_references));
    selection_sections(&mut h, report);
    exposure_section(&mut h, report);
    albedo_section(&mut h, report);
    texels_section(&mut h, dir, report, estimate, scene)?;
    h.push_str(
        "<h2>Files</h2><ul><li><a href=\"report.json\">report.json</a>: every figure \
         (its JSON Schema: <code>lightprobe schema --report</code>)</li><li><a href=\"envmap.ron\">envmap.ron</a>, \
         <a href=\"envmap.exr\">envmap.exr</a>: the envmap (lat-long EXR in Mitsuba's \
         convention)</li><li><a href=\"mitsuba/scene.xml\">mitsuba/scene.xml</a>, \
         <code>blender.py</code>, <a href=\"lights.usda\">lights.usda</a>: the estimate in \
         other tools</li></ul>\n</body></html>\n",
    );
    imageio::write_bytes(&dir.join("index.html"), h.as_bytes())
}

fn key_figures(h: &mut String, r: &Value) {
    h.push_str("<h2>Key figures</h2><table>\n");
    let rows: [(&str, &str, Format); 13] = [
        (
            "relMAE of the envmap's re-render",
            "rel_mae",
            Format::Percent,
        ),
        (
            "relMAE of the sphere model's re-render",
            "spheres.rel_mae",
            Format::Percent,
        ),
        (
            "noise floor (relMAE the images' noise alone gives)",
            "noise_floor_rel_mae",
            Format::Percent,
        ),
        (
            "representation limit (best envmap of this resolution, --oracle)",
            "representation_limit_rel_mae",
            Format::Percent,
        ),
        (
            "fit test: residual over what the noise explains",
            "fit_test.residual_over_noise",
            Format::Ratio,
        ),
        ("fit test: p-value", "fit_test.p_value", Format::Scientific),
        (
            "whole command (all but writing this page and report.json)",
            "timings.total_seconds",
            Format::Seconds,
        ),
        (
            "envmap fit (transport and solve)",
            "timings.fit_seconds",
            Format::Seconds,
        ),
        (
            "sphere models' fits",
            "timings.sphere_fit_seconds",
            Format::Seconds,
        ),
        (
            "envmap's re-render and the noise floor",
            "timings.rerender_seconds",
            Format::Seconds,
        ),
        (
            "sphere model's re-render",
            "spheres.rerender_seconds",
            Format::Seconds,
        ),
        (
            "peak memory (of the estimate, before its files)",
            "memory.peak_bytes",
            Format::MiB,
        ),
        (
            "envmap transport's memory (at most)",
            "memory.transport_bytes",
            Format::MiB,
        ),
    ];
    for (what, path, format) in rows {
        // Rows of what this run did not do are left out: null figures, and phases that took
        // no time to speak of (a re-render skipped by --fit-only still times its set-up).
        let idle = matches!(format, Format::Seconds)
            && at(r, path)
                .and_then(Value::as_f64)
                .is_some_and(|t| t < 0.005);
        if at(r, path).is_some_and(|v| !v.is_null()) && !idle {
            let _ = writeln!(h, "<tr><th>{what}</th>{}</tr>", cell(r, path, format));
        }
    }
    h.push_str("</table>\n");
}

fn views(
    h: &mut String,
    dir: &Path,
    r: &Value,
    estimate: &Estimate,
    seen: &SeenViews,
) -> Result<()> {
    if estimate.envmap.renders.is_empty() {
        h.push_str("<h2>Views</h2><p>No re-render (<code>--fit-only</code>).</p>\n");
        return Ok(());
    }
    for (cam, reference) in seen.views.iter().zip(&seen.references) {
        imageio::write_png(
            &dir.join("figures")
                .join(format!("{}.reference.png", cam.name)),
            reference,
            imageio::auto_exposure(reference),
        )?;
    }
    let mut models = vec![("envmap", "estimate", "views", "estimate.rel_mae")];
    if estimate.spheres.is_some() {
        models.insert(
            0,
            (
                r["spheres"]["model"].as_str().unwrap_or("spheres"),
                "spheres",
                "spheres.views",
                "rel_mae",
            ),
        );
    }
    h.push_str("<h2>Views</h2>\n");
    for (name, folder, list, key) in models {
        let _ = writeln!(
            h,
            "<h3>{}</h3><table class=\"views\"><tr><th>view</th><th>relMAE</th>\
             <th>reference</th><th>estimate (re-rendered)</th><th>signed error</th></tr>",
            escape(name)
        );
        for (i, cam) in seen.views.iter().enumerate() {
            let v = escape(&cam.name);
            let src = |file: String| escape(&url(&file));
            let _ = writeln!(
                h,
                "<tr><td>{v}</td>{}<td><img src=\"{}\" alt=\"reference {v}\"></td>\
                 <td><img src=\"{}\" alt=\"estimate {v}\"></td><td><img class=\"err\" \
                 src=\"{}\" alt=\"error {v}\"></td></tr>",
                cell(r, &format!("{list}.{i}.{key}"), Format::Percent),
                src(format!("figures/{}.reference.png", cam.name)),
                src(format!("{folder}/{}.png", cam.name)),
                src(format!("{folder}/{}.error.png", cam.name)),
            );
        }
        h.push_str("</table>\n");
    }
    h.push_str(
        "<p class=\"note\">Previews: linear radiance × k, clipped to 1, sRGB curve; k puts the \
         reference's 99th-percentile luminance at 1, and the estimate beside it uses the same \
         k. Error: (estimate − reference) per pixel, the channels' mean, over the reference's \
         mean radiance in its view; blue is too dark, red too bright; all views of a model \
         share one colour scale (its bar); grey pixels are left out (background, saturated, \
         or masked).</p>\n",
    );
    Ok(())
}

fn envmap_section(
    h: &mut String,
    dir: &Path,
    r: &Value,
    estimate: &Estimate,
    kept: &[usize],
    scene: Option<&Scene>,
    rendered_references: bool,
) -> Result<()> {
    let vec3 = |v: &Value| -> Option<glam::Vec3> {
        let a = v.as_array()?;
        Some(glam::Vec3::new(
            a.first()?.as_f64()? as f32,
            a.get(1)?.as_f64()? as f32,
            a.get(2)?.as_f64()? as f32,
        ))
    };
    let word = truth_word(rendered_references);
    let mut marks = Vec::new();
    let center = scene.map(|s| s.center());
    if let (Some(scene), Some(c)) = (scene, center) {
        for (k, l) in scene.lights.iter().enumerate() {
            marks.push(Mark {
                direction: (l.center - c).normalize_or_zero(),
                kind: MarkKind::True,
                label: format!("{word} {k}"),
            });
        }
    }
    let recovery = r["light_recovery"].as_array().cloned().unwrap_or_default();
    for (k, cl) in r["clusters"].as_array().into_iter().flatten().enumerate() {
        let Some(d) = vec3(&cl["direction"]) else {
            continue;
        };
        let matched = recovery
            .iter()
            .find(|m| vec3(&m["estimated_direction"]).is_some_and(|e| e == d));
        let label = match matched {
            Some(m) => format!(
                "cluster {k}: {:.1}° off {word} {}, power ×{:.2}",
                m["angle_error_degrees"].as_f64().unwrap_or(f64::NAN),
                m["true_light"],
                m["power_ratio"].as_f64().unwrap_or(f64::NAN)
            ),
            None => format!("cluster {k}"),
        };
        marks.push(Mark {
            direction: d,
            kind: MarkKind::Estimated,
            label,
        });
    }
    // Sphere lights by their row in the report's (and the page's) table; the model's lights
    // are the kept ones, which the recovery's `estimated` counts.
    if let (Some(so), Some(c)) = (&estimate.spheres, center) {
        let recovered = r["spheres"]["recovery"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        for (j, &k) in kept.iter().enumerate() {
            let rec = recovered
                .iter()
                .find(|m| m["estimated"].as_u64() == Some(j as u64));
            let off = rec.and_then(|m| m["centre_error_m"].as_f64());
            marks.push(Mark {
                direction: (so.fit.fitted[k].light.center - c).normalize_or_zero(),
                kind: MarkKind::Estimated,
                label: match (off, rec) {
                    (Some(e), Some(m)) => {
                        format!("sphere {k}: centre {e:.3} m off {word} {}", m["true_light"])
                    }
                    _ => format!("sphere {k}"),
                },
            });
        }
    }
    let env = &estimate.envmap.fit.envmap;
    figure::write_envmap_figure(
        &dir.join("figures").join("envmap.png"),
        &format!(
            "The {}-ring envmap estimate (○ {word}s, × recovered)",
            env.grid.rings(),
        ),
        env,
        &marks,
    )?;
    h.push_str(
        "<h2>Envmap</h2><figure><img class=\"wide\" src=\"figures/envmap.png\" alt=\"the \
         envmap in lat-long\"><figcaption class=\"note\">Directions from the scene's centre, \
         glTF frame (+Y up). Radiance tone-mapped: exposure putting the brightest cell's \
         luminance at 3, then x/(1+x) per channel and the sRGB curve. Lines: the ring \
         grid's cells. Sphere lights are marked by their direction from the scene's \
         centre.</figcaption></figure>\n",
    );
    let clusters = r["clusters"].as_array().map_or(0, Vec::len);
    if clusters > 0 {
        h.push_str(
            "<table><tr><th>cluster</th><th>power (luminance × sr)</th>\
             <th>its σ (relative)</th><th>σ of its direction</th>\
             <th colspan=\"4\">colour: share of its power in R, G, B</th></tr>\n",
        );
        for k in 0..clusters {
            let share: Vec<f64> = (0..3)
                .map(|c| r["clusters"][k]["chromaticity"][c].as_f64().unwrap_or(0.0))
                .collect();
            // The swatch: the colour at its brightest channel's full value.
            let top = share.iter().copied().fold(0.0, f64::max).max(1e-9);
            let srgb = |v: f64| (255.0 * imageio::linear_to_srgb((v / top) as f32)).round() as u8;
            let swatch = format!(
                "<td><span class=\"swatch\" style=\"background:rgb({},{},{})\"></span></td>",
                srgb(share[0]),
                srgb(share[1]),
                srgb(share[2])
            );
            let shares: String = (0..3)
                .map(|c| {
                    cell(
                        r,
                        &format!("clusters.{k}.chromaticity.{c}"),
                        Format::Percent,
                    )
                })
                .collect();
            let _ = writeln!(
                h,
                "<tr><td>{k}</td>{}{}{}{swatch}{shares}</tr>",
                cell(r, &format!("clusters.{k}.power"), Format::Significant),
                cell(
                    r,
                    &format!("clusters.{k}.power_sigma_relative"),
                    Format::Percent
                ),
                cell(
                    r,
                    &format!("clusters.{k}.direction_sigma_degrees"),
                    Format::Degrees
                ),
            );
        }
        h.push_str("</table>\n");
        if r["clusters"][0]["direction_sigma_degrees"].is_null() {
            h.push_str(
                "<p class=\"note\">No σ: the clusters' intervals are measured only with the \
                 NNLS solver, --colour per-channel and at most 17 rings, and when every \
                 jackknife replicate converged.</p>\n",
            );
        }
    }
    if !recovery.is_empty() {
        let _ = writeln!(
            h,
            "<table><tr><th>{word}</th><th>envmap's direction off by</th>\
             <th>power ratio</th></tr>",
        );
        for k in 0..recovery.len() {
            let _ = writeln!(
                h,
                "<tr>{}{}{}</tr>",
                cell(
                    r,
                    &format!("light_recovery.{k}.true_light"),
                    Format::Integer
                ),
                cell(
                    r,
                    &format!("light_recovery.{k}.angle_error_degrees"),
                    Format::Degrees
                ),
                cell(r, &format!("light_recovery.{k}.power_ratio"), Format::Ratio),
            );
        }
        h.push_str("</table>\n");
    }
    Ok(())
}

/// `--exposure per-view`: each view's fitted exposure relative to their geometric mean.
fn exposure_section(h: &mut String, r: &Value) {
    let Some(views) = r["exposure"]["relative"].as_array() else {
        return;
    };
    let _ = writeln!(
        h,
        "<h2>Exposures (--exposure per-view)</h2><p class=\"note\">Each view's exposure \
         relative to their geometric mean (the lighting is in that mean's units), from {} \
         alternating fits; {}.</p><table><tr><th>view</th><th>relative exposure</th></tr>",
        span(r, "exposure.fits", Format::Integer),
        if r["exposure"]["converged"].as_bool() == Some(true) {
            "converged"
        } else {
            "<b>not converged</b>"
        }
    );
    for (i, v) in views.iter().enumerate() {
        let _ = writeln!(
            h,
            "<tr><td>{}</td>{}</tr>",
            escape(v["view"].as_str().unwrap_or("")),
            cell(r, &format!("exposure.relative.{i}.exposure"), Format::Ratio),
        );
    }
    h.push_str("</table>\n");
}

/// `--fit-albedo`: each material's given and fitted albedo, with swatches.
fn albedo_section(h: &mut String, r: &Value) {
    let Some(materials) = r["albedo"]["materials"].as_array() else {
        return;
    };
    let _ = writeln!(
        h,
        "<h2>Albedo (--fit-albedo)</h2><p class=\"note\">{}; {} {}, {}. A material is fitted \
         from the pixels that see it alone; observability says how well the images tell its \
         albedo from the light (0: not at all, as when only it sees that light; 1: as well as \
         beside a material lit exactly alike; below 0.01 it is kept as given). Where the fit \
         test says the model does not explain the images, the albedo has taken up part of the \
         misfit.</p><table><tr><th>material</th><th>status</th><th>pixels</th>\
         <th>observability</th><th>given (linear RGB)</th><th>fitted</th><th></th></tr>",
        escape(r["albedo"]["gauge"].as_str().unwrap_or("")),
        span(r, "albedo.fits", Format::Integer),
        if r["albedo"]["method"].as_str() == Some("joint") {
            "joint passes"
        } else {
            "alternating fits"
        },
        if r["albedo"]["converged"].as_bool() == Some(true) {
            "converged"
        } else {
            "<b>not converged</b>"
        }
    );
    let swatch = |v: &Value| -> String {
        let c = |i: usize| {
            let x = v[i].as_f64().unwrap_or(0.0) as f32;
            (crate::imageio::linear_to_srgb(x.clamp(0.0, 1.0)) * 255.0).round() as u8
        };
        format!(
            "<span style=\"display:inline-block;width:1.2em;height:1.2em;\
             background:rgb({},{},{});border:1px solid #888\"></span>",
            c(0),
            c(1),
            c(2)
        )
    };
    for (i, m) in materials.iter().enumerate() {
        let rgb = |what: &str| {
            (0..3)
                .map(|c| {
                    span(
                        r,
                        &format!("albedo.materials.{i}.{what}.{c}"),
                        Format::Significant,
                    )
                })
                .collect::<Vec<_>>()
                .join(" ")
        };
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td>{}{}<td>{}</td><td>{}</td><td>{} {}</td></tr>",
            escape(m["name"].as_str().unwrap_or("")),
            escape(m["status"].as_str().unwrap_or("")),
            cell(r, &format!("albedo.materials.{i}.pixels"), Format::Integer),
            cell(
                r,
                &format!("albedo.materials.{i}.observability"),
                Format::Significant
            ),
            rgb("given"),
            rgb("fitted"),
            swatch(&m["given"]),
            swatch(&m["fitted"]),
        );
    }
    h.push_str("</table>\n");
}

/// Longest side of a texture's pictures on the page.
const TEXTURE_PICTURE: u32 = 256;

/// `texture × factor` reduced by box means to at most [`TEXTURE_PICTURE`] a side.
fn texture_picture(texture: &crate::scene::Texture, factor: glam::Vec3) -> imageio::Image {
    let block = texture
        .width
        .max(texture.height)
        .div_ceil(TEXTURE_PICTURE)
        .max(1);
    let (w, h) = (
        texture.width.div_ceil(block),
        texture.height.div_ceil(block),
    );
    let mut rgb = vec![glam::Vec3::ZERO; (w * h) as usize];
    let mut count = vec![0u32; (w * h) as usize];
    for (i, t) in texture.texels.iter().enumerate() {
        let (x, y) = (i as u32 % texture.width, i as u32 / texture.width);
        let k = ((y / block) * w + x / block) as usize;
        rgb[k] += (*t * factor).clamp(glam::Vec3::ZERO, glam::Vec3::ONE);
        count[k] += 1;
    }
    for (c, n) in rgb.iter_mut().zip(&count) {
        *c /= (*n).max(1) as f32;
    }
    imageio::Image {
        width: w,
        height: h,
        rgb,
        alpha: None,
    }
}

/// `--fit-albedo texels`: each corrected texture as given and as fitted, the change between
/// them, and its correction's figures.
fn texels_section(
    h: &mut String,
    dir: &Path,
    r: &Value,
    estimate: &Estimate,
    scene: Option<&Scene>,
) -> Result<()> {
    let Some(fits) = r["albedo"]["texels"].as_array().filter(|f| !f.is_empty()) else {
        return Ok(());
    };
    let (Some(scene), Some(fitted)) = (scene, estimate.materials.as_ref()) else {
        return Ok(());
    };
    let _ = writeln!(
        h,
        "<h2>Texels (--fit-albedo texels)</h2><p class=\"note\">{} round(s) of a correction \
         per texture (a coarse grid of multipliers, smooth, keeping the sum of the material's \
         re-rendered pixels) and a fit of the materials' albedo and the lighting at it. The \
         table's ratios are of the texels alone (fitted over given, where pixels see them); the \
         change map is of the albedo as rendered, fitted over given less 1 (mean of the \
         channels), the material's multiplier included: shading baked into the given texture \
         shows as a brightened patch. σ: one standard deviation of the correction, relative, \
         over the cells pixels see (from the residuals: noise, and misfit as if noise); \
         none on grids of more than 4096 cells or where the system could not be solved.</p><table><tr><th>material</th><th>grid</th>\
         <th>cells seen</th><th>pixels</th><th>least texel ratio</th><th>largest</th>\
         <th>last change</th><th>texels clamped</th><th>σ median</th><th>σ largest</th></tr>",
        span(r, "albedo.texel_rounds", Format::Integer),
    );
    for (i, fit) in fits.iter().enumerate() {
        let p = format!("albedo.texels.{i}");
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}×{}</td>{}{}{}{}{}{}{}{}</tr>",
            escape(fit["material"].as_str().unwrap_or("")),
            span(r, &format!("{p}.grid.0"), Format::Integer),
            span(r, &format!("{p}.grid.1"), Format::Integer),
            cell(r, &format!("{p}.cells_seen"), Format::Integer),
            cell(r, &format!("{p}.pixels"), Format::Integer),
            cell(r, &format!("{p}.range.0"), Format::Ratio),
            cell(r, &format!("{p}.range.1"), Format::Ratio),
            cell(r, &format!("{p}.last_change"), Format::Percent),
            cell(r, &format!("{p}.clamped_texels"), Format::Integer),
            cell(r, &format!("{p}.sigma.0"), Format::Percent),
            cell(r, &format!("{p}.sigma.1"), Format::Percent),
        );
    }
    h.push_str("</table>\n");
    for (i, fit) in fits.iter().enumerate() {
        let name = fit["material"].as_str().unwrap_or("");
        let Some(m) = fit["index"]
            .as_u64()
            .map(|m| m as usize)
            .filter(|&m| m < scene.materials.len().min(fitted.len()))
        else {
            continue;
        };
        use crate::scene::Albedo;
        let (
            Albedo::Texture {
                texture: given,
                factor: given_factor,
            },
            Albedo::Texture { texture, factor },
        ) = (&scene.materials[m].albedo, &fitted[m].albedo)
        else {
            continue;
        };
        let (before, after) = (
            texture_picture(given, *given_factor),
            texture_picture(texture, *factor),
        );
        let stem = format!("texels_{i}");
        imageio::write_png(&dir.join(format!("figures/{stem}_given.png")), &before, 1.0)?;
        imageio::write_png(&dir.join(format!("figures/{stem}_fitted.png")), &after, 1.0)?;
        let change: Vec<f32> = before
            .rgb
            .iter()
            .zip(&after.rgb)
            .map(|(b, a)| {
                let (b, a) = (b.element_sum(), a.element_sum());
                if b > 0.0 { a / b - 1.0 } else { f32::NAN }
            })
            .collect();
        let scale = figure::shared_scale([&change]);
        figure::write_signed_map(
            &dir.join(format!("figures/{stem}_change.png")),
            &format!("{name}: fitted / given − 1"),
            (before.width, before.height),
            &change,
            scale,
            "change of the albedo",
        )?;
        let _ = writeln!(
            h,
            "<figure><img src=\"figures/{stem}_given.png\" alt=\"{0} as given\" width=\"256\"> \
             <img src=\"figures/{stem}_fitted.png\" alt=\"{0} as fitted\" width=\"256\"> \
             <img src=\"figures/{stem}_change.png\" alt=\"change of {0}\"><figcaption>{0}: \
             as given, as fitted (<code>{1}</code> beside the glTF exports), and the change\
             </figcaption></figure>",
            escape(name),
            escape(fit["file"].as_str().unwrap_or("")),
        );
    }
    Ok(())
}

fn spheres_section(h: &mut String, r: &Value, kept: &[usize], word: &str) {
    let lights = r["spheres"]["lights"].as_array().map_or(0, Vec::len);
    if lights == 0 {
        return;
    }
    let _ = writeln!(
        h,
        "<h2>Sphere lights ({})</h2><table><tr><th>light</th><th>status</th>\
         <th>radius</th><th>σ of its direction</th><th>σ of its distance</th>\
         <th>σ of its power (relative)</th></tr>",
        escape(r["spheres"]["model"].as_str().unwrap_or(""))
    );
    for k in 0..lights {
        let p = format!("spheres.lights.{k}");
        let _ = writeln!(
            h,
            "<tr><td>{k}</td><td>{}</td>{}{}{}{}</tr>",
            escape(r["spheres"]["lights"][k]["status"].as_str().unwrap_or("")),
            cell(r, &format!("{p}.light.radius"), Format::Metres),
            cell(r, &format!("{p}.direction_sigma_degrees"), Format::Degrees),
            cell(r, &format!("{p}.distance_sigma_m"), Format::Metres),
            cell(r, &format!("{p}.power_sigma_relative"), Format::Percent),
        );
    }
    h.push_str("</table>\n");
    let recovered = r["spheres"]["recovery"].as_array().map_or(0, Vec::len);
    if recovered > 0 {
        let _ = writeln!(
            h,
            "<table><tr><th>{word}</th><th>sphere light</th><th>centre off by</th>\
             <th>its distance</th><th>its radius</th><th>power ratio</th></tr>",
        );
        for k in 0..recovered {
            let p = format!("spheres.recovery.{k}");
            // The table's light: `estimated` counts the kept lights only.
            let estimated = r["spheres"]["recovery"][k]["estimated"]
                .as_u64()
                .and_then(|j| kept.get(j as usize).copied())
                .map_or("—".to_string(), |row| row.to_string());
            let _ = writeln!(
                h,
                "<tr>{}<td>{estimated}</td>{}{}{}{}</tr>",
                cell(r, &format!("{p}.true_light"), Format::Integer),
                cell(r, &format!("{p}.centre_error_m"), Format::Metres),
                cell(r, &format!("{p}.true_distance_m"), Format::Metres),
                cell(r, &format!("{p}.true_radius"), Format::Metres),
                cell(r, &format!("{p}.power_ratio"), Format::Ratio),
            );
        }
        h.push_str("</table>\n");
    }
}

fn selection_sections(h: &mut String, r: &Value) {
    for (title, key, name) in [
        ("Model selection", "model_selection", "model"),
        (
            "Resolution selection (--rings auto)",
            "rings_selection",
            "rings",
        ),
    ] {
        let Some(candidates) = r[key]["candidates"].as_array() else {
            continue;
        };
        let chosen = &r[key][if key == "model_selection" {
            "chosen"
        } else {
            "rings"
        }];
        let _ = writeln!(
            h,
            "<h2>{title}</h2><p class=\"note\">Each candidate fitted without a held-out quarter \
             of the pixels and scored on it; the simplest within one standard error of the best \
             is chosen (bold). A sphere model's fit time includes the smaller models' it grew \
             from.</p><table><tr><th>{name}</th><th>held-out relMAE</th>\
             <th>excess over the best</th><th>its standard error</th><th>fit time</th></tr>"
        );
        for (i, c) in candidates.iter().enumerate() {
            let p = format!("{key}.candidates.{i}");
            // A model's name, or a ring count (a number of the report: tagged).
            let label = match &c[name] {
                Value::String(s) => format!("<td>{}</td>", escape(s)),
                _ => cell(r, &format!("{p}.{name}"), Format::Integer),
            };
            let _ = writeln!(
                h,
                "<tr{}>{}{}{}{}{}</tr>",
                if &c[name] == chosen {
                    " class=\"chosen\""
                } else {
                    ""
                },
                label,
                cell(r, &format!("{p}.validation_rel_mae"), Format::Percent),
                cell(r, &format!("{p}.excess_over_best"), Format::Percent),
                cell(r, &format!("{p}.standard_error"), Format::Percent),
                cell(r, &format!("{p}.seconds"), Format::Seconds),
            );
        }
        h.push_str("</table>\n");
        if let Some(m) = r[key]["at_noise_floor"].as_str() {
            let _ = writeln!(
                h,
                "<p class=\"note\">{} re-renders at {} the noise floor on the \
                 held-out pixels (within {:.0}%) and is chosen over every smaller model: no \
                 larger model was fitted, since none could change the choice.</p>",
                escape(m),
                span(r, &format!("{key}.over_noise_floor"), Format::Ratio),
                100.0 * crate::estimate::select::MODEL_TOLERANCE
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_show_the_value_at_their_path() {
        let r: Value = serde_json::json!({"a": [{"b": 0.0936}], "n": null});
        let c = cell(&r, "a.0.b", Format::Percent);
        assert_eq!(
            c,
            "<td class=\"num\" data-json=\"a.0.b\" data-value=\"0.0936\" \
             data-format=\"percent\">9.36%</td>"
        );
        assert!(cell(&r, "n", Format::Seconds).contains(">—<"));
        assert!(cell(&r, "missing.0", Format::Seconds).contains("data-value=\"null\""));
        assert_eq!(escape("<a&\"b\">"), "&lt;a&amp;&quot;b&quot;&gt;");
        // A view's name goes into a link whole: '#', '?', '%' and spaces are its own.
        assert_eq!(url("figures/cam #1?%.png"), "figures/cam%20%231%3F%25.png");
        assert_eq!(url("estimate/vue_é.png"), "estimate/vue_%C3%A9.png");
        assert_eq!(Format::Significant.show(5.61146), "5.611");
        assert_eq!(Format::Significant.show(0.0123456), "0.01235");
        assert_eq!(Format::Significant.show(12345.6), "12346");
    }
}
