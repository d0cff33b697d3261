//! `compare`: photometric error of an image against a reference.

use std::path::PathBuf;

use serde_json::json;

use super::outln;
use lightprobe::output::figure;
use lightprobe::{imageio, metrics};

#[derive(clap::Args)]
pub struct Args {
    /// The image to judge (EXR).
    image: PathBuf,
    /// The reference (EXR); its alpha, if any, masks out background pixels.
    reference: PathBuf,
    /// Write a heat map (PNG) of the signed error per pixel, (image − reference) over the
    /// reference's mean radiance, blue below zero and red above, with a colour bar in percent.
    #[arg(long)]
    heatmap: Option<PathBuf>,
    /// The heat map's colour scale runs from −SCALE to +SCALE, a fraction of the reference's
    /// mean radiance (default: the 99th percentile of the error's magnitude).
    #[arg(long)]
    scale: Option<f32>,
    /// Compare every pixel, ignoring the reference's alpha mask.
    #[arg(long)]
    no_mask: bool,
    /// Print the metrics as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let image = imageio::read_exr(&a.image)?;
    let reference = imageio::read_exr(&a.reference)?;
    if (image.width, image.height) != (reference.width, reference.height) {
        anyhow::bail!(
            "{}: image is {}×{} but the reference {} is {}×{}",
            a.image.display(),
            image.width,
            image.height,
            a.reference.display(),
            reference.width,
            reference.height
        );
    }
    // Negative values are allowed: another renderer's image may ring below zero, and the
    // metrics are still defined.
    imageio::check_radiance(&a.image, &image, true)?;
    imageio::check_radiance(&a.reference, &reference, true)?;
    if let Some(s) = a.scale
        && !(s.is_finite() && s > 0.0)
    {
        anyhow::bail!("--scale must be a finite number > 0");
    }
    let mask = if a.no_mask {
        vec![true; reference.rgb.len()]
    } else {
        metrics::mask_of(&reference)
    };
    if !mask.contains(&true) {
        anyhow::bail!(
            "{}: its alpha (coverage) is zero everywhere, so no pixel is compared; pass --no-mask to compare every pixel",
            a.reference.display()
        );
    }
    if reference
        .rgb
        .iter()
        .zip(&mask)
        .all(|(c, &m)| !m || *c == glam::Vec3::ZERO)
    {
        anyhow::bail!(
            "{}: is black (zero) on every compared pixel, so the relative errors are undefined",
            a.reference.display()
        );
    }
    let m = metrics::compare(&image, &reference, &mask)?;
    let scale = match &a.heatmap {
        Some(p) => {
            let err = figure::signed_error(&image, &reference, &mask);
            let scale = a.scale.unwrap_or_else(|| figure::shared_scale([&err]));
            let title = format!(
                "{} − {}",
                a.image.file_name().unwrap_or_default().to_string_lossy(),
                a.reference
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
            );
            figure::write_error_map(p, &title, (image.width, image.height), &err, scale)?;
            Some(scale)
        }
        None => None,
    };
    if a.json {
        let mut v = serde_json::to_value(m)?;
        v["image"] = json!(a.image);
        v["reference"] = json!(a.reference);
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            v["heatmap"] = json!({
                "path": p,
                "scale": s,
                "units": "fraction of the reference's mean radiance (signed, −scale to +scale)",
            });
        }
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        outln!("relMAE  {:.5}  ({:.2}%)", m.rel_mae, 100.0 * m.rel_mae)?;
        outln!("MAE     {:.6}", m.mae)?;
        outln!("RMSE    {:.6}", m.rmse)?;
        outln!("relMSE  {:.6}", m.rel_mse)?;
        outln!("PSNR    {:.2} dB", m.psnr)?;
        outln!(
            "pixels  {} compared, {} masked out (background)",
            m.pixels,
            m.masked_out
        )?;
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            outln!(
                "heatmap {} (signed error, ±{:.2}% of the reference's mean)",
                p.display(),
                100.0 * s
            )?;
        }
    }
    Ok(())
}
