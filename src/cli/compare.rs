//! `compare`: photometric error of an image against a reference.

use std::path::PathBuf;

use serde_json::json;

use lightprobe::{imageio, metrics};

#[derive(clap::Args)]
pub struct Args {
    /// The image to judge (EXR).
    image: PathBuf,
    /// The reference (EXR); its alpha, if any, masks out background pixels.
    reference: PathBuf,
    /// Write a per-pixel error heat map (PNG) with a colour bar.
    #[arg(long)]
    heatmap: Option<PathBuf>,
    /// Top of the heat map's colour scale (default: 99th percentile of the error).
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
    for (img, path) in [(&image, &a.image), (&reference, &a.reference)] {
        if let Some(i) = img.rgb.iter().position(|c| !c.is_finite()) {
            anyhow::bail!(
                "{}: pixel ({}, {}) is not finite",
                path.display(),
                i as u32 % img.width,
                i as u32 / img.width
            );
        }
    }
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
    let m = metrics::compare(&image, &reference, &mask)?;
    let scale = match &a.heatmap {
        Some(p) => Some(metrics::write_heatmap(
            p, &image, &reference, &mask, a.scale,
        )?),
        None => None,
    };
    if a.json {
        let mut v = serde_json::to_value(m)?;
        v["image"] = json!(a.image);
        v["reference"] = json!(a.reference);
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            v["heatmap"] = json!({ "path": p, "scale": s });
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("relMAE  {:.5}  ({:.2}%)", m.rel_mae, 100.0 * m.rel_mae);
        println!("MAE     {:.6}", m.mae);
        println!("RMSE    {:.6}", m.rmse);
        println!("relMSE  {:.6}", m.rel_mse);
        println!("PSNR    {:.2} dB", m.psnr);
        println!(
            "pixels  {} compared, {} masked out (background)",
            m.pixels, m.masked_out
        );
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            println!("heatmap {} (scale 0..{s:.4})", p.display());
        }
    }
    Ok(())
}
