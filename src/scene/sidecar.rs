//! The scene sidecar: a RON file describing what glTF cannot (views, image size, albedo
//! overrides, the reference sphere lights, the envmap resolution, render settings).
//!
//! Parsing is strict: unknown fields are errors, and every range check happens *during*
//! deserialisation (through the validated newtypes below), so even "radius must be positive"
//! is reported with the file, line and column. Paths are relative to the sidecar's folder.
//!
//! ```ron
//! Scene(
//!     gltf: "tabletop.glb",
//!     views: ["cam_front", "cam_side"],
//!     image: (width: 128, height: 96),
//!     albedo: { "mug": Constant((0.8, 0.15, 0.1)) },
//!     lights: [Sphere(center: (1.2, 2.5, -0.4), radius: 0.15, radiance: (30.0, 28.0, 26.0))],
//!     envmap: (rings: 9),
//!     render: (spp: 512, max_bounces: 2, seed: 1),
//! )
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest accepted image side, in pixels (a guard against typos like `width: 1280000`).
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Largest accepted samples per pixel.
pub const MAX_SPP: u32 = 1 << 20;
/// Largest accepted bounce count.
pub const MAX_BOUNCES: u32 = 64;
use crate::checked::checked;
/// Largest accepted ring count of the envmap grid.
pub use crate::envmap::MAX_RINGS;
pub use crate::envmap::{Rgb, Rings};

/// The sidecar file, as written by a person.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(rename = "Scene", deny_unknown_fields)]
pub struct Sidecar {
    /// The glTF 2.0 file (`.gltf` or `.glb`), relative to the sidecar.
    pub gltf: PathBuf,
    /// Views to render, in order: glTF camera node names or the names of `cameras`. Empty or
    /// absent: every perspective camera node, then every one of `cameras`.
    #[serde(default)]
    pub views: Vec<String>,
    /// Views whose poses come from elsewhere (SLAM, structure from motion), beside the glTF's
    /// camera nodes; they are picked by `views` like those.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<CameraDesc>,
    /// Image size in pixels of every view. Absent: each view is `--height` (default 480)
    /// pixels high at its glTF camera's aspectRatio (4:3 where it has none), or as large as
    /// the references given for it.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        serialize_with = "inline_some"
    )]
    pub image: Option<ImageSize>,
    /// Albedo overrides by glTF material name (linear RGB or an sRGB-encoded image).
    #[serde(default)]
    pub albedo: BTreeMap<String, AlbedoSource>,
    /// The reference illumination.
    #[serde(default)]
    pub lights: Vec<LightDesc>,
    /// The estimated light model.
    #[serde(default)]
    pub envmap: EnvmapDesc,
    /// Monte Carlo render settings.
    #[serde(default)]
    pub render: RenderDesc,
}

/// Writes `Some(x)` as `x`, as the parser (with RON's implicit `Some`) reads it back.
fn inline_some<S: serde::Serializer, T: Serialize>(
    value: &Option<T>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    match value {
        Some(v) => v.serialize(s),
        None => s.serialize_none(),
    }
}

/// Image size in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ImageSize {
    #[schemars(range(min = 1, max = 16384))]
    pub width: Side,
    #[schemars(range(min = 1, max = 16384))]
    pub height: Side,
}

/// Where a material's albedo comes from.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
pub enum AlbedoSource {
    /// An image (PNG/JPEG, sRGB-encoded like glTF baseColor textures), relative to the sidecar,
    /// looked up with the mesh's first texture coordinates.
    Map(PathBuf),
    /// A constant linear RGB albedo, each channel in [0, 1].
    Constant(Albedo),
}

/// A light of the reference illumination.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub enum LightDesc {
    /// A spherical area light emitting uniform radiance from its surface.
    Sphere {
        /// Centre in world space (glTF frame: +Y up), metres.
        center: Point,
        /// Radius in metres, > 0.
        radius: Positive,
        /// Emitted radiance, linear RGB (W·sr⁻¹·m⁻² per channel), each ≥ 0.
        radiance: Rgb,
    },
    /// A point light: what a sphere light becomes as it shrinks at fixed radiant intensity
    /// (glTF's `KHR_lights_punctual` point light).
    Point {
        /// Position in world space (glTF frame: +Y up), metres.
        center: Point,
        /// Radiant intensity, linear RGB (W·sr⁻¹ per channel), each ≥ 0: a glTF light of
        /// `intensity` candela and colour c has c × intensity / 683.
        intensity: Rgb,
    },
}

/// A pinhole camera given by its pose, glTF's camera model: it looks down its −Z axis with +Y
/// up and +X to the right of the image.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraDesc {
    /// The view's name, which its files take (`<name>.exr`, …).
    pub name: String,
    /// Vertical field of view, radians, in (0, π).
    #[schemars(range(min = 0.0, max = std::f64::consts::PI))]
    pub yfov: Yfov,
    /// Image width / height this camera was made for (glTF's `aspectRatio`): checked against
    /// the references' size; absent: any.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        serialize_with = "inline_some"
    )]
    pub aspect_ratio: Option<Positive>,
    /// Where it is and where it looks.
    pub pose: Pose,
}

/// A camera's pose in the world frame (glTF's: +Y up, metres).
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub enum Pose {
    /// At `eye`, looking at `target`, with `up` (default +Y) upward in the image.
    LookAt {
        eye: Point,
        target: Point,
        #[serde(default = "default_up")]
        up: Point,
    },
    /// The 4×4 camera-to-world matrix, written row by row (`((r00, r01, r02, tx), …,
    /// (0, 0, 0, 1))`), its columns the camera's +X, +Y, +Z axes and position in the world.
    /// Scale and shear are removed (a camera is rigid). A pose in OpenCV's camera axes (+Z
    /// forward, +Y down), as COLMAP and most SLAM systems give it, becomes this one by
    /// negating its second and third columns.
    Matrix([[f32; 4]; 4]),
}

fn default_up() -> Point {
    Point((0.0, 1.0, 0.0))
}

/// The ring environment map's resolution.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EnvmapDesc {
    /// Number of rings of constant polar angle, poles included (1..=1000).
    #[schemars(range(min = 1, max = 1000))]
    pub rings: Rings,
}

impl Default for EnvmapDesc {
    fn default() -> Self {
        EnvmapDesc { rings: Rings(9) }
    }
}

/// Monte Carlo render settings.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RenderDesc {
    /// Samples per pixel (≥ 1).
    #[serde(default = "default_spp")]
    #[schemars(range(min = 1))]
    pub spp: Spp,
    /// Scattering events per path: 1 = direct light only (Mitsuba's max_depth − 1).
    #[serde(default = "default_bounces")]
    #[schemars(range(min = 1, max = 64))]
    pub max_bounces: Bounces,
    /// Seed of every random stream.
    #[serde(default = "default_seed")]
    pub seed: u64,
}

fn default_spp() -> Spp {
    Spp(512)
}
fn default_bounces() -> Bounces {
    Bounces(2)
}
fn default_seed() -> u64 {
    1
}

impl Default for RenderDesc {
    fn default() -> Self {
        RenderDesc {
            spp: default_spp(),
            max_bounces: default_bounces(),
            seed: default_seed(),
        }
    }
}

// ---- Validated values: checked while parsing, so errors carry a position ----

checked!(
    /// An image side in pixels, 1..=16384.
    Side(u32), "u32", |v| (1..=MAX_IMAGE_SIDE).contains(&v),
    "image side must be between 1 and 16384 pixels, got {}"
);
checked!(
    /// Samples per pixel, 1..=2^20.
    Spp(u32), "u32", |v| (1..=MAX_SPP).contains(&v),
    "spp must be between 1 and 1048576, got {}"
);
checked!(
    /// Scattering events per path, 1..=64.
    Bounces(u32), "u32", |v| (1..=MAX_BOUNCES).contains(&v),
    "max_bounces must be between 1 and 64, got {}"
);
checked!(
    /// A finite length > 0.
    Positive(f32), "f32", |v| v.is_finite() && v > 0.0,
    "must be a finite number > 0, got {}"
);
checked!(
    /// A finite point or vector: `(x, y, z)` or `[x, y, z]`.
    Point((f32, f32, f32)), "(f32, f32, f32)", |v| v.0.is_finite() && v.1.is_finite() && v.2.is_finite(),
    "coordinates must be finite, got {:?}"
);
checked!(
    /// A vertical field of view in radians, in (0, π).
    Yfov(f32), "f32", |v| v > 0.0 && v < std::f32::consts::PI,
    "yfov must be in (0, π) radians, got {}"
);
checked!(
    /// Linear RGB albedo, each channel in [0, 1]: `(r, g, b)` or `[r, g, b]`.
    Albedo((f32, f32, f32)), "(f32, f32, f32)", |v| [v.0, v.1, v.2].iter().all(|c| (0.0..=1.0).contains(c)),
    "albedo must be in [0, 1] in every channel, got {:?}"
);

impl Sidecar {
    /// Reads and validates a sidecar file. Errors name the file, line and column.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::memory::read_input_text(path)?;
        Self::parse(&text, path)
    }

    /// Parses sidecar text; `path` is only used in error messages.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        // `image: (width: …, height: …)` for an optional field, without RON's `Some(…)`.
        ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
            .from_str::<Sidecar>(text)
            .map_err(|e| {
                let p = e.span.start;
                let message = match e.code {
                    // ron names neither the field nor the range.
                    ron::error::Error::IntegerOutOfBounds => {
                        "integer out of range for this field (negative, or too large)".to_string()
                    }
                    code => code.to_string(),
                };
                Error::file_at(path, p.line, p.col, message)
            })
    }

    /// The sidecar's folder, against which its relative paths resolve.
    pub fn base_dir(path: &Path) -> PathBuf {
        path.parent().map(Path::to_path_buf).unwrap_or_default()
    }
}

/// The JSON Schema of the sidecar, generated from these types (committed as
/// `schemas/scene.schema.json`; a test keeps it in sync).
pub fn json_schema() -> String {
    let schema = schemars::schema_for!(Sidecar);
    serde_json::to_string_pretty(&schema).expect("a schema always serialises") + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Sidecar> {
        Sidecar::parse(text, Path::new("test.ron"))
    }

    const MINIMAL: &str = r#"Scene(gltf: "a.glb", image: (width: 4, height: 3))"#;

    #[test]
    fn three_numbers_are_read_as_a_tuple_or_a_list_and_only_three() {
        let light = |c: &str| {
            parse(&format!(
                r#"Scene(gltf: "a.glb", lights: [Sphere(center: {c}, radius: 1, radiance: [1, 2, 3])])"#
            ))
        };
        let center = |s: Sidecar| match s.lights[0] {
            LightDesc::Sphere { center, .. } => center.0,
            _ => unreachable!(),
        };
        assert_eq!(center(light("(1, 2.5, 3)").unwrap()), (1.0, 2.5, 3.0));
        assert_eq!(center(light("[1, 2.5, 3]").unwrap()), (1.0, 2.5, 3.0));
        for bad in ["[1, 2]", "(1, 2, 3, 4)", "[1, 2, \"x\"]", "[1, 2, inf]"] {
            assert!(light(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn minimal_gets_defaults() {
        let s = parse(MINIMAL).unwrap();
        assert_eq!(s.render.spp.0, 512);
        assert_eq!(s.render.max_bounces.0, 2);
        assert_eq!(s.envmap.rings.0, 9);
        assert!(s.views.is_empty() && s.lights.is_empty());
    }

    #[test]
    fn full_example_parses() {
        let s = parse(
            r#"Scene(
                gltf: "tabletop.glb",
                views: ["cam_front", "cam_side"],
                image: (width: 128, height: 96),
                albedo: { "table": Map("albedo/table.png"), "mug": Constant((0.8, 0.15, 0.1)) },
                lights: [Sphere(center: (1.2, 2.5, -0.4), radius: 0.15, radiance: (30.0, 28.0, 26.0))],
                envmap: (rings: 9),
                render: (spp: 64, max_bounces: 3, seed: 7),
            )"#,
        )
        .unwrap();
        assert_eq!(s.views.len(), 2);
        assert_eq!(s.albedo.len(), 2);
        assert_eq!(s.render.seed, 7);
        match &s.lights[0] {
            LightDesc::Sphere { radius, .. } => assert_eq!(radius.0, 0.15),
            LightDesc::Point { .. } => panic!("a sphere light was written"),
        }
    }

    fn err(text: &str) -> String {
        parse(text).unwrap_err().to_string()
    }

    #[test]
    fn errors_carry_file_line_column() {
        let e = err("Scene(\n  gltf: \"a.glb\",\n  image: (width: 4, height: 3),\n  colour: 1,\n)");
        assert!(e.starts_with("test.ron:4:"), "{e}");
        assert!(e.contains("colour"), "{e}");
    }

    #[test]
    fn range_errors_carry_position() {
        let e = err(
            "Scene(gltf: \"a.glb\", image: (width: 4, height: 3),\n lights: [Sphere(center: (0,0,0), radius: -1.0, radiance: (1,1,1))])",
        );
        assert!(e.starts_with("test.ron:2:"), "{e}");
        assert!(e.contains("> 0"), "{e}");
    }

    #[test]
    fn rejects_bad_values() {
        for (text, needle) in [
            (
                r#"Scene(gltf: "a.glb", image: (width: 0, height: 3))"#,
                "image side",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 99999))"#,
                "image side",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), render: (spp: 0))"#,
                "spp",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), envmap: (rings: 0))"#,
                "rings",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), envmap: (rings: 5000))"#,
                "rings",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), lights: [Sphere(center: (0,0,0), radius: NaN, radiance: (1,1,1))])"#,
                "> 0",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), lights: [Sphere(center: (0,0,0), radius: 1, radiance: (1,-1,1))])"#,
                "radiance",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), lights: [Sphere(center: (0,inf,0), radius: 1, radiance: (1,1,1))])"#,
                "finite",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3), albedo: {"m": Constant((1.5, 0, 0))})"#,
                "albedo",
            ),
            (
                r#"Scene(gltf: "a.glb", image: (width: 4, height: 3)"#,
                "test.ron:1:",
            ),
        ] {
            let e = err(text);
            assert!(e.contains(needle), "{text}\n-> {e}");
            assert!(e.starts_with("test.ron:"), "{e}");
        }
    }

    #[test]
    fn schema_mentions_every_field() {
        let s = json_schema();
        for f in [
            "gltf",
            "views",
            "image",
            "albedo",
            "lights",
            "envmap",
            "render",
            "spp",
            "max_bounces",
            "radius",
        ] {
            assert!(s.contains(&format!("\"{f}\"")), "{f}");
        }
    }
}
