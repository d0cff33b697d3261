//! The scene with an estimate as a Mitsuba 3 scene (`scene.xml` and the files it names), so
//! that `mitsuba scene.xml` renders every view as lightprobe's re-render does:
//!
//! - meshes: one binary PLY per material, world space, metres, +Y up (Mitsuba's frame is
//!   glTF's), with lightprobe's shading normals, glTF texture coordinates (v down, which
//!   Mitsuba's bitmap texture also takes) and per-vertex colours when the material has them;
//! - materials: two-sided `diffuse` of lightprobe's albedo — a constant, a float EXR texture of
//!   baseColorFactor × the decoded texture (bilinear, repeat), or the vertex colours × the
//!   factor (Mitsuba has no product of a texture and vertex colours: such a material keeps its
//!   texture, and [`write`] says so);
//! - lights: sphere lights as `sphere` shapes with an `area` emitter and a black BSDF, point
//!   lights as `point` emitters (intensity in W/sr per channel), the envmap as an `envmap`
//!   emitter of a lat-long EXR in Mitsuba's convention with its default (identity) frame;
//! - the `path` integrator with lightprobe's bounce count (`max_depth` = bounces + 1, Russian
//!   roulette off, emitters hidden from the camera), one `perspective` sensor per view
//!   (vertical field of view, box filter, RGBA float film) in the views' order, which Mitsuba's
//!   `-s` picks (a comment at the top lists them); the sample count overridable as
//!   `mitsuba -Dspp=N`.

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;

use super::super::{Albedo, Scene, SphereLight};
use crate::envmap::Envmap;
use crate::envmap::latlong::{self, Filter, Target};
use crate::error::{Error, Result};
use crate::imageio;

/// Width of the envmap's lat-long EXR (its height is half): Mitsuba interpolates between
/// pixels, which blurs a cell's edges by half a pixel (the worst cell of 9 rings loses 0.7% of
/// its power at this width, 2.7% at 1024).
const ENVMAP_WIDTH: u32 = 4096;

/// How Mitsuba should render: lightprobe's samples per pixel and bounce count.
#[derive(Debug, Clone, Copy)]
pub struct Render {
    pub spp: u32,
    /// Scattering events per path (lightprobe's `max_bounces`).
    pub max_bounces: u32,
}

/// Writes `dir/scene.xml` with `meshes/`, `textures/` and `envmap.exr` beside it. Returns
/// what the Mitsuba scene leaves out, one sentence each (empty when nothing).
pub fn write(
    dir: &Path,
    scene: &Scene,
    lights: &[SphereLight],
    doubts: super::RadiusDoubts,
    envmap: Option<&Envmap>,
    render: Render,
) -> Result<Vec<String>> {
    let mut notes = Vec::new();
    for sub in ["meshes", "textures"] {
        let d = dir.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
    }
    let mut xml = String::from("<?xml version=\"1.0\" encoding=\"utf-8\"?>\n");
    xml += "<!-- Written by lightprobe: the scene under its estimated lighting. Linear RGB, metres, +Y up. -->\n";
    xml += "<!-- One sensor per view; render view k (numbered from 0) with `mitsuba -s k -o <view>.exr scene.xml`:";
    for (k, cam) in scene.cameras.iter().enumerate() {
        let _ = write!(xml, " {k} {}", escape(&cam.name).replace("--", "- -"));
    }
    xml += " -->\n<scene version=\"3.0.0\">\n";
    let _ = writeln!(xml, "    <default name=\"spp\" value=\"{}\"/>", render.spp);
    let _ = writeln!(
        xml,
        "    <integrator type=\"path\">\n        <integer name=\"max_depth\" value=\"{}\"/>\n        <integer name=\"rr_depth\" value=\"{}\"/>\n        <boolean name=\"hide_emitters\" value=\"true\"/>\n    </integrator>",
        render.max_bounces + 1,
        render.max_bounces + 2
    );
    for cam in &scene.cameras {
        let forward = -cam.world_from_camera.z_axis;
        let up = cam.world_from_camera.y_axis;
        let target = cam.origin_world + forward;
        let _ = writeln!(
            xml,
            "    <sensor type=\"perspective\" id=\"{}\">\n        <string name=\"fov_axis\" value=\"y\"/>\n        <float name=\"fov\" value=\"{}\"/>\n        <float name=\"near_clip\" value=\"0.001\"/>\n        <float name=\"far_clip\" value=\"10000\"/>\n        <transform name=\"to_world\">\n            <lookat origin=\"{}\" target=\"{}\" up=\"{}\"/>\n        </transform>\n        <sampler type=\"independent\">\n            <integer name=\"sample_count\" value=\"$spp\"/>\n        </sampler>\n        <film type=\"hdrfilm\">\n            <integer name=\"width\" value=\"{}\"/>\n            <integer name=\"height\" value=\"{}\"/>\n            <string name=\"pixel_format\" value=\"rgba\"/>\n            <rfilter type=\"box\"/>\n        </film>\n    </sensor>",
            sensor_id(&cam.name),
            cam.yfov.to_degrees(),
            triple(cam.origin_world),
            triple(target),
            triple(up),
            cam.width,
            cam.height
        );
    }
    let mesh = &scene.mesh;
    for (m, material) in scene.materials.iter().enumerate() {
        let triangles: Vec<[u32; 3]> = mesh
            .triangles
            .iter()
            .zip(&mesh.triangle_material)
            .filter(|(_, tm)| **tm == m as u32)
            .map(|(t, _)| *t)
            .collect();
        if triangles.is_empty() {
            continue;
        }
        let colored = triangles
            .iter()
            .flatten()
            .any(|&v| mesh.colors[v as usize] != Vec3::ONE);
        let factor = match &material.albedo {
            Albedo::Constant(c) => *c,
            Albedo::Texture { factor, .. } => *factor,
        };
        let reflectance = match (&material.albedo, colored) {
            (Albedo::Texture { texture, factor }, _) => {
                if colored {
                    notes.push(format!(
                        "material {:?}: Mitsuba cannot multiply a texture by vertex colours; its mitsuba/ scene keeps the texture and leaves the colours out",
                        material.name
                    ));
                }
                let file = format!("textures/{m}.exr");
                imageio::write_exr(&dir.join(&file), &super::albedo_image(texture, *factor))?;
                format!(
                    "<texture type=\"bitmap\" name=\"reflectance\">\n                <string name=\"filename\" value=\"{file}\"/>\n                <string name=\"filter_type\" value=\"bilinear\"/>\n                <string name=\"wrap_mode\" value=\"repeat\"/>\n                <boolean name=\"raw\" value=\"true\"/>\n            </texture>"
                )
            }
            (Albedo::Constant(_), true) => "<texture type=\"mesh_attribute\" name=\"reflectance\">\n                <string name=\"name\" value=\"vertex_color\"/>\n            </texture>".to_string(),
            (Albedo::Constant(c), false) => format!("<rgb name=\"reflectance\" value=\"{}\"/>", triple(*c)),
        };
        // Vertex colours carry the factor: Mitsuba's `mesh_attribute` cannot be scaled here.
        let colors = (colored && matches!(material.albedo, Albedo::Constant(_))).then_some(factor);
        let file = format!("meshes/{m}.ply");
        imageio::write_bytes(&dir.join(&file), &ply(scene, &triangles, colors))?;
        let _ = writeln!(
            xml,
            "    <!-- material {} -->\n    <shape type=\"ply\">\n        <string name=\"filename\" value=\"{file}\"/>\n        <boolean name=\"face_normals\" value=\"false\"/>\n        <bsdf type=\"twosided\">\n            <bsdf type=\"diffuse\">\n            {reflectance}\n            </bsdf>\n        </bsdf>\n    </shape>",
            escape(&material.name).replace("--", "- -")
        );
    }
    for (k, l) in lights.iter().enumerate() {
        if let Some(f) = super::doubt(doubts, k) {
            let _ = writeln!(
                xml,
                "    <!-- {} -->",
                super::radius_doubt_words(l.radius, f)
            );
        }
        if l.is_point() {
            let _ = writeln!(
                xml,
                "    <emitter type=\"point\">\n        <point name=\"position\" value=\"{}\"/>\n        <rgb name=\"intensity\" value=\"{}\"/>\n    </emitter>",
                triple(l.center),
                triple(l.intensity())
            );
        } else {
            let _ = writeln!(
                xml,
                "    <shape type=\"sphere\">\n        <point name=\"center\" value=\"{}\"/>\n        <float name=\"radius\" value=\"{}\"/>\n        <emitter type=\"area\">\n            <rgb name=\"radiance\" value=\"{}\"/>\n        </emitter>\n        <bsdf type=\"diffuse\">\n            <rgb name=\"reflectance\" value=\"0\"/>\n        </bsdf>\n    </shape>",
                triple(l.center),
                l.radius,
                triple(l.radiance)
            );
        }
    }
    if let Some(env) = envmap {
        imageio::write_latlong_exr(
            &dir.join("envmap.exr"),
            &latlong::export(env, Target::Mitsuba, Filter::Box, ENVMAP_WIDTH),
        )?;
        xml += "    <emitter type=\"envmap\">\n        <string name=\"filename\" value=\"envmap.exr\"/>\n    </emitter>\n";
    }
    xml += "</scene>\n";
    imageio::write_bytes(&dir.join("scene.xml"), xml.as_bytes())?;
    Ok(notes)
}

/// `x, y, z` for an XML attribute.
fn triple(v: Vec3) -> String {
    format!("{}, {}, {}", v.x, v.y, v.z)
}

/// A view's name as a sensor `id`: Mitsuba substitutes `$name` in every attribute value, so a
/// `$` becomes `_` (the comment atop the file lists the views by index as they are named).
fn sensor_id(name: &str) -> String {
    escape(&name.replace('$', "_"))
}

/// Text safe inside an XML attribute or comment.
fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A binary little-endian PLY of `triangles` of the scene's mesh: their vertices (position,
/// normal, texture coordinates; with `colors`, the vertex colour times that factor as float
/// `r g b`, which Mitsuba reads as the `vertex_color` attribute) and faces.
fn ply(scene: &Scene, triangles: &[[u32; 3]], colors: Option<Vec3>) -> Vec<u8> {
    let mesh = &scene.mesh;
    let mut index = vec![u32::MAX; mesh.positions.len()];
    let mut used = Vec::new();
    let faces: Vec<[u32; 3]> = triangles
        .iter()
        .map(|t| {
            t.map(|v| {
                if index[v as usize] == u32::MAX {
                    index[v as usize] = used.len() as u32;
                    used.push(v);
                }
                index[v as usize]
            })
        })
        .collect();
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment lightprobe: world space, metres, +Y up; uv as glTF (v down)\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty float u\nproperty float v\n",
        used.len()
    );
    if colors.is_some() {
        header += "property float r\nproperty float g\nproperty float b\n";
    }
    header += &format!(
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        faces.len()
    );
    let per_vertex = 4 * if colors.is_some() { 11 } else { 8 };
    let mut out = Vec::with_capacity(header.len() + used.len() * per_vertex + faces.len() * 13);
    out.extend_from_slice(header.as_bytes());
    for &v in &used {
        let v = v as usize;
        let mut put = |x: f32| out.extend_from_slice(&x.to_le_bytes());
        let (p, n, uv) = (mesh.positions[v], mesh.normals[v], mesh.uvs[v]);
        for x in [p.x, p.y, p.z, n.x, n.y, n.z, uv.x, uv.y] {
            put(x);
        }
        if let Some(f) = colors {
            let c = (mesh.colors[v] * f).clamp(Vec3::ZERO, Vec3::ONE);
            for x in [c.x, c.y, c.z] {
                put(x);
            }
        }
    }
    for f in faces {
        out.push(3);
        for v in f {
            out.extend_from_slice(&(v as i32).to_le_bytes());
        }
    }
    out
}
