//! Random illumination scenarios of one scene, for the paper's experiment: one or two sphere
//! lights at random directions over the upper hemisphere (some low, some grazing), distances
//! from about the scene's size to 10× it, varied radii and brightness (up to 10× between two
//! lights). Deterministic in the seed; each scenario is written as a sidecar of its own.
//!
//! Directions and distances are measured from the scene centre (the centre of the geometry's
//! bounding box), elevation above the world horizontal plane (+Y up), azimuth
//! φ = atan2(x, −z) like the envmap grid's.

use std::path::{Component, Path, PathBuf};

use glam::Vec3;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::sampling::{Rng, mix64};
use crate::scene::sidecar::{self, LightDesc, Sidecar};
use crate::scene::{Scene, SphereLight};

/// One light of a scenario, with the numbers it was drawn from.
#[derive(Debug, Clone, Serialize)]
pub struct ScenarioLight {
    /// Above the horizontal plane through the scene centre, degrees.
    pub elevation_degrees: f32,
    /// φ = atan2(x, −z), degrees in [0, 360).
    pub azimuth_degrees: f32,
    /// Centre distance from the scene centre, metres.
    pub distance: f32,
    /// Half-angle the sphere subtends at the scene centre, degrees.
    pub angular_radius_degrees: f32,
    /// Irradiance it alone delivers at the scene centre facing it, W·m⁻² (luminance), ≈ π L sin²α.
    pub irradiance: f32,
    pub center: [f32; 3],
    pub radius: f32,
    pub radiance: [f32; 3],
}

/// A generated scenario.
#[derive(Debug, Clone, Serialize)]
pub struct Scenario {
    pub name: String,
    /// Which elevation band the first light was drawn from: "high", "low" or "grazing".
    pub kind: String,
    pub lights: Vec<ScenarioLight>,
}

impl ScenarioLight {
    pub fn sphere(&self) -> SphereLight {
        SphereLight {
            center: Vec3::from(self.center),
            radius: self.radius,
            radiance: Vec3::from(self.radiance),
        }
    }
}

/// True when a sphere could show in, or block, any of the scene's views (with a margin).
fn seen_by_cameras(scene: &Scene, center: Vec3, radius: f32) -> bool {
    scene.cameras.iter().any(|cam| {
        let to = center - cam.origin_world;
        let d = to.length();
        if d <= radius * 1.5 {
            return true;
        }
        let forward = -(cam.world_from_camera.z_axis);
        let aspect = cam.width as f32 / cam.height as f32;
        let t = (0.5 * cam.yfov).tan();
        let half_diagonal = (t * (1.0 + aspect * aspect).sqrt()).atan();
        let angle = forward.angle_between(to / d);
        angle < half_diagonal + (radius / d).asin() + 3f32.to_radians()
    })
}

/// Draws `count` scenarios of `scene`. The same (scene, count, seed) gives the same scenarios.
/// Fails when no valid placement turns up (e.g. the views see every direction).
pub fn generate(scene: &Scene, count: usize, seed: u64) -> Result<Vec<Scenario>> {
    let (lo, hi) = scene.mesh.bounds();
    let center = 0.5 * (lo + hi);
    // "The scene's size": the larger horizontal extent (the table's width here).
    let size = (hi.x - lo.x).max(hi.z - lo.z).max(1e-3);
    let half_diagonal = 0.5 * (hi - lo).length();
    (0..count)
        .map(|i| {
            let mut rng = Rng::new(mix64(seed ^ mix64(i as u64 + 0x5CE7)));
            let two = rng.next_f32() < 0.5;
            let u = rng.next_f32();
            let kind = if u < 0.7 {
                "high"
            } else if u < 0.9 {
                "low"
            } else {
                "grazing"
            };
            let mut lights: Vec<ScenarioLight> = Vec::new();
            let n = if two { 2 } else { 1 };
            let mut attempts = 0;
            // The first light sets the exposure; the second is 0.1–1× as bright.
            let e_first = 2.0 * 4f32.powf(rng.next_f32());
            while lights.len() < n {
                attempts += 1;
                if attempts > 100_000 {
                    return Err(Error::Invalid(format!(
                        "{}: found no light placement that the views do not see",
                        scene.source.display()
                    )));
                }
                let band = if lights.is_empty() { kind } else { "high" };
                let (e_lo, e_hi) = match band {
                    "high" => (15.0f32, 85.0f32),
                    "low" => (5.0, 15.0),
                    _ => (1.0, 5.0),
                };
                // Uniform in solid angle within the band.
                let (s_lo, s_hi) = (e_lo.to_radians().sin(), e_hi.to_radians().sin());
                let elevation = (s_lo + (s_hi - s_lo) * rng.next_f32()).asin();
                let azimuth = std::f32::consts::TAU * rng.next_f32();
                let distance = size * 10f32.powf(rng.next_f32());
                let alpha = (1.5f32 * (8.0f32 / 1.5).powf(rng.next_f32())).to_radians();
                let radius = distance * alpha.sin();
                let dir = Vec3::new(
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                    -elevation.cos() * azimuth.cos(),
                );
                let c = center + distance * dir;
                let e = if lights.is_empty() {
                    e_first
                } else {
                    e_first * 0.1 * 10f32.powf(rng.next_f32())
                };
                let clear_of_geometry = distance - radius > half_diagonal + 0.1;
                let apart = lights
                    .iter()
                    .all(|l| Vec3::from(l.center).distance(c) > l.radius + radius + 0.1);
                if !clear_of_geometry || !apart || seen_by_cameras(scene, c, radius) {
                    continue;
                }
                // A mild warm or cool tint, luminance-normalised.
                let warm = rng.next_f32() - 0.5;
                let tint = Vec3::new(1.0 + 0.3 * warm, 1.0, 1.0 - 0.3 * warm);
                let tint = tint / crate::imageio::luminance(tint);
                let l = e / (std::f32::consts::PI * alpha.sin().powi(2));
                let rad = tint * l;
                lights.push(ScenarioLight {
                    elevation_degrees: elevation.to_degrees(),
                    azimuth_degrees: azimuth.to_degrees(),
                    distance,
                    angular_radius_degrees: alpha.to_degrees(),
                    irradiance: e,
                    center: c.to_array(),
                    radius,
                    radiance: rad.to_array(),
                });
            }
            Ok(Scenario {
                name: format!("s{i:02}"),
                kind: kind.to_string(),
                lights,
            })
        })
        .collect()
}

/// The components of an absolute path with `.` and `..` resolved lexically.
fn normalise(p: &Path) -> Vec<Component<'_>> {
    let mut v: Vec<Component> = Vec::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir if matches!(v.last(), Some(Component::Normal(_))) => {
                v.pop();
            }
            _ => v.push(c),
        }
    }
    v
}

/// `target` as a path relative to folder `from` (both made absolute first).
pub fn relative_path(target: &Path, from: &Path) -> Result<PathBuf> {
    let abs = |p: &Path| -> Result<PathBuf> { std::path::absolute(p).map_err(|e| Error::io(p, e)) };
    let (t, f) = (abs(target)?, abs(from)?);
    let (t, f) = (normalise(&t), normalise(&f));
    let common = t.iter().zip(&f).take_while(|(a, b)| a == b).count();
    let mut out = PathBuf::new();
    for _ in common..f.len() {
        out.push("..");
    }
    for c in &t[common..] {
        out.push(c.as_os_str());
    }
    Ok(out)
}

/// The sidecar text of `scenario`: the template's scene, views and settings (its paths made
/// relative to `out_dir`), with the scenario's lights.
pub fn sidecar_text(template: &Path, scenario: &Scenario, out_dir: &Path) -> Result<String> {
    if crate::scene::is_gltf(template) {
        return Err(Error::file(
            template,
            "is a glTF; scenarios copy a sidecar with new lights: write a sidecar (.ron) that names it",
        ));
    }
    let mut sc = Sidecar::load(template)?;
    let base = Sidecar::base_dir(template);
    sc.gltf = relative_path(&base.join(&sc.gltf), out_dir)?;
    for source in sc.albedo.values_mut() {
        if let sidecar::AlbedoSource::Map(p) = source {
            *p = relative_path(&base.join(&*p), out_dir)?;
        }
    }
    sc.lights = scenario
        .lights
        .iter()
        .map(|l| LightDesc::Sphere {
            center: sidecar::Point(l.center.into()),
            radius: sidecar::Positive(l.radius),
            radiance: sidecar::Rgb(l.radiance.into()),
        })
        .collect();
    let body =
        ron::ser::to_string_pretty(&sc, ron::ser::PrettyConfig::default().struct_names(true))
            .map_err(|e| Error::Invalid(format!("cannot write the sidecar: {e}")))?;
    let mut text = format!(
        "// Scenario {} ({} light, generated by `lightprobe scenarios` from {}):\n",
        scenario.name,
        scenario.kind,
        template.display()
    );
    for (k, l) in scenario.lights.iter().enumerate() {
        text += &format!(
            "// light {k}: elevation {:.1}°, azimuth {:.1}°, distance {:.2} m, angular radius {:.2}°, irradiance {:.2}\n",
            l.elevation_degrees,
            l.azimuth_degrees,
            l.distance,
            l.angular_radius_degrees,
            l.irradiance
        );
    }
    Ok(text + &body + "\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths() {
        let r = relative_path(Path::new("/a/b/c.glb"), Path::new("/a/d/e")).unwrap();
        assert_eq!(r, PathBuf::from("../../b/c.glb"));
        let r = relative_path(Path::new("/a/b/../c.glb"), Path::new("/a/./")).unwrap();
        assert_eq!(r, PathBuf::from("c.glb"));
    }
}
