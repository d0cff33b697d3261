//! `info`: what lightprobe loaded from a scene, as JSON.

use serde_json::json;

use super::{SceneArgs, outln};
use lightprobe::scene::Albedo;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let path = &a.scene.scene;
    let scene = a.scene.load()?;
    let (lo, hi) = scene.mesh.bounds();
    let materials: Vec<_> = scene
        .materials
        .iter()
        .map(|m| match &m.albedo {
            Albedo::Constant(c) => json!({ "name": m.name, "albedo": c.to_array() }),
            Albedo::Texture { texture, factor } => json!({
                "name": m.name,
                "albedo_factor": factor.to_array(),
                "texture": { "width": texture.width, "height": texture.height, "mean_linear": texture.mean().to_array() },
            }),
        })
        .collect();
    let cameras: Vec<_> = scene
        .cameras
        .iter()
        .map(|c| {
            json!({
                "name": c.name,
                "origin": c.origin_world.to_array(),
                "right": c.world_from_camera.x_axis.to_array(),
                "up": c.world_from_camera.y_axis.to_array(),
                "forward": (-c.world_from_camera.z_axis).to_array(),
                "yfov": c.yfov,
                "width": c.width,
                "height": c.height,
            })
        })
        .collect();
    let out = json!({
        "scene": path,
        "triangles": scene.mesh.triangle_count(),
        "vertices": scene.mesh.positions.len(),
        "vertex_colors": scene.mesh.has_colors(),
        "bounds": { "min": lo.to_array(), "max": hi.to_array() },
        "surface_area": scene.mesh.surface_area(),
        "materials": materials,
        "cameras": cameras,
        "lights": scene.lights.iter().map(|l| if l.is_point() {
            json!({ "center": l.center.to_array(), "radius": 0.0, "intensity": l.radiance.to_array() })
        } else {
            json!({ "center": l.center.to_array(), "radius": l.radius, "radiance": l.radiance.to_array() })
        }).collect::<Vec<_>>(),
        "ignored": scene.ignored,
        "settings": {
            "width": scene.common_size().map(|s| s.0), "height": scene.common_size().map(|s| s.1),
            "spp": scene.settings.spp,
            "max_bounces": scene.settings.max_bounces, "seed": scene.settings.seed, "rings": scene.settings.rings,
        },
    });
    outln!("{}", serde_json::to_string_pretty(&out)?)?;
    Ok(())
}
