//! The estimate as a Blender script (`blender.py`): run by Blender (`blender --background
//! --python blender.py`) or by the `bpy` module (`python blender.py`), it imports the glTF
//! written beside it (the scene with the estimate's lights as `KHR_lights_punctual`), makes
//! every material the Lambertian lightprobe renders (a Diffuse BSDF of roughness 0 whose colour
//! is baseColorFactor × texture × vertex colour), sets the World to the envmap (an
//! Environment Texture of the lat-long EXR in Blender's convention, default mapping), the
//! lights' radii to those in their `extras`, Cycles to lightprobe's bounce count and samples,
//! and renders each view to `renders/<view>.exr` (linear float RGBA; alpha = coverage, the
//! envmap seen directly is transparent, as lightprobe renders it black). The settings and
//! why each is what it is are written in the script.

use std::path::Path;

use glam::Vec3;
use serde_json::json;

use super::super::{Albedo, Scene};
use crate::envmap::Envmap;
use crate::envmap::latlong::{self, Filter, Target};
use crate::error::Result;
use crate::imageio;

/// Width of the envmap's lat-long EXR (its height is half). Cycles' bilinear lookup shrinks
/// the map's bright cells by about half a pixel, −0.08% of their power at this width.
const ENVMAP_WIDTH: u32 = 4096;

/// The script, with this scene's data put in (see [`write`]).
const SCRIPT: &str = include_str!("blender.py");

/// Writes `dir/blender.py`, which renders `dir/<gltf>` (written by
/// [`super::write_with_lights`]) under `envmap` (written beside it as
/// `envmap_blender.exr`), with albedo textures as linear EXRs in `dir/blender_textures/`.
/// `spp` and `max_bounces` are lightprobe's.
pub fn write(
    dir: &Path,
    gltf: &str,
    scene: &Scene,
    envmap: Option<&Envmap>,
    spp: u32,
    max_bounces: u32,
) -> Result<()> {
    let mut materials = serde_json::Map::new();
    for (m, material) in scene.materials.iter().enumerate() {
        let (factor, texture) = match &material.albedo {
            Albedo::Constant(c) => (*c, None),
            Albedo::Texture { texture, factor } => {
                let tex_dir = dir.join("blender_textures");
                std::fs::create_dir_all(&tex_dir)
                    .map_err(|e| crate::error::Error::io(&tex_dir, e))?;
                let file = format!("blender_textures/{m}.exr");
                imageio::write_exr(&dir.join(&file), &super::albedo_image(texture, *factor))?;
                (Vec3::ONE, Some(file))
            }
        };
        materials.insert(
            material.name.clone(),
            json!({ "color": factor.to_array(), "texture": texture }),
        );
    }
    let views: Vec<_> = scene
        .cameras
        .iter()
        .map(|c| {
            let m = c.world_from_camera;
            json!({
                "name": c.name,
                "origin": c.origin_world.to_array(),
                "right": m.x_axis.to_array(),
                "up": m.y_axis.to_array(),
                "back": m.z_axis.to_array(),
                "yfov": c.yfov,
                "width": c.width,
                "height": c.height,
            })
        })
        .collect();
    let envmap_file = match envmap {
        Some(env) => {
            imageio::write_latlong_exr(
                &dir.join("envmap_blender.exr"),
                &latlong::export(env, Target::Blender, Filter::Box, ENVMAP_WIDTH),
            )?;
            Some("envmap_blender.exr")
        }
        None => None,
    };
    let data = json!({
        "gltf": gltf,
        "envmap": envmap_file,
        "spp": spp,
        "max_bounces": max_bounces,
        "views": views,
        "materials": materials,
    });
    let text = SCRIPT.replace(
        "DATA = {}  # filled in by lightprobe",
        &format!(
            "DATA = json.loads(r'''{}''')",
            // A quote would end the raw string; JSON reads the escape back.
            serde_json::to_string_pretty(&data)
                .expect("JSON of plain values")
                .replace('\'', "\\u0027")
        ),
    );
    imageio::write_bytes(&dir.join("blender.py"), text.as_bytes())
}
