//! The scene: world-space triangles with Lambertian materials, the cameras to render from, and
//! the reference sphere and point lights, loaded from a glTF 2.0 file by itself (its cameras,
//! materials and `KHR_lights_punctual` lights) or through a RON sidecar that names one and
//! overrides or adds to it.
//!
//! Conventions (glTF's): right-handed, +Y up, metres, linear RGB. Every triangle is stored in
//! world space (the node hierarchy is multiplied out at load time). Surfaces are two-sided.
//!
//! ```no_run
//! let scene = lightprobe::scene::Scene::load(std::path::Path::new("scenes/tabletop/tabletop.ron"))?;
//! println!("{} triangles, {} views", scene.mesh.triangle_count(), scene.cameras.len());
//! # Ok::<(), lightprobe::Error>(())
//! ```

mod camera;
pub mod export;
mod gltf;
pub mod sidecar;

use std::path::{Path, PathBuf};

use glam::{Vec2, Vec3};

pub use camera::Camera;
pub use sidecar::Sidecar;

use crate::error::{Error, Result};

/// A texture of linear RGB albedo, looked up bilinearly with repeat wrapping. Texture
/// coordinates follow glTF: (0, 0) is the image's top-left corner, v grows down.
#[derive(Debug, Clone)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    /// Row-major texels, row 0 at the top, linear RGB.
    pub texels: Vec<Vec3>,
}

impl Texture {
    /// Decodes 8-bit sRGB-encoded texels (`channels` = 1..=4 interleaved; alpha ignored).
    pub fn from_srgb8(width: u32, height: u32, channels: usize, bytes: &[u8]) -> Texture {
        let lut: Vec<f32> = (0..256).map(|i| srgb_to_linear(i as f32 / 255.0)).collect();
        let texels = bytes
            .chunks_exact(channels)
            .map(|c| match channels {
                1 | 2 => Vec3::splat(lut[c[0] as usize]),
                _ => Vec3::new(lut[c[0] as usize], lut[c[1] as usize], lut[c[2] as usize]),
            })
            .collect();
        Texture {
            width,
            height,
            texels,
        }
    }

    /// Bilinear lookup at glTF texture coordinates, repeat wrapping.
    #[inline(always)]
    pub fn sample(&self, uv: Vec2) -> Vec3 {
        let (w, h) = (self.width as i64, self.height as i64);
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        if !(x.is_finite() && y.is_finite()) {
            return self.texels[0];
        }
        let (x0, y0) = (crate::math::floor(x), crate::math::floor(y));
        let (fx, fy) = (x - x0, y - y0);
        // Wrap once per axis (an integer division each); the next texel wraps by comparison.
        let (i0, j0) = ((x0 as i64).rem_euclid(w), (y0 as i64).rem_euclid(h));
        let next = |k: i64, n: i64| if k + 1 == n { 0 } else { k + 1 };
        let (i1, j1) = (next(i0, w), next(j0, h));
        let at = |i: i64, j: i64| self.texels[(j * w + i) as usize];
        let top = at(i0, j0) * (1.0 - fx) + at(i1, j0) * fx;
        let bottom = at(i0, j1) * (1.0 - fx) + at(i1, j1) * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// The mean texel (what a uniform lookup averages to), summed in f64: an f32 sum of a
    /// 2048² map is off by 0.3%.
    pub fn mean(&self) -> Vec3 {
        let sum = self
            .texels
            .iter()
            .fold(glam::DVec3::ZERO, |s, t| s + t.as_dvec3());
        (sum / self.texels.len().max(1) as f64).as_vec3()
    }
}

pub use crate::imageio::srgb_to_linear;

/// Where a material's albedo comes from.
#[derive(Debug, Clone)]
pub enum Albedo {
    /// Constant linear RGB.
    Constant(Vec3),
    /// A texture times a factor (glTF baseColorTexture × baseColorFactor).
    Texture {
        texture: std::sync::Arc<Texture>,
        factor: Vec3,
    },
}

/// A two-sided Lambertian material.
#[derive(Debug, Clone)]
pub struct Material {
    /// The glTF material name (what sidecar overrides refer to).
    pub name: String,
    pub albedo: Albedo,
}

impl Material {
    /// The albedo at texture coordinates `uv`, clamped to [0, 1].
    #[inline(always)]
    pub fn albedo_at(&self, uv: Vec2) -> Vec3 {
        match &self.albedo {
            Albedo::Constant(c) => *c,
            Albedo::Texture { texture, factor } => {
                (texture.sample(uv) * *factor).clamp(Vec3::ZERO, Vec3::ONE)
            }
        }
    }

    /// The material with its albedo multiplied per channel by `k` (≥ 0): a constant clamped to
    /// [0, 1], a texture's factor multiplied (lookups are clamped).
    pub fn scaled(&self, k: Vec3) -> Material {
        Material {
            name: self.name.clone(),
            albedo: match &self.albedo {
                Albedo::Constant(c) => Albedo::Constant((*c * k).clamp(Vec3::ZERO, Vec3::ONE)),
                Albedo::Texture { texture, factor } => Albedo::Texture {
                    texture: texture.clone(),
                    factor: (*factor * k).max(Vec3::ZERO),
                },
            },
        }
    }

    /// The mean albedo as rendered: the constant, or the mean over texels of texel × factor
    /// clamped to 1 (vertex colours not included).
    pub fn mean_albedo(&self) -> Vec3 {
        match &self.albedo {
            Albedo::Constant(c) => *c,
            Albedo::Texture { texture, factor } => {
                let sum = texture.texels.iter().fold(glam::DVec3::ZERO, |s, t| {
                    s + (*t * *factor).min(Vec3::ONE).as_dvec3()
                });
                (sum / texture.texels.len().max(1) as f64).as_vec3()
            }
        }
    }
}

/// A spherical area light emitting uniform radiance from its whole surface, or with radius 0
/// a point light (glTF's `KHR_lights_punctual` point): the limit of a sphere shrinking at
/// fixed radiant intensity, which no ray can hit and which casts hard shadows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SphereLight {
    /// Centre, world space (metres).
    pub center: Vec3,
    /// Radius in metres (≥ 0; 0 is a point light).
    pub radius: f32,
    /// Linear RGB: the emitted radiance (W·sr⁻¹·m⁻² per channel) of a sphere; of a point light
    /// (radius 0), its radiant intensity (W·sr⁻¹ per channel).
    pub radiance: Vec3,
}

impl SphereLight {
    /// A point light of radiant intensity `intensity` (W·sr⁻¹, linear RGB) at `center`.
    pub fn point(center: Vec3, intensity: Vec3) -> SphereLight {
        SphereLight {
            center,
            radius: 0.0,
            radiance: intensity,
        }
    }

    /// Whether this is a point light (radius 0).
    #[inline]
    pub fn is_point(&self) -> bool {
        self.radius == 0.0
    }

    /// Radiant intensity seen from far away, W·sr⁻¹ per channel: π r² L for a sphere, the
    /// intensity itself for a point light.
    pub fn intensity(&self) -> Vec3 {
        if self.is_point() {
            self.radiance
        } else {
            std::f32::consts::PI * self.radius * self.radius * self.radiance
        }
    }

    /// What turns [`SphereLight::radiance`] into irradiance on a surface facing the light at
    /// `p`: the solid angle the sphere subtends there, 2π(1 − cos α), sr; for a point light
    /// 1/d², m⁻². Zero from inside the sphere.
    pub fn solid_angle_from(&self, p: Vec3) -> f32 {
        let d2 = (self.center - p).length_squared();
        if self.is_point() {
            return 1.0 / d2;
        }
        let sin2 = self.radius * self.radius / d2;
        if sin2 >= 1.0 {
            return 0.0;
        }
        std::f32::consts::TAU * sin2 / (1.0 + (1.0 - sin2).sqrt())
    }
}

/// World-space triangles with per-vertex normals and texture coordinates.
///
/// Triangles of meshes without normals are stored unshared with their face normal on each
/// vertex, so they shade flat, as glTF requires.
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Unit shading normals, world space (zero where a file gave a degenerate one).
    pub normals: Vec<Vec3>,
    pub uvs: Vec<Vec2>,
    /// Per-vertex colour, linear RGB in [0, 1], multiplying the material's albedo (glTF
    /// `COLOR_0`, what scanned meshes carry); 1 where the file has none.
    pub colors: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    /// Material index of each triangle.
    pub triangle_material: Vec<u32>,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The three corners of triangle `t`.
    #[inline]
    pub fn corners(&self, t: usize) -> [Vec3; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Appends triangles (world space). Without `normals` they shade flat; without `uvs`
    /// texture coordinates are (0, 0). `indices` must be in range (checked by the caller).
    pub fn push(
        &mut self,
        positions: &[Vec3],
        normals: Option<&[Vec3]>,
        uvs: Option<&[Vec2]>,
        indices: &[u32],
        material: u32,
    ) {
        self.push_colored(positions, normals, uvs, None, indices, material)
    }

    /// [`Mesh::push`] with per-vertex colours (1 without).
    pub fn push_colored(
        &mut self,
        positions: &[Vec3],
        normals: Option<&[Vec3]>,
        uvs: Option<&[Vec2]>,
        colors: Option<&[Vec3]>,
        indices: &[u32],
        material: u32,
    ) {
        debug_assert!(indices.len().is_multiple_of(3));
        let uv = |i: u32| uvs.map_or(Vec2::ZERO, |u| u[i as usize]);
        let color = |i: u32| colors.map_or(Vec3::ONE, |c| c[i as usize]);
        match normals {
            Some(normals) => {
                let base = self.positions.len() as u32;
                self.positions.extend_from_slice(positions);
                self.normals
                    .extend(normals.iter().map(|n| n.normalize_or_zero()));
                self.uvs.extend((0..positions.len() as u32).map(uv));
                self.colors.extend((0..positions.len() as u32).map(color));
                for t in indices.chunks_exact(3) {
                    self.triangles.push([base + t[0], base + t[1], base + t[2]]);
                    self.triangle_material.push(material);
                }
            }
            None => {
                for t in indices.chunks_exact(3) {
                    let p = [
                        positions[t[0] as usize],
                        positions[t[1] as usize],
                        positions[t[2] as usize],
                    ];
                    let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
                    let base = self.positions.len() as u32;
                    for (k, &i) in t.iter().enumerate() {
                        self.positions.push(p[k]);
                        self.normals.push(n);
                        self.uvs.push(uv(i));
                        self.colors.push(color(i));
                    }
                    self.triangles.push([base, base + 1, base + 2]);
                    self.triangle_material.push(material);
                }
            }
        }
    }

    /// Sets the colours of `material`'s vertices to 1 (each vertex belongs to the triangles
    /// of one [`Mesh::push`], so to one material).
    pub fn clear_colors(&mut self, material: u32) {
        for (t, &m) in self.triangles.iter().zip(&self.triangle_material) {
            if m == material {
                for &v in t {
                    self.colors[v as usize] = Vec3::ONE;
                }
            }
        }
    }

    /// Whether any vertex has a colour other than 1.
    pub fn has_colors(&self) -> bool {
        self.colors.iter().any(|&c| c != Vec3::ONE)
    }

    /// Appends another mesh's triangles with material `material` (its normals and texture
    /// coordinates are kept).
    pub fn append(&mut self, other: &Mesh, material: u32) {
        let indices: Vec<u32> = other.triangles.iter().flatten().copied().collect();
        self.push_colored(
            &other.positions,
            Some(&other.normals),
            Some(&other.uvs),
            Some(&other.colors),
            &indices,
            material,
        );
    }

    /// Axis-aligned bounds (min, max), world space.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in 0..self.triangles.len() {
            for p in self.corners(t) {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        (lo, hi)
    }

    /// Total surface area, m².
    pub fn surface_area(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| {
                let [a, b, c] = self.corners(t);
                0.5 * (b - a).as_dvec3().cross((c - a).as_dvec3()).length()
            })
            .sum()
    }
}

/// Render settings from the sidecar (defaults for a glTF alone). Image sizes are the views'
/// ([`Camera::width`], [`Camera::height`]).
#[derive(Debug, Clone, Copy)]
pub struct SceneSettings {
    pub spp: u32,
    pub max_bounces: u32,
    pub seed: u64,
    pub rings: u32,
}

/// Height of a view's image when neither the sidecar, `--height` nor references give one.
pub const DEFAULT_HEIGHT: u32 = 480;

/// How large each view's image is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViewSize {
    /// Every view this size (the sidecar's `image`).
    Fixed { width: u32, height: u32 },
    /// This height, and the width of each camera's glTF aspectRatio (4:3 where it has none).
    Height(u32),
}

impl ViewSize {
    /// The image size of a camera of glTF aspect ratio `aspect`; an error says what is too
    /// large.
    pub fn for_aspect(self, aspect: Option<f32>) -> std::result::Result<(u32, u32), String> {
        match self {
            ViewSize::Fixed { width, height } => Ok((width, height)),
            ViewSize::Height(h) => {
                let a = aspect.unwrap_or(4.0 / 3.0) as f64;
                let w = (h as f64 * a).round().max(1.0);
                if w > sidecar::MAX_IMAGE_SIDE as f64 {
                    return Err(format!(
                        "aspect ratio {a} at a height of {h} pixels is {w} pixels wide, above the {} allowed",
                        sidecar::MAX_IMAGE_SIDE
                    ));
                }
                Ok((w as u32, h))
            }
        }
    }
}

/// Something in the scene's files that lightprobe's model leaves out: said once on stderr,
/// and listed in report.json.
#[derive(Debug, Clone, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct Ignored {
    /// What has it: `material "name"` or `light "name"`.
    pub what: String,
    /// What is left out of it, each with its value.
    pub properties: Vec<String>,
}

/// How to load a scene.
#[derive(Debug, Clone, Default)]
pub struct LoadOptions {
    /// Height of every view's image in pixels, overriding the sidecar's image (its aspect
    /// kept) or the default, [`DEFAULT_HEIGHT`].
    pub height: Option<u32>,
    /// The views by camera node name, in order, overriding the sidecar's `views` (empty: the
    /// sidecar's, or every camera).
    pub views: Vec<String>,
}

/// Why views could not be picked by name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PickError {
    /// A name two cameras have: which one is meant is not said.
    Ambiguous(String),
    /// A name given twice: its renders would overwrite each other's files and count twice in
    /// a fit.
    Twice(String),
    /// A name no camera has.
    Missing(String),
}

/// The cameras named, in the order named.
pub fn pick_views(
    cameras: &[Camera],
    names: &[String],
) -> std::result::Result<Vec<Camera>, PickError> {
    let mut picked = Vec::new();
    for (i, v) in names.iter().enumerate() {
        if names[..i].contains(v) {
            return Err(PickError::Twice(v.clone()));
        }
        let mut named = cameras.iter().filter(|c| &c.name == v);
        let c = named.next().ok_or_else(|| PickError::Missing(v.clone()))?;
        if named.next().is_some() {
            return Err(PickError::Ambiguous(v.clone()));
        }
        picked.push(c.clone());
    }
    Ok(picked)
}

/// The cameras `names` names (`listed` says where the names come from; errors name the file
/// `sidecar`), or every camera when it names none (then no two may share a name).
fn pick_or_all(
    cameras: Vec<Camera>,
    names: &[String],
    listed: &str,
    gltf_path: &Path,
    sidecar: &Path,
) -> Result<Vec<Camera>> {
    if !names.is_empty() {
        let picked = pick_views(&cameras, names).map_err(|e| {
            let message = match e {
                PickError::Twice(v) => format!("view {v:?} is listed twice in {listed}"),
                PickError::Ambiguous(v) => format!(
                    "view {v:?} names two camera nodes of {}; rename one",
                    gltf_path.display()
                ),
                PickError::Missing(v) => {
                    let names: Vec<_> = cameras.iter().map(|c| c.name.as_str()).collect();
                    let also = if sidecar == gltf_path {
                        ""
                    } else {
                        " nor one of the sidecar's `cameras`"
                    };
                    format!(
                        "view {v:?} is not a perspective camera node of {}{also} (there are {names:?})",
                        gltf_path.display()
                    )
                }
            };
            Error::file(sidecar, message)
        })?;
        check_view_names(&picked, gltf_path)?;
        return Ok(picked);
    }
    if cameras.is_empty() {
        return Err(Error::file(
            gltf_path,
            "has no perspective camera node to render from (add one)",
        ));
    }
    for (i, c) in cameras.iter().enumerate() {
        if cameras[..i].iter().any(|d| d.name == c.name) {
            // Their files and random streams would collide.
            return Err(Error::file(
                gltf_path,
                format!("has two camera nodes named {:?}; rename one", c.name),
            ));
        }
    }
    check_view_names(&cameras, gltf_path)?;
    Ok(cameras)
}

/// A camera the sidecar gives by its pose, sized by `size` at its aspect ratio. Errors name
/// the sidecar and the camera: a pose with no direction (eye at the target, up along the line
/// of sight), a matrix that is not a rigid placement (non-finite, degenerate, a reflection,
/// a last row other than (0, 0, 0, 1)).
fn posed_camera(desc: &sidecar::CameraDesc, size: ViewSize, sidecar_path: &Path) -> Result<Camera> {
    let bad = |why: String| Error::file(sidecar_path, format!("camera {:?}: {why}", desc.name));
    let aspect = desc.aspect_ratio.map(|a| a.0);
    let (width, height) = size.for_aspect(aspect).map_err(bad)?;
    let yfov = desc.yfov.0;
    let v = |p: &sidecar::Point| Vec3::new(p.0.0, p.0.1, p.0.2);
    let mut camera = match &desc.pose {
        sidecar::Pose::LookAt { eye, target, up } => {
            Camera::looking_at(&desc.name, v(eye), v(target), v(up), yfov, width, height)
                .ok_or_else(|| {
                    bad("its eye is its target, or its up is along its line of sight".into())
                })?
        }
        sidecar::Pose::Matrix(rows) => {
            if rows.iter().flatten().any(|x| !x.is_finite()) {
                return Err(bad("its matrix has a value that is not finite".into()));
            }
            if rows[3] != [0.0, 0.0, 0.0, 1.0] {
                return Err(bad(format!(
                    "its matrix's last row is {:?}, not (0, 0, 0, 1): a camera-to-world placement has no projection",
                    rows[3]
                )));
            }
            let world = glam::Mat4::from_cols_array_2d(rows).transpose();
            let det = glam::Mat3::from_mat4(world).determinant();
            if !(det.is_finite() && det > 1e-12) {
                return Err(bad(format!(
                    "its matrix's 3×3 part has determinant {det}: {}",
                    if det < 0.0 {
                        "a reflection, which would mirror the image"
                    } else {
                        "it scales by 0, leaving no direction to look in"
                    }
                )));
            }
            Camera::from_node(desc.name.clone(), world, yfov, width, height)
        }
    };
    camera.aspect_ratio = aspect;
    Ok(camera)
}

/// Suffixes lightprobe puts after a view's name in its file names.
const VIEW_FILE_SUFFIXES: &[&str] = &[".error", ".depth", ".normal", ".albedo", ".mask"];

/// Refuses view names that cannot name files: empty, a leading dot (`..`, hidden files), path
/// separators or control
/// characters (a camera named `../x` would write outside the output folder), or one view's
/// name plus a suffix lightprobe appends (`.error`, `.depth`, …) being another's.
fn check_view_names(views: &[Camera], gltf_path: &Path) -> Result<()> {
    for c in views {
        let n = &c.name;
        let bad = n.is_empty()
            || n.starts_with('.')
            || n.chars()
                .any(|ch| ch == '/' || ch == '\\' || ch.is_control());
        if bad {
            return Err(Error::file(
                gltf_path,
                format!(
                    "camera node {n:?} cannot name a view's files (empty, leading dot, path separator or control character); rename it"
                ),
            ));
        }
        for d in views {
            if let Some(rest) = d.name.strip_prefix(n.as_str())
                && VIEW_FILE_SUFFIXES.contains(&rest)
            {
                return Err(Error::file(
                    gltf_path,
                    format!(
                        "views {n:?} and {:?} would write over each other's files ({n}{rest}.png); rename one",
                        d.name
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// A loaded scene, ready to build an acceleration structure over and render.
#[derive(Debug, Clone)]
pub struct Scene {
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    /// The views, in the sidecar's order (a glTF alone: the file's camera nodes in order).
    pub cameras: Vec<Camera>,
    /// The reference illumination: the sidecar's lights, or the glTF's own.
    pub lights: Vec<SphereLight>,
    pub settings: SceneSettings,
    /// Whether the views' image size was given (the sidecar's `image`, or
    /// [`LoadOptions::height`]) rather than the default: references may then not set it.
    pub size_given: bool,
    /// What the files hold that the model leaves out.
    pub ignored: Vec<Ignored>,
    /// The file this came from: a sidecar or a glTF (empty for scenes built in code).
    pub source: PathBuf,
    /// The glTF file the geometry came from (empty for scenes built in code).
    pub gltf: PathBuf,
    /// Every camera the files name, views or not (a name a view's twin, `<view>_b`, may not
    /// take; empty for scenes built in code).
    pub camera_names: Vec<String>,
}

/// Whether `path` is a glTF file rather than a RON sidecar: by its extension, else by its
/// first bytes (binary glTF's magic, or JSON's brace).
pub fn is_gltf(path: &Path) -> bool {
    match path.extension().and_then(|e| e.to_str()) {
        Some(e) if e.eq_ignore_ascii_case("gltf") || e.eq_ignore_ascii_case("glb") => true,
        Some(e) if e.eq_ignore_ascii_case("ron") => false,
        _ => {
            let mut head = [0u8; 16];
            let n = std::fs::File::open(path)
                .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
                .unwrap_or(0);
            head[..n].starts_with(b"glTF")
                || head[..n]
                    .iter()
                    .find(|b| !b.is_ascii_whitespace())
                    .is_some_and(|&b| b == b'{')
        }
    }
}

impl Scene {
    /// Loads a scene with default options ([`Scene::load_with`]).
    pub fn load(path: &Path) -> Result<Scene> {
        Scene::load_with(path, LoadOptions::default())
    }

    /// Loads a glTF (`.gltf`/`.glb`) by itself, or a sidecar and the glTF it names, applies
    /// the sidecar's albedo overrides and selects its views.
    pub fn load_with(path: &Path, options: LoadOptions) -> Result<Scene> {
        if is_gltf(path) {
            return Scene::from_gltf(path, options);
        }
        let sidecar_path = path;
        let sidecar = Sidecar::load(sidecar_path)?;
        let base = Sidecar::base_dir(sidecar_path);
        let gltf_path = base.join(&sidecar.gltf);
        let size = match (sidecar.image, options.height) {
            (Some(i), None) => ViewSize::Fixed {
                width: i.width.0,
                height: i.height.0,
            },
            (Some(i), Some(h)) => ViewSize::Fixed {
                width: ((i.width.0 as f64 * h as f64 / i.height.0 as f64).round() as u32)
                    .clamp(1, sidecar::MAX_IMAGE_SIDE),
                height: h,
            },
            (None, h) => ViewSize::Height(h.unwrap_or(DEFAULT_HEIGHT)),
        };
        let loaded = gltf::load(&gltf_path, size)?;

        let mut materials = loaded.materials;
        let mut mesh = loaded.mesh;
        let mut ignored = loaded.ignored;
        for (name, source) in &sidecar.albedo {
            let Some(index) = materials.iter().position(|m| &m.name == name) else {
                return Err(Error::file(
                    sidecar_path,
                    format!(
                        "albedo override names material {name:?}, which {} does not have",
                        gltf_path.display()
                    ),
                ));
            };
            // An override is the whole albedo: the material's vertex colours go too.
            mesh.clear_colors(index as u32);
            materials[index].albedo = match source {
                sidecar::AlbedoSource::Constant(c) => {
                    Albedo::Constant(Vec3::new(c.0.0, c.0.1, c.0.2))
                }
                sidecar::AlbedoSource::Map(p) => Albedo::Texture {
                    texture: std::sync::Arc::new(load_albedo_map(&base.join(p))?),
                    factor: Vec3::ONE,
                },
            };
        }
        // The sidecar's lights are the reference illumination; the glTF's then play no part.
        if !sidecar.lights.is_empty() {
            ignored.retain(|i| !i.what.starts_with("light "));
        }
        let (names, listed) = if options.views.is_empty() {
            (&sidecar.views, "the sidecar's `views`")
        } else {
            (&options.views, "the views asked for")
        };
        let mut cameras = loaded.cameras;
        for desc in &sidecar.cameras {
            if cameras.iter().any(|c| c.name == desc.name) {
                return Err(Error::file(
                    sidecar_path,
                    format!(
                        "camera {:?} is named twice (among `cameras`, or as a camera node of {}); rename one",
                        desc.name,
                        gltf_path.display()
                    ),
                ));
            }
            cameras.push(posed_camera(desc, size, sidecar_path)?);
        }
        let camera_names = cameras.iter().map(|c| c.name.clone()).collect();
        let cameras = pick_or_all(cameras, names, listed, &gltf_path, sidecar_path)?;
        let lights = if sidecar.lights.is_empty() {
            loaded.lights
        } else {
            sidecar.sphere_lights()
        };
        Ok(Scene {
            mesh,
            materials,
            cameras,
            lights,
            settings: SceneSettings {
                spp: sidecar.render.spp.0,
                max_bounces: sidecar.render.max_bounces.0,
                seed: sidecar.render.seed,
                rings: sidecar.envmap.rings.0,
            },
            size_given: sidecar.image.is_some() || options.height.is_some(),
            ignored,
            source: sidecar_path.to_path_buf(),
            gltf: gltf_path,
            camera_names,
        })
    }

    /// A glTF by itself: every camera node a view, its materials, its point lights, the
    /// sidecar's default settings.
    fn from_gltf(path: &Path, options: LoadOptions) -> Result<Scene> {
        let size = ViewSize::Height(options.height.unwrap_or(DEFAULT_HEIGHT));
        let loaded = gltf::load(path, size)?;
        let defaults = (
            sidecar::RenderDesc::default(),
            sidecar::EnvmapDesc::default(),
        );
        let camera_names = loaded.cameras.iter().map(|c| c.name.clone()).collect();
        Ok(Scene {
            mesh: loaded.mesh,
            materials: loaded.materials,
            camera_names,
            cameras: pick_or_all(
                loaded.cameras,
                &options.views,
                "the views asked for",
                path,
                path,
            )?,
            lights: loaded.lights,
            settings: SceneSettings {
                spp: defaults.0.spp.0,
                max_bounces: defaults.0.max_bounces.0,
                seed: defaults.0.seed,
                rings: defaults.1.rings.0,
            },
            size_given: options.height.is_some(),
            ignored: loaded.ignored,
            source: path.to_path_buf(),
            gltf: path.to_path_buf(),
        })
    }

    /// Sizes each view as its image in `sizes` (one per view, in order), checking it against
    /// the camera's glTF aspect ratio (within a pixel of rounding). `what` names each image
    /// in errors.
    pub fn size_views(
        &mut self,
        sizes: &[(u32, u32)],
        what: impl Fn(usize) -> PathBuf,
    ) -> Result<()> {
        for (i, (cam, &(w, h))) in self.cameras.iter_mut().zip(sizes).enumerate() {
            if let Some(a) = cam.aspect_ratio {
                // The width a camera of this aspect has at this height, ± a pixel of rounding.
                if ((w as f32) - a * h as f32).abs() > 1.0 {
                    return Err(Error::file(
                        what(i),
                        format!(
                            "is {w}×{h}, but camera {:?} has aspect ratio {a} (an image {:.0}×{h}); crop or pad the image, or change the camera's aspectRatio",
                            cam.name,
                            a * h as f32
                        ),
                    ));
                }
            }
            (cam.width, cam.height) = (w, h);
        }
        Ok(())
    }

    /// Pixels in all views together.
    pub fn pixel_count(&self) -> u64 {
        self.cameras
            .iter()
            .map(|c| c.width as u64 * c.height as u64)
            .sum()
    }

    /// The one image size every view has, if they share one.
    pub fn common_size(&self) -> Option<(u32, u32)> {
        let first = self.cameras.first().map(|c| (c.width, c.height))?;
        self.cameras
            .iter()
            .all(|c| (c.width, c.height) == first)
            .then_some(first)
    }

    /// The centre of the geometry's bounding box (the "scene centre" of light directions).
    pub fn center(&self) -> Vec3 {
        let (lo, hi) = self.mesh.bounds();
        0.5 * (lo + hi)
    }
}

impl Sidecar {
    /// The reference sphere lights, in world space.
    pub fn sphere_lights(&self) -> Vec<SphereLight> {
        self.lights
            .iter()
            .map(|l| match l {
                sidecar::LightDesc::Sphere {
                    center,
                    radius,
                    radiance,
                } => SphereLight {
                    center: Vec3::new(center.0.0, center.0.1, center.0.2),
                    radius: radius.0,
                    radiance: Vec3::new(radiance.0.0, radiance.0.1, radiance.0.2),
                },
                sidecar::LightDesc::Point { center, intensity } => SphereLight::point(
                    Vec3::new(center.0.0, center.0.1, center.0.2),
                    Vec3::new(intensity.0.0, intensity.0.1, intensity.0.2),
                ),
            })
            .collect()
    }
}

/// Loads geometry, materials and cameras from glTF/GLB bytes that need no external files
/// (for fuzzing and embedding): (mesh, materials, cameras). `label` names the bytes in errors.
pub fn load_gltf_bytes(
    bytes: &[u8],
    label: &Path,
    width: u32,
    height: u32,
) -> Result<(Mesh, Vec<Material>, Vec<Camera>)> {
    let l = gltf::load_slice(bytes, label, ViewSize::Fixed { width, height })?;
    Ok((l.mesh, l.materials, l.cameras))
}

/// Loads an sRGB-encoded albedo image (PNG or JPEG) as linear RGB.
pub fn load_albedo_map(path: &Path) -> Result<Texture> {
    let bytes = crate::memory::read_input(path)?;
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Error::io(path, e))
    };
    let undecodable =
        |e: image::ImageError| Error::file(path, format!("cannot decode albedo map: {e}"));
    let (w, h) = reader()?.into_dimensions().map_err(undecodable)?;
    // Decoded as 8-bit RGB, then kept as linear f32 RGB.
    crate::memory::reserve(w as u64 * h as u64 * 15, || {
        format!("{}: decoding its {w}×{h} albedo map", path.display())
    })?;
    let img = reader()?.decode().map_err(undecodable)?;
    let rgb = img.to_rgb8();
    Ok(Texture::from_srgb8(
        rgb.width(),
        rgb.height(),
        3,
        rgb.as_raw(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_decoding_endpoints_and_midpoint() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
    }

    #[test]
    fn the_mean_of_a_large_texture_is_exact() {
        // 2048² texels: an f32 running sum drifts by about 0.3% here.
        let t = Texture {
            width: 2048,
            height: 2048,
            texels: vec![Vec3::new(0.1, 0.3, 0.7); 2048 * 2048],
        };
        let m = t.mean();
        assert!(
            (m - Vec3::new(0.1, 0.3, 0.7)).abs().max_element() < 1e-6,
            "{m}"
        );
    }

    #[test]
    fn texture_bilinear_and_wrap() {
        // 2×1: left texel black, right white (linear 1.0 from sRGB 255).
        let t = Texture::from_srgb8(2, 1, 3, &[0, 0, 0, 255, 255, 255]);
        assert!((t.sample(Vec2::new(0.25, 0.5)).x - 0.0).abs() < 1e-6);
        assert!((t.sample(Vec2::new(0.75, 0.5)).x - 1.0).abs() < 1e-6);
        assert!((t.sample(Vec2::new(0.5, 0.5)).x - 0.5).abs() < 1e-6);
        // Repeat: u = 1.25 is u = 0.25.
        assert!((t.sample(Vec2::new(1.25, 0.5)) - t.sample(Vec2::new(0.25, 0.5))).length() < 1e-6);
        // Wrapping across the seam blends the two edge texels.
        assert!((t.sample(Vec2::new(0.0, 0.5)).x - 0.5).abs() < 1e-6);
    }

    #[test]
    fn flat_meshes_are_unshared_with_face_normals() {
        let mut m = Mesh::default();
        let p = [Vec3::ZERO, Vec3::X, Vec3::Z, Vec3::new(1.0, 0.0, 1.0)];
        m.push(&p, None, None, &[0, 2, 1, 1, 2, 3], 0);
        assert_eq!(m.positions.len(), 6);
        assert!(
            m.normals
                .iter()
                .all(|n| (n.abs() - Vec3::Y).length() < 1e-6)
        );
        assert!((m.surface_area() - 1.0).abs() < 1e-9);
        assert_eq!(m.bounds(), (Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0)));
    }
}
