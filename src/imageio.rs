//! Images in and out: linear RGB(A) f32 OpenEXR for data, sRGB PNG for looking at.
//!
//! Every write goes to a temporary file beside the target and is renamed into place only when
//! complete, so an interrupted or failed run never leaves a partial image behind.

use std::path::{Path, PathBuf};

use exr::prelude::{self as x, ReadChannels, ReadLayers, WritableImage};
use glam::Vec3;

use crate::cleanup;
use crate::error::{Error, Result};

/// A linear RGB image, row-major, row 0 at the top, with an optional alpha channel (lightprobe
/// writes the fraction of camera samples that saw scene geometry there).
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<Vec3>,
    pub alpha: Option<Vec<f32>>,
}

impl Image {
    /// A black image without alpha.
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            rgb: vec![Vec3::ZERO; (width * height) as usize],
            alpha: None,
        }
    }

    /// Mean of each channel over all pixels.
    pub fn mean(&self) -> Vec3 {
        let s = self
            .rgb
            .iter()
            .fold(glam::DVec3::ZERO, |a, p| a + p.as_dvec3());
        (s / self.rgb.len().max(1) as f64).as_vec3()
    }
}

/// Runs `write` on a temporary path beside `path`, then renames it into place. On failure the
/// temporary file is removed and `path` is untouched.
pub fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::file(path, "is not a file path"))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
        && !dir.is_dir()
    {
        // Otherwise the OS says "no such file", which reads like a missing input.
        let what = if dir.exists() {
            "is not a folder"
        } else {
            "does not exist"
        };
        return Err(Error::file(
            path,
            format!("cannot be written: {} {what}", dir.display()),
        ));
    }
    // Renaming over a device, a link or a folder would replace it (as root, even /dev/null).
    if let Ok(meta) = std::fs::symlink_metadata(path)
        && !meta.is_file()
    {
        return Err(Error::file(
            path,
            "exists and is not a regular file (a device, a link or a folder); name a new or regular file",
        ));
    }
    cleanup::remove_stale_of(path);
    let tmp: PathBuf = path.with_file_name(cleanup::temporary_name(&name.to_string_lossy()));
    cleanup::register(&tmp);
    let result =
        write(&tmp).and_then(|()| std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    cleanup::unregister(&tmp);
    result
}

/// Writes bytes atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |tmp| {
        std::fs::write(tmp, bytes).map_err(|e| Error::io(path, e))
    })
}

/// Writes a linear f32 EXR (RGB, plus A when the image has alpha), losslessly compressed.
pub fn write_exr(path: &Path, img: &Image) -> Result<()> {
    write_exr_encoded(
        path,
        img,
        x::LayerAttributes::default(),
        x::Encoding::SMALL_LOSSLESS,
    )
}

/// Writes a lat-long environment map, tagged as one, as a linear f32 EXR. (ZIP: 0.2 MB for a
/// 4096 × 2048 ring envmap; RLE was barely faster and 60× bigger.)
pub fn write_latlong_exr(path: &Path, img: &Image) -> Result<()> {
    let attributes = x::LayerAttributes {
        environment_map: Some(exr::meta::attribute::EnvironmentMap::LatitudeLongitude),
        ..Default::default()
    };
    write_exr_encoded(path, img, attributes, x::Encoding::SMALL_LOSSLESS)
}

/// Writes a linear f32 EXR with the given layer attributes and encoding.
fn write_exr_encoded(
    path: &Path,
    img: &Image,
    attributes: x::LayerAttributes,
    encoding: x::Encoding,
) -> Result<()> {
    let (w, h) = (img.width as usize, img.height as usize);
    if img.rgb.len() != w * h || img.alpha.as_ref().is_some_and(|a| a.len() != w * h) {
        return Err(Error::Invalid(format!(
            "image buffer does not match {w}×{h}"
        )));
    }
    let at = |p: x::Vec2<usize>| p.y() * w + p.x();
    write_atomic(path, |tmp| {
        let result = match &img.alpha {
            Some(alpha) => {
                let channels = x::SpecificChannels::rgba(|p: x::Vec2<usize>| {
                    let c = img.rgb[at(p)];
                    (c.x, c.y, c.z, alpha[at(p)])
                });
                let layer = x::Layer::new((w, h), attributes, encoding, channels);
                x::Image::from_layer(layer).write().to_file(tmp)
            }
            None => {
                let channels = x::SpecificChannels::rgb(|p: x::Vec2<usize>| {
                    let c = img.rgb[at(p)];
                    (c.x, c.y, c.z)
                });
                let layer = x::Layer::new((w, h), attributes, encoding, channels);
                x::Image::from_layer(layer).write().to_file(tmp)
            }
        };
        result.map_err(|e| Error::file(path, format!("cannot write EXR: {e}")))
    })
}

/// The largest image side read or written, pixels.
pub const MAX_SIDE: usize = 16384;

/// Reads the first RGB(A) layer of an EXR as f32. Alpha is kept only if the file has it.
/// The header is checked first (sides, the chunk table against the file's size, the memory
/// the pixels need against [`crate::memory::budget`]), so a few bytes declaring a huge image
/// are refused before anything is allocated for it.
pub fn read_exr(path: &Path) -> Result<Image> {
    if !path.exists() {
        return Err(Error::file(path, "no such file"));
    }
    let bytes = crate::memory::read_input(path)?;
    read_exr_bytes(&bytes, path)
}

/// The image size of an EXR file, from its header alone (the first layer's, as [`read_exr`]
/// reads it).
pub fn exr_size(path: &Path) -> Result<(u32, u32)> {
    if !path.exists() {
        return Err(Error::file(path, "no such file"));
    }
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| Error::file(path, format!("cannot read as an RGB OpenEXR image: {e}")))?;
    let header = meta
        .headers
        .first()
        .ok_or_else(|| Error::file(path, "has no image layer"))?;
    check_windows(header, path)?;
    let size = header.layer_size;
    if size.width() > MAX_SIDE || size.height() > MAX_SIDE || size.area() == 0 {
        return Err(Error::file(
            path,
            format!(
                "declares a {}×{} image; 1×1 to {MAX_SIDE}×{MAX_SIDE} is read",
                size.width(),
                size.height()
            ),
        ));
    }
    Ok((size.width() as u32, size.height() as u32))
}

/// Refuses an EXR whose pixels (data window) are not its whole image (display window): a
/// cropped image read as if whole would put every pixel in the wrong place.
fn check_windows(header: &exr::meta::header::Header, path: &Path) -> Result<()> {
    let (data, display) = (
        header.data_window(),
        header.shared_attributes.display_window,
    );
    if data != display {
        let b = |w: exr::meta::attribute::IntegerBounds| {
            format!(
                "{}×{} at ({}, {})",
                w.size.width(),
                w.size.height(),
                w.position.x(),
                w.position.y()
            )
        };
        return Err(Error::file(
            path,
            format!(
                "holds pixels {} of a {} image (a crop): lightprobe reads whole images; write it uncropped",
                b(data),
                b(display)
            ),
        ));
    }
    Ok(())
}

/// [`read_exr`] on the bytes of an EXR file (`path` names it in errors).
pub fn read_exr_bytes(bytes: &[u8], path: &Path) -> Result<Image> {
    check_exr_header(bytes, path)?;
    struct Buf {
        w: usize,
        rgb: Vec<Vec3>,
        alpha: Option<Vec<f32>>,
    }
    let img = x::read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size, channels: &x::RgbaChannels| Buf {
                w: size.width(),
                rgb: vec![Vec3::ZERO; size.area()],
                alpha: channels.3.as_ref().map(|_| vec![1.0; size.area()]),
            },
            |buf: &mut Buf, p: x::Vec2<usize>, (r, g, b, a): (f32, f32, f32, f32)| {
                let i = p.y() * buf.w + p.x();
                buf.rgb[i] = Vec3::new(r, g, b);
                if let Some(alpha) = &mut buf.alpha {
                    alpha[i] = a;
                }
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| Error::file(path, format!("cannot read as an RGB OpenEXR image: {e}")))?;
    let size = img.layer_data.size;
    let buf = img.layer_data.channel_data.pixels;
    Ok(Image {
        width: size.width() as u32,
        height: size.height() as u32,
        rgb: buf.rgb,
        alpha: buf.alpha,
    })
}

/// How photographs and HDR images become radiance ([`read_photo`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Decoding {
    /// 8- and 16-bit values are linear already (default: sRGB-encoded, as cameras write them).
    pub linear: bool,
    /// A pixel with any channel at or above this (after decoding) is saturated. 8- and 16-bit
    /// images are saturated at their format's maximum whatever this is.
    pub saturation: Option<f32>,
}

/// The image formats [`read_photo`] reads, by file extension, in order of preference.
pub const PHOTO_EXTENSIONS: &[&str] = &["exr", "hdr", "png", "jpg", "jpeg"];

/// Reads an image as linear radiance: OpenEXR (RGB or RGBA, half or float), Radiance `.hdr`,
/// 8- and 16-bit PNG and JPEG (sRGB-decoded unless `decoding.linear`; alpha kept as alpha).
/// Also returns which pixels are usable: not saturated (any channel at the format's maximum,
/// or at `decoding.saturation`).
pub fn read_photo(path: &Path, decoding: Decoding) -> Result<(Image, Vec<bool>)> {
    let ext = extension(path);
    let (img, mut usable) = if ext == "exr" {
        let img = read_exr(path)?;
        let n = img.rgb.len();
        (img, vec![true; n])
    } else {
        read_decoded(path, decoding)?
    };
    if let Some(x) = decoding.saturation {
        for (u, c) in usable.iter_mut().zip(&img.rgb) {
            *u &= c.max_element() < x;
        }
    }
    Ok((img, usable))
}

/// A file's extension in lower case ("" without one): image formats are told by it.
pub fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// Reads a lat-long environment map as linear radiance: OpenEXR or Radiance `.hdr` (the
/// formats that hold radiance above 1), by extension.
pub fn read_latlong(path: &Path) -> Result<Image> {
    let ext = extension(path);
    match ext.as_str() {
        "exr" => read_exr(path),
        "hdr" => Ok(read_decoded(
            path,
            Decoding {
                linear: true,
                saturation: None,
            },
        )?
        .0),
        _ => Err(Error::file(
            path,
            "is not an environment map lightprobe reads: give an OpenEXR (.exr) or Radiance (.hdr) lat-long image",
        )),
    }
}

/// The size of an image [`read_photo`] reads, from its header.
pub fn photo_size(path: &Path) -> Result<(u32, u32)> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        return exr_size(path);
    }
    if !path.exists() {
        return Err(Error::file(path, "no such file"));
    }
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| Error::io(path, e))?
        .into_dimensions()
        .map_err(|e| Error::file(path, format!("cannot read as an image: {e}")))
}

/// A PNG, JPEG or Radiance HDR file through the `image` crate: linear RGB, alpha, and the
/// pixels not at the format's maximum.
fn read_decoded(path: &Path, decoding: Decoding) -> Result<(Image, Vec<bool>)> {
    use image::DynamicImage as D;
    let (w, h) = photo_size(path)?;
    if w as usize > MAX_SIDE || h as usize > MAX_SIDE {
        return Err(Error::file(
            path,
            format!("is {w}×{h}; at most {MAX_SIDE}×{MAX_SIDE} is read"),
        ));
    }
    // The decoded image (up to 16 bytes a pixel) and ours (16 bytes and a flag).
    crate::memory::reserve(w as u64 * h as u64 * 33, || {
        format!("{}: reading its {w}×{h} image", path.display())
    })?;
    let bytes = crate::memory::read_input(path)?;
    let decoded = image::ImageReader::new(std::io::Cursor::new(&bytes))
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?
        .decode()
        .map_err(|e| Error::file(path, format!("cannot decode: {e}")))?;
    let n = (w * h) as usize;
    let has_alpha = decoded.color().has_alpha();
    let mut img = Image::new(w, h);
    let mut alpha = has_alpha.then(|| vec![1.0f32; n]);
    let mut usable = vec![true; n];
    let encoded = |v: f32| {
        if decoding.linear {
            v
        } else {
            srgb_to_linear(v)
        }
    };
    match decoded {
        D::ImageRgb32F(_) | D::ImageRgba32F(_) => {
            // Radiance HDR: linear floating point; its EXPOSURE header says by how much the
            // stored values were scaled (original = stored / exposure).
            let exposure = image::codecs::hdr::HdrDecoder::new(std::io::Cursor::new(&bytes))
                .ok()
                .and_then(|d| d.metadata().exposure)
                .filter(|e| e.is_finite() && *e > 0.0)
                .unwrap_or(1.0);
            let f = decoded.to_rgba32f();
            for (i, p) in f.pixels().enumerate() {
                img.rgb[i] = Vec3::new(p[0], p[1], p[2]) / exposure;
                if let Some(a) = &mut alpha {
                    a[i] = p[3];
                }
            }
        }
        D::ImageLuma16(_) | D::ImageLumaA16(_) | D::ImageRgb16(_) | D::ImageRgba16(_) => {
            let f = decoded.to_rgba16();
            for (i, p) in f.pixels().enumerate() {
                let c = |k: usize| encoded(p[k] as f32 / 65535.0);
                img.rgb[i] = Vec3::new(c(0), c(1), c(2));
                usable[i] = p[0].max(p[1]).max(p[2]) < u16::MAX;
                if let Some(a) = &mut alpha {
                    a[i] = p[3] as f32 / 65535.0;
                }
            }
        }
        other => {
            let lut: Vec<f32> = (0..256).map(|v| encoded(v as f32 / 255.0)).collect();
            let f = other.to_rgba8();
            for (i, p) in f.pixels().enumerate() {
                img.rgb[i] = Vec3::new(lut[p[0] as usize], lut[p[1] as usize], lut[p[2] as usize]);
                usable[i] = p[0].max(p[1]).max(p[2]) < u8::MAX;
                if let Some(a) = &mut alpha {
                    a[i] = p[3] as f32 / 255.0;
                }
            }
        }
    }
    img.alpha = alpha;
    Ok((img, usable))
}

/// The largest radiance value read from an image: beyond any exposure a camera records, and
/// low enough that sums of squares over 10^7 pixels stay finite in f32.
pub const MAX_RADIANCE: f32 = 1e15;

/// Most negative light an image may hold, per channel, as a share of its positive light:
/// small negative values are noise that processing leaves in captured HDRs (a denoiser, a
/// colour matrix; seven of the eight Poly Haven worlds bundled with Blender hold some) and
/// that linear data keeps; more is not radiance.
pub const MAX_NEGATIVE_SHARE: f64 = 1e-3;

/// The error for an image whose negative light, per channel, exceeds [`MAX_NEGATIVE_SHARE`]
/// of its positive light (sums as given: plain, or weighted by solid angle).
pub fn negative_share_error(positive: [f64; 3], negative: [f64; 3]) -> Option<String> {
    let ch = (0..3).find(|&ch| negative[ch] > MAX_NEGATIVE_SHARE * positive[ch])?;
    Some(if positive[ch] > 0.0 {
        format!(
            "its negative pixels hold {:.3}% of the light of its positive ones in channel {ch} (more than the {}% that processing noise leaves): not radiance",
            100.0 * negative[ch] / positive[ch],
            100.0 * MAX_NEGATIVE_SHARE
        )
    } else {
        format!("channel {ch} is negative where it is not zero: not radiance")
    })
}

/// Refuses an image whose negative pixels hold more than [`MAX_NEGATIVE_SHARE`] of its light
/// in a channel, naming the file.
pub fn check_negative_share(path: &Path, img: &Image) -> Result<()> {
    let (mut positive, mut negative) = ([0.0f64; 3], [0.0f64; 3]);
    for c in &img.rgb {
        for ch in 0..3 {
            let v = c[ch] as f64;
            if v > 0.0 {
                positive[ch] += v;
            } else {
                negative[ch] -= v;
            }
        }
    }
    match negative_share_error(positive, negative) {
        Some(why) => Err(Error::file(path, why)),
        None => Ok(()),
    }
}

/// Checks an image's pixels as radiance: colour finite, within ±[`MAX_RADIANCE`] and, unless
/// `negative_ok`, not negative; alpha (coverage) finite and in [0, 1]. The error names the
/// file, the first bad pixel and how many others there are.
pub fn check_radiance(path: &Path, img: &Image, negative_ok: bool) -> Result<()> {
    let colour = |c: &Vec3| -> Option<&'static str> {
        if !c.is_finite() {
            Some("is not finite")
        } else if c.abs().max_element() > MAX_RADIANCE {
            Some("exceeds 1e15 (beyond any radiance; sums over it would overflow)")
        } else if !negative_ok && c.min_element() < 0.0 {
            Some("is negative (radiance cannot be; clamp it to 0 if it is noise)")
        } else {
            None
        }
    };
    // The first bad pixel (of those `bad` yields), described, with the count of the others.
    let report = |mut bad: &mut dyn Iterator<Item = usize>, describe: &dyn Fn(usize) -> String| {
        let Some(i) = bad.next() else {
            return Ok(());
        };
        let more = match (&mut bad).count() {
            0 => String::new(),
            n => format!(" ({n} more pixels are invalid)"),
        };
        let (x, y) = (i as u32 % img.width.max(1), i as u32 / img.width.max(1));
        Err(Error::file(
            path,
            format!("pixel ({x}, {y}) {}{more}", describe(i)),
        ))
    };
    report(
        &mut (0..img.rgb.len()).filter(|&i| colour(&img.rgb[i]).is_some()),
        &|i| {
            format!(
                "{}: {}",
                colour(&img.rgb[i]).unwrap_or_default(),
                img.rgb[i]
            )
        },
    )?;
    if let Some(alpha) = &img.alpha {
        report(
            &mut (0..alpha.len()).filter(|&i| !(0.0..=1.0).contains(&alpha[i])),
            &|i| format!("has alpha {}, outside [0, 1]", alpha[i]),
        )?;
    }
    Ok(())
}

/// Checks every layer an EXR declares before any pixel is decoded.
fn check_exr_header(bytes: &[u8], path: &Path) -> Result<()> {
    let len = bytes.len() as u64;
    let meta = exr::meta::MetaData::read_from_buffered(bytes, false)
        .map_err(|e| Error::file(path, format!("cannot read as an RGB OpenEXR image: {e}")))?;
    for header in meta.headers.iter() {
        check_windows(header, path)?;
        let size = header.layer_size;
        if size.width() > MAX_SIDE || size.height() > MAX_SIDE {
            return Err(Error::file(
                path,
                format!(
                    "declares a {}×{} image; at most {MAX_SIDE}×{MAX_SIDE} is read",
                    size.width(),
                    size.height()
                ),
            ));
        }
        // Each chunk has an 8-byte entry in the offset table, so a file shorter than its
        // table cannot hold the image it declares.
        let table = header.chunk_count as u64 * 8;
        if table > len {
            return Err(Error::file(
                path,
                format!(
                    "truncated: its header declares {} chunks of pixels, more than a {len}-byte file holds",
                    header.chunk_count
                ),
            ));
        }
        // Read as f32 RGB and alpha, plus the decoder's copy of the file's chunks.
        let need = size.area() as u64 * 16 + len;
        crate::memory::reserve(need, || {
            format!(
                "{}: reading its {}×{} image",
                path.display(),
                size.width(),
                size.height()
            )
        })?;
    }
    Ok(())
}

/// The sRGB transfer function's inverse (encoded [0, 1] → linear), the inverse of
/// [`linear_to_srgb`].
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// The sRGB transfer function (linear [0, 1] → encoded).
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// An exposure that maps the 99th percentile of luminance to 1 (for previews).
pub fn auto_exposure(img: &Image) -> f32 {
    let mut lum: Vec<f32> = img
        .rgb
        .iter()
        .map(|c| luminance(*c))
        .filter(|l| l.is_finite() && *l > 0.0)
        .collect();
    if lum.is_empty() {
        return 1.0;
    }
    let k = ((lum.len() - 1) as f32 * 0.99) as usize;
    let (_, p99, _) = lum.select_nth_unstable_by(k, f32::total_cmp);
    1.0 / *p99
}

/// Rec. 709 luminance weights of linear R, G, B.
pub const LUMINANCE: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// Rec. 709 luminance of linear RGB.
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    LUMINANCE[0] * c.x + LUMINANCE[1] * c.y + LUMINANCE[2] * c.z
}

/// Writes `img × exposure`, clamped and sRGB-encoded, as an 8-bit PNG.
pub fn write_png(path: &Path, img: &Image, exposure: f32) -> Result<()> {
    let bytes: Vec<u8> = img
        .rgb
        .iter()
        .flat_map(|c| (*c * exposure).to_array())
        .map(|v| {
            (linear_to_srgb(if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            }) * 255.0
                + 0.5) as u8
        })
        .collect();
    write_rgb8_png(path, img.width, img.height, bytes)
}

/// Writes 8-bit RGB bytes (already encoded) as a PNG.
pub fn write_rgb8_png(path: &Path, width: u32, height: u32, bytes: Vec<u8>) -> Result<()> {
    let buf = image::RgbImage::from_raw(width, height, bytes)
        .ok_or_else(|| Error::Invalid(format!("PNG buffer does not match {width}×{height}")))?;
    write_atomic(path, |tmp| {
        buf.save_with_format(tmp, image::ImageFormat::Png)
            .map_err(|e| Error::file(path, format!("cannot write PNG: {e}")))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cropped_exr_is_refused_and_hdr_exposure_is_undone() {
        use exr::prelude::*;
        let dir = std::env::temp_dir().join(format!("lp-crop-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // 4×3 pixels at (1, 1) of a 6×5 image.
        let layer = Layer::new(
            (4, 3),
            LayerAttributes {
                layer_position: exr::math::Vec2(1, 1),
                ..LayerAttributes::default()
            },
            Encoding::FAST_LOSSLESS,
            SpecificChannels::rgb(|_: exr::math::Vec2<usize>| (0.5f32, 0.5f32, 0.5f32)),
        );
        let image = exr::image::Image::new(
            ImageAttributes::new(IntegerBounds::new((0, 0), (6, 5))),
            layer,
        );
        let p = dir.join("crop.exr");
        image.write().to_file(&p).unwrap();
        let e = read_exr(&p).unwrap_err().to_string();
        assert!(e.contains("4×3 at (1, 1) of a 6×5 at (0, 0) image"), "{e}");
        assert!(exr_size(&p).is_err());
        // A Radiance file whose header says its values were scaled by 2 reads at half.
        let mut hdr = Vec::new();
        let pixels = [image::Rgb([2.0f32, 4.0, 8.0]); 2];
        image::codecs::hdr::HdrEncoder::new(&mut hdr)
            .encode(&pixels, 2, 1)
            .unwrap();
        let text = String::from_utf8_lossy(&hdr).into_owned();
        let at = text.find("FORMAT=").unwrap();
        let mut with = hdr[..at].to_vec();
        with.extend(b"EXPOSURE=2.0\n");
        with.extend(&hdr[at..]);
        let p = dir.join("x.hdr");
        std::fs::write(&p, with).unwrap();
        let (img, _) = read_photo(&p, Decoding::default()).unwrap();
        assert_eq!(img.rgb[0], Vec3::new(1.0, 2.0, 4.0));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn sample(alpha: bool) -> Image {
        let (w, h) = (7u32, 5u32);
        let rgb = (0..w * h)
            .map(|i| Vec3::new(i as f32 * 0.5, -(i as f32), 1e-7 * i as f32))
            .collect();
        Image {
            width: w,
            height: h,
            rgb,
            alpha: alpha.then(|| (0..w * h).map(|i| i as f32 / 35.0).collect()),
        }
    }

    #[test]
    fn exr_round_trip_is_exact_with_and_without_alpha() {
        let dir = tempfile::tempdir().unwrap();
        for alpha in [false, true] {
            let img = sample(alpha);
            let p = dir.path().join(format!("a{alpha}.exr"));
            write_exr(&p, &img).unwrap();
            assert_eq!(read_exr(&p).unwrap(), img);
        }
        // Only the final files remain: no temporaries.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.exr");
        let r = write_atomic(&p, |tmp| {
            std::fs::write(tmp, b"partial").unwrap();
            Err(Error::Invalid("boom".into()))
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn reading_garbage_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.exr");
        std::fs::write(&p, b"not an exr at all").unwrap();
        let e = read_exr(&p).unwrap_err().to_string();
        assert!(e.contains("bad.exr"), "{e}");
    }

    #[test]
    fn small_negatives_pass_as_noise_and_a_negative_image_is_refused() {
        let img = |low: f32| Image {
            width: 100,
            height: 1,
            rgb: (0..100)
                .map(|i| Vec3::splat(if i == 0 { low } else { 1.0 }))
                .collect(),
            alpha: None,
        };
        let p = Path::new("ref.exr");
        assert!(check_negative_share(p, &img(-0.05)).is_ok());
        let e = check_negative_share(p, &img(-1.0)).unwrap_err().to_string();
        assert!(e.contains("ref.exr") && e.contains("1.010%"), "{e}");
        let black = Image {
            rgb: vec![Vec3::new(0.0, -0.5, 0.0); 100],
            ..img(0.0)
        };
        let e = check_negative_share(p, &black).unwrap_err().to_string();
        assert!(e.contains("channel 1 is negative"), "{e}");
    }

    #[test]
    fn srgb_round_trip() {
        for i in 0..=100 {
            let c = i as f32 / 100.0;
            assert!((srgb_to_linear(linear_to_srgb(c)) - c).abs() < 1e-5);
        }
    }
}
