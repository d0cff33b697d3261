//! `render.json`: what `render-reference` rendered, typed.

use std::path::PathBuf;

use serde::Serialize;

use super::RenderSettings;

/// What a render of reference images produced and how long it took.
#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    pub lightprobe_version: String,
    /// The scene file, as given.
    pub scene: PathBuf,
    pub triangles: usize,
    /// The image size every view shares (null when views differ: see each view's).
    pub image: Option<ImageSize>,
    /// The sphere and point lights rendered.
    pub lights: Vec<LightReport>,
    /// The ring envmap rendered, if any.
    pub envmap: Option<EnvmapReport>,
    pub settings: RenderSettings,
    pub threads: usize,
    /// The BVH traversal kernels: `avx2` (x86-64-v3, detected at run time) or `portable`
    /// (any CPU, or `LIGHTPROBE_ISA=portable`). The images are the same either way.
    pub kernels: crate::accel::Isa,
    pub timings: RenderTimings,
    /// Camera samples per second over all views (samples of pixels whose rays meet nothing
    /// count too: they cost nearly nothing).
    pub samples_per_second: f64,
    pub views: Vec<ViewRender>,
}

/// Pixels.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ImageSize {
    pub width: u32,
    pub height: u32,
}

/// A sphere light: centre (world, metres), radius (metres), linear RGB radiance; radius 0 is
/// a point light, whose `radiance` is its radiant intensity (W·sr⁻¹).
#[derive(Debug, Clone, Serialize)]
pub struct LightReport {
    pub center: [f32; 3],
    pub radius: f32,
    pub radiance: [f32; 3],
}

/// A ring envmap's file and resolution.
#[derive(Debug, Clone, Serialize)]
pub struct EnvmapReport {
    pub file: PathBuf,
    pub rings: u32,
}

/// Seconds per phase.
#[derive(Debug, Clone, Serialize)]
pub struct RenderTimings {
    pub load_seconds: f64,
    pub bvh_seconds: f64,
    pub render_seconds: f64,
}

/// One view's files and figures.
#[derive(Debug, Clone, Serialize)]
pub struct ViewRender {
    pub view: String,
    /// Image size, pixels.
    pub width: u32,
    pub height: u32,
    pub exr: PathBuf,
    pub png: PathBuf,
    /// With `--twin`: `<view>_b.exr`, the same render with other random numbers.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub twin: Option<PathBuf>,
    /// Geometry buffers written, by name (`depth`, `normal`, `albedo`).
    pub aov: std::collections::BTreeMap<String, PathBuf>,
    /// Mean linear RGB over all pixels.
    pub mean_rgb: [f32; 3],
    /// Mean fraction of camera samples that saw geometry.
    pub coverage: f64,
    pub seconds: f64,
    pub samples_per_second: f64,
}
