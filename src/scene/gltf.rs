//! glTF 2.0 loading: the default scene's node hierarchy multiplied out into world-space
//! triangles, perspective camera nodes, baseColor materials (factor × sRGB texture) and
//! `KHR_lights_punctual` point lights. What the Lambertian model leaves out of a material is
//! listed ([`Ignored`]), not silently dropped.

use std::path::Path;
use std::sync::Arc;

use glam::{Mat3, Mat4, Vec2, Vec3};
use gltf::mesh::Mode;

use super::{Albedo, Camera, Ignored, Material, Mesh, SphereLight, Texture, ViewSize};
use crate::error::{Error, Result};

/// Lumens per watt of KHR_lights_punctual's photometric units, as Blender's glTF importer and
/// exporter convert them: a point light of `intensity` candela has a radiant intensity of
/// `intensity / 683` W·sr⁻¹ (times its colour).
pub const LUMENS_PER_WATT: f32 = 683.0;

/// Deeper node hierarchies are refused (glTF forbids cycles, but a broken file may have one).
const MAX_NODE_DEPTH: usize = 256;

pub(super) struct Loaded {
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    pub cameras: Vec<Camera>,
    /// The file's `KHR_lights_punctual` lights, world space.
    pub lights: Vec<SphereLight>,
    /// What the model leaves out, per material or light.
    pub ignored: Vec<Ignored>,
}

/// Loads a `.gltf` or `.glb`; cameras get their image size from `size`.
pub(super) fn load(path: &Path, size: ViewSize) -> Result<Loaded> {
    // Checked before opening: a pipe would block the open, a device never ends.
    let len = crate::memory::regular_file(path)?.len();
    let mut head = [0u8; 12];
    let n = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
        .map_err(|e| Error::io(path, e))?;
    if len == 0 {
        return Err(Error::file(path, "is empty (expected a glTF 2.0 scene)"));
    }
    let glb = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    if glb && !head[..n].starts_with(b"glTF") {
        return Err(Error::file(
            path,
            "not a GLB file: it does not start with the GLB signature \"glTF\"",
        ));
    }
    let json = head[..n]
        .iter()
        // (a UTF-8 byte-order mark is tolerated, as the gltf crate does)
        .find(|b| !b.is_ascii_whitespace() && ![0xEF, 0xBB, 0xBF].contains(*b))
        .is_some_and(|&b| b == b'{');
    if !head[..n].starts_with(b"glTF") && !json {
        return Err(Error::file(
            path,
            "not a glTF 2.0 file: neither JSON (.gltf) nor binary glTF (.glb)",
        ));
    }
    check_glb_header(&head[..n], len, path)?;
    check_uris(path)?;
    let imported = contain(path, || gltf::import(path))?.map_err(|e| match e {
        gltf::Error::Io(io) => Error::io(path, io),
        other => Error::file(path, format!("not a valid glTF 2.0 file: {other}")),
    })?;
    contain(path, || build(path, imported, size))?
}

/// Loads glTF or GLB bytes that need no external files (`label` names them in errors).
pub(super) fn load_slice(bytes: &[u8], label: &Path, size: ViewSize) -> Result<Loaded> {
    check_glb_header(bytes, bytes.len() as u64, label)?;
    let imported = contain(label, || gltf::import_slice(bytes))?
        .map_err(|e| Error::file(label, format!("not a valid glTF 2.0 file: {e}")))?;
    contain(label, || build(label, imported, size))?
}

/// Runs the gltf crate's parser, turning a panic inside it into an error. gltf 1.4 indexes
/// unchecked references in some validation hooks (found by fuzzing: a POSITION accessor index
/// out of range panics even in release builds); a malformed file must give an error, not a
/// crash. The panic hook is silenced for the duration (the parser runs on the calling thread).
fn contain<T>(path: &Path, parse: impl FnOnce() -> T) -> Result<T> {
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(parse));
    std::panic::set_hook(hook);
    result.map_err(|_| {
        Error::file(
            path,
            "not a valid glTF 2.0 file: it refers to objects that do not exist",
        )
    })
}

/// Checks a GLB header (the first bytes of a file of `len` bytes) before the gltf crate does
/// arithmetic on it (gltf 1.4 subtracts 12 from the declared length unchecked: found by
/// fuzzing). Text glTF passes through.
fn check_glb_header(head: &[u8], len: u64, path: &Path) -> Result<()> {
    if !head.starts_with(b"glTF") {
        return Ok(());
    }
    if head.len() < 12 {
        return Err(Error::file(
            path,
            "not a valid glTF 2.0 file: truncated GLB header",
        ));
    }
    let word = |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
    if word(4) != 2 {
        return Err(Error::file(
            path,
            format!(
                "not a valid glTF 2.0 file: GLB version {} (only 2 is supported)",
                word(4)
            ),
        ));
    }
    if word(8) < 12 {
        return Err(Error::file(
            path,
            format!(
                "not a valid glTF 2.0 file: GLB declares a length of {} bytes",
                word(8)
            ),
        ));
    }
    if u64::from(word(8)) > len {
        return Err(Error::file(
            path,
            format!(
                "not a valid glTF 2.0 file: truncated (the GLB declares {} bytes, the file has {len})",
                word(8)
            ),
        ));
    }
    Ok(())
}

/// Refuses buffer and image URIs that would read outside the glTF's folder (absolute paths,
/// `..`), before anything is read.
fn check_uris(path: &Path) -> Result<()> {
    let Ok(gltf) = contain(path, || gltf::Gltf::open(path))? else {
        return Ok(()); // the import reports the real problem
    };
    let uris = gltf
        .buffers()
        .filter_map(|b| match b.source() {
            gltf::buffer::Source::Uri(u) => Some(u.to_string()),
            gltf::buffer::Source::Bin => None,
        })
        .chain(gltf.images().filter_map(|i| match i.source() {
            gltf::image::Source::Uri { uri, .. } => Some(uri.to_string()),
            gltf::image::Source::View { .. } => None,
        }));
    for uri in uris {
        if uri.starts_with("data:") {
            continue;
        }
        let p = Path::new(&uri);
        let escapes = p.is_absolute()
            || uri.contains("://")
            || p.components()
                .any(|c| matches!(c, std::path::Component::ParentDir));
        if escapes {
            return Err(Error::file(
                path,
                format!("refuses URI {uri:?}: it points outside the glTF's folder"),
            ));
        }
        let file = path
            .parent()
            .unwrap_or(Path::new(""))
            .join(percent_decode(&uri));
        if !file.is_file() {
            return Err(Error::file(
                path,
                format!("refers to {uri:?}, which does not exist next to it"),
            ));
        }
    }
    Ok(())
}

/// Decodes `%XX` escapes of a relative URI (glTF URIs are RFC 3986).
pub(super) fn percent_decode(uri: &str) -> String {
    let b = uri.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let Ok(v) =
                u8::from_str_radix(std::str::from_utf8(&b[i + 1..i + 3]).unwrap_or("zz"), 16)
        {
            out.push(v);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

type Imported = (
    gltf::Document,
    Vec<gltf::buffer::Data>,
    Vec<gltf::image::Data>,
);

fn build(path: &Path, (doc, buffers, images): Imported, size: ViewSize) -> Result<Loaded> {
    // Textures are kept as linear f32 RGB: 12 bytes a texel.
    let texels: u64 = images
        .iter()
        .map(|i| i.width as u64 * i.height as u64)
        .sum();
    crate::memory::reserve(texels * 12, || {
        format!(
            "{}: its {} textures ({texels} texels)",
            path.display(),
            images.len()
        )
    })?;
    let textures: Vec<Arc<Texture>> = images
        .iter()
        .map(|img| Arc::new(decode_image(img)))
        .collect();

    // Material 0 is glTF's default material (white), used by primitives without one.
    let mut materials = vec![Material {
        name: String::new(),
        albedo: Albedo::Constant(Vec3::ONE),
    }];
    let mut texcoord_set = vec![0u32];
    let mut ignored = Vec::new();
    for m in doc.materials() {
        let pbr = m.pbr_metallic_roughness();
        let [r, g, b, _] = pbr.base_color_factor();
        let factor = Vec3::new(r, g, b).clamp(Vec3::ZERO, Vec3::ONE);
        let name = m
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("material{}", materials.len() - 1));
        let albedo = match pbr.base_color_texture() {
            Some(info) => {
                texcoord_set.push(info.tex_coord());
                let texture = textures[info.texture().source().index()].clone();
                Albedo::Texture { texture, factor }
            }
            None => {
                texcoord_set.push(0);
                Albedo::Constant(factor)
            }
        };
        let left_out = left_out_of(&m);
        if !left_out.is_empty() {
            ignored.push(Ignored {
                what: format!("material {name:?}"),
                properties: left_out,
            });
        }
        materials.push(Material { name, albedo });
    }

    let scene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| Error::file(path, "has no scene"))?;

    check_expansion(path, &scene, doc.nodes().len())?;
    let mut out = Loaded {
        mesh: Mesh::default(),
        materials,
        cameras: Vec::new(),
        lights: Vec::new(),
        ignored,
    };
    let mut placed = std::collections::HashSet::new();
    let mut stack: Vec<(gltf::Node, Mat4, usize)> =
        scene.nodes().map(|n| (n, Mat4::IDENTITY, 0)).collect();
    stack.reverse();
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > MAX_NODE_DEPTH {
            return Err(Error::file(
                path,
                "node hierarchy is deeper than 256 levels (a cycle?)",
            ));
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if !world.is_finite() {
            return Err(Error::file(
                path,
                format!("node {} has a non-finite transform", node_name(&node)),
            ));
        }
        // The same mesh under the same world transform twice (a node reached along two
        // paths of a shared hierarchy) is the same surface twice: loaded once. Coincident
        // copies add nothing to an image and make the BVH build quadratic.
        let fresh = node
            .mesh()
            .is_some_and(|m| placed.insert((m.index(), world.to_cols_array().map(f32::to_bits))));
        if let Some(mesh) = node.mesh().filter(|_| fresh) {
            for (pi, prim) in mesh.primitives().enumerate() {
                let what = format!("mesh {:?} primitive {pi}", mesh.name().unwrap_or(""));
                let material = prim.material().index().map_or(0, |i| i + 1);
                load_primitive(
                    path,
                    &what,
                    &prim,
                    &buffers,
                    world,
                    material as u32,
                    texcoord_set[material],
                    &out.materials[material],
                    &mut out.mesh,
                )?;
            }
        }
        if let Some(cam) = node.camera()
            && let gltf::camera::Projection::Perspective(p) = cam.projection()
        {
            let yfov = p.yfov();
            if !(yfov.is_finite() && yfov > 0.0 && yfov < std::f32::consts::PI) {
                return Err(Error::file(
                    path,
                    format!(
                        "camera node {} has yfov {yfov}, outside (0, π)",
                        node_name(&node)
                    ),
                ));
            }
            // A camera's frame must be a rotation after removing scale: a zero or non-finite
            // scale leaves no direction to look in (a NaN camera renders black).
            let frame = glam::Mat3::from_mat4(world);
            let det = frame.determinant();
            if !(det.is_finite() && det.abs() > 1e-12) {
                return Err(Error::file(
                    path,
                    format!(
                        "camera node {} has a degenerate transform (its world matrix scales by {det}: a scale of 0?)",
                        node_name(&node)
                    ),
                ));
            }
            // A mirrored or sheared frame has no right, up and forward to render with: taking
            // its rotation part would silently turn or unmirror the view.
            let axes = [frame.x_axis, frame.y_axis, frame.z_axis].map(Vec3::normalize);
            let skew = [(0, 1), (0, 2), (1, 2)]
                .map(|(i, j)| axes[i].dot(axes[j]).abs())
                .into_iter()
                .fold(0.0f32, f32::max);
            if det < 0.0 || skew > 1e-4 {
                return Err(Error::file(
                    path,
                    format!(
                        "camera node {} is {} by its node transforms; a camera must be placed by a rotation, a translation and a scale along its own axes",
                        node_name(&node),
                        if det < 0.0 { "mirrored" } else { "sheared" }
                    ),
                ));
            }
            let aspect = p.aspect_ratio();
            if aspect.is_some_and(|a| !(a.is_finite() && a > 0.0)) {
                return Err(Error::file(
                    path,
                    format!(
                        "camera node {} has aspectRatio {}, not a number > 0",
                        node_name(&node),
                        aspect.unwrap_or_default()
                    ),
                ));
            }
            // An unnamed camera still needs a name: it names the view's files and its random
            // stream.
            let name = node
                .name()
                .or(cam.name())
                .map_or_else(|| format!("camera{}", node.index()), str::to_string);
            let (width, height) = size
                .for_aspect(aspect)
                .map_err(|e| Error::file(path, format!("camera node {}: {e}", node_name(&node))))?;
            let mut camera = Camera::from_node(name, world, yfov, width, height);
            camera.aspect_ratio = aspect;
            out.cameras.push(camera);
        }
        if let Some(light) = node.light() {
            out.lights.push(punctual_light(path, &node, &light, world)?);
            if let Some(range) = light.range() {
                out.ignored.push(Ignored {
                    what: format!("light {:?}", light.name().unwrap_or("")),
                    properties: vec![format!(
                        "range {range} m (a hint for real-time cut-offs: lightprobe's lights reach everywhere, as the extension's physical falloff says)"
                    )],
                });
            }
        }
        let mut children: Vec<_> = node.children().map(|c| (c, world, depth + 1)).collect();
        children.reverse();
        stack.extend(children);
    }
    if out.mesh.triangle_count() == 0 {
        return Err(Error::file(path, "has no triangles in its scene"));
    }
    if out.mesh.triangle_material.contains(&0) {
        // glTF's default material is metallic 1 and roughness 1: a rough metal, which the
        // Lambertian model renders as a white diffuse surface.
        out.ignored.insert(
            0,
            Ignored {
                what: "glTF's default material (primitives without one)".into(),
                properties: vec!["specular reflection (metallic 1, roughness 1)".into()],
            },
        );
    }
    Ok(out)
}

/// A `KHR_lights_punctual` light on `node` (world transform `world`) as lightprobe renders it:
/// a point light, or with a radius in the light's or the node's `extras` (`{"radius": r}`,
/// metres) a sphere of the same radiant intensity. Spot and directional lights are refused.
fn punctual_light(
    path: &Path,
    node: &gltf::Node,
    light: &gltf::khr_lights_punctual::Light,
    world: Mat4,
) -> Result<SphereLight> {
    use gltf::khr_lights_punctual::Kind;
    let what = format!(
        "light {:?} on node {}",
        light.name().unwrap_or(""),
        node_name(node)
    );
    match light.kind() {
        Kind::Point => {}
        Kind::Spot { .. } => {
            return Err(Error::file(
                path,
                format!(
                    "{what} is a spot light; lightprobe renders point and sphere lights only (make it a point light, or remove it and estimate the lighting instead)"
                ),
            ));
        }
        Kind::Directional => {
            return Err(Error::file(
                path,
                format!(
                    "{what} is a directional light; lightprobe renders point and sphere lights only (give a distant light as an envmap with render-reference --envmap, or remove it)"
                ),
            ));
        }
    }
    let color = Vec3::from(light.color());
    let cd = light.intensity();
    if !(color.is_finite() && color.min_element() >= 0.0 && cd.is_finite() && cd >= 0.0) {
        return Err(Error::file(
            path,
            format!("{what} has colour {color} and intensity {cd}: each must be finite and ≥ 0"),
        ));
    }
    let center = world.transform_point3(Vec3::ZERO);
    if !center.is_finite() {
        return Err(Error::file(
            path,
            format!("{what} has a non-finite position"),
        ));
    }
    let intensity = color * (cd / LUMENS_PER_WATT);
    if intensity.max_element() > crate::imageio::MAX_RADIANCE {
        return Err(Error::file(
            path,
            format!(
                "{what} has intensity {cd} cd: {} W/sr, beyond the 1e15 lightprobe renders",
                intensity.max_element()
            ),
        ));
    }
    let radius = match extras_radius(light.extras()).or_else(|| extras_radius(node.extras())) {
        None => 0.0,
        Some(Ok(r)) => r,
        Some(Err(got)) => {
            return Err(Error::file(
                path,
                format!("{what}: extras radius {got} is not a length ≥ 0 in metres"),
            ));
        }
    };
    if radius == 0.0 {
        return Ok(SphereLight::point(center, intensity));
    }
    let radiance = intensity / (std::f32::consts::PI * radius * radius);
    if !radiance.is_finite() || radiance.max_element() > crate::imageio::MAX_RADIANCE {
        return Err(Error::file(
            path,
            format!(
                "{what}: a sphere of radius {radius} m at that intensity has radiance {}, beyond the 1e15 lightprobe renders (give a larger radius)",
                radiance.max_element()
            ),
        ));
    }
    Ok(SphereLight {
        center,
        radius,
        radiance,
    })
}

/// `radius` from glTF `extras` (an object), if it has one: the value, or what it was instead
/// of a finite number ≥ 0.
fn extras_radius(extras: &gltf::json::Extras) -> Option<std::result::Result<f32, String>> {
    let raw = extras.as_ref()?;
    let value: serde_json::Value = serde_json::from_str(raw.get()).ok()?;
    let r = value.get("radius")?;
    Some(match r.as_f64() {
        Some(v) if (0.0..1e30).contains(&v) => Ok(v as f32),
        _ => Err(r.to_string()),
    })
}

/// What a glTF material has that the Lambertian model leaves out (empty when it has nothing):
/// lightprobe renders every surface diffuse, with the base colour as its albedo.
fn left_out_of(m: &gltf::Material) -> Vec<String> {
    let pbr = m.pbr_metallic_roughness();
    let mut out = Vec::new();
    let (metallic, roughness) = (pbr.metallic_factor(), pbr.roughness_factor());
    if metallic > 0.0 || roughness < 1.0 || pbr.metallic_roughness_texture().is_some() {
        out.push(format!(
            "specular reflection (metallic {metallic}, roughness {roughness}{})",
            if pbr.metallic_roughness_texture().is_some() {
                ", textured"
            } else {
                ""
            }
        ));
    }
    if m.emissive_factor() != [0.0; 3] || m.emissive_texture().is_some() {
        out.push(format!(
            "emission (emissive factor {:?}{})",
            m.emissive_factor(),
            if m.emissive_texture().is_some() {
                ", textured"
            } else {
                ""
            }
        ));
    }
    if m.alpha_mode() != gltf::material::AlphaMode::Opaque {
        out.push(format!(
            "transparency (alphaMode {:?}, base colour alpha {})",
            m.alpha_mode(),
            pbr.base_color_factor()[3]
        ));
    }
    if m.normal_texture().is_some() {
        out.push("normal map".into());
    }
    if m.occlusion_texture().is_some() {
        out.push("occlusion map (the path tracer computes occlusion itself)".into());
    }
    if let Some(ext) = m.extensions() {
        out.extend(ext.keys().map(|k| format!("extension {k}")));
    }
    out
}

/// Most node instances a scene may expand to (a node reached along two paths counts twice).
const MAX_INSTANCES: u64 = 1 << 24;

/// Memory a loaded triangle takes at most, with its BVH and while that is built: mesh
/// (three vertices of position, normal and texture coordinates, indices, material: 112
/// bytes), BVH leaves, nodes and the builder's working arrays.
pub const BYTES_PER_TRIANGLE: u64 = 400;

/// Counts the node instances and triangles `scene` expands to, without expanding it, and
/// refuses one that is too large for the memory budget: nodes may instance a mesh through a
/// shared hierarchy (a DAG of children), so a file of a few kilobytes can declare 2^40
/// triangles.
fn check_expansion(path: &Path, scene: &gltf::Scene, nodes: usize) -> Result<()> {
    // Per node: (instances, triangles) of its subtree, saturating; memoised, so shared
    // subtrees are counted once. The recursion is bounded by MAX_NODE_DEPTH (cycles).
    fn count(
        path: &Path,
        node: &gltf::Node,
        depth: usize,
        memo: &mut Vec<Option<(u64, u64)>>,
    ) -> Result<(u64, u64)> {
        if depth > MAX_NODE_DEPTH {
            return Err(Error::file(
                path,
                "node hierarchy is deeper than 256 levels (a cycle?)",
            ));
        }
        if let Some(known) = memo.get(node.index()).copied().flatten() {
            return Ok(known);
        }
        let mut instances = 1u64;
        // Per primitive: its triangles (from the index or position count) and the vertices
        // read for it (every attribute accessor's count: a sparse accessor without a buffer
        // view declares its count freely).
        let mut triangles = node.mesh().map_or(0, |m| {
            m.primitives()
                .map(|p| {
                    let vertices = p
                        .attributes()
                        .map(|(_, a)| a.count() as u64)
                        .max()
                        .unwrap_or(0);
                    let corners = p.indices().map_or(vertices, |a| a.count() as u64);
                    // A vertex (32 bytes) costs less than a triangle; count it as a third.
                    (corners / 3).saturating_add(vertices / 3)
                })
                .fold(0u64, u64::saturating_add)
        });
        for child in node.children() {
            let (i, t) = count(path, &child, depth + 1, memo)?;
            instances = instances.saturating_add(i);
            triangles = triangles.saturating_add(t);
        }
        if let Some(slot) = memo.get_mut(node.index()) {
            *slot = Some((instances, triangles));
        }
        Ok((instances, triangles))
    }
    let mut memo = vec![None; nodes];
    let (mut instances, mut triangles) = (0u64, 0u64);
    for node in scene.nodes() {
        let (i, t) = count(path, &node, 0, &mut memo)?;
        instances = instances.saturating_add(i);
        triangles = triangles.saturating_add(t);
    }
    if instances > MAX_INSTANCES {
        return Err(Error::file(
            path,
            format!(
                "its node hierarchy expands to {} node instances (nodes shared by several parents count once per parent); at most {MAX_INSTANCES} are loaded",
                big(instances)
            ),
        ));
    }
    if triangles > u32::MAX as u64 / 8 {
        return Err(Error::file(
            path,
            format!(
                "expands to {} triangles; at most {} are loaded",
                big(triangles),
                u32::MAX / 8
            ),
        ));
    }
    crate::memory::reserve(triangles.saturating_mul(BYTES_PER_TRIANGLE), || {
        format!(
            "{}: loading its {} triangles and their BVH",
            path.display(),
            big(triangles)
        )
    })
}

/// A count for messages: exact below a million, else like 1.1e12 (saturated counts are
/// "at least").
fn big(n: u64) -> String {
    if n == u64::MAX {
        "more than 1.8e19".to_string()
    } else if n < 1_000_000 {
        n.to_string()
    } else {
        format!("{n:.1e}")
    }
}

fn node_name(node: &gltf::Node) -> String {
    format!("{:?} (#{})", node.name().unwrap_or(""), node.index())
}

#[allow(clippy::too_many_arguments)]
fn load_primitive(
    path: &Path,
    what: &str,
    prim: &gltf::Primitive,
    buffers: &[gltf::buffer::Data],
    world: Mat4,
    material: u32,
    texcoord_set: u32,
    mat: &Material,
    mesh: &mut Mesh,
) -> Result<()> {
    if prim.mode() != Mode::Triangles {
        return Err(Error::file(
            path,
            format!(
                "{what} has mode {:?}; only triangle lists are supported",
                prim.mode()
            ),
        ));
    }
    check_accessor_types(path, what, prim, texcoord_set)?;
    let accessors = [
        prim.get(&gltf::Semantic::Positions),
        prim.get(&gltf::Semantic::Normals),
        prim.get(&gltf::Semantic::TexCoords(texcoord_set)),
        prim.get(&gltf::Semantic::Colors(0)),
        prim.indices(),
    ];
    for a in accessors.iter().flatten() {
        check_sparse(path, what, a, buffers)?;
    }
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let no_positions = || {
        Error::file(
            path,
            format!(
                "{what} has no readable POSITION attribute (missing, or its buffer view is missing or out of range)"
            ),
        )
    };
    let non_finite = || Error::file(path, format!("{what} has non-finite vertex positions"));
    let to_world = |p: Vec3| world.transform_point3(p);
    let normal_from_local = Mat3::from_mat4(world).inverse().transpose();
    let normal_to_world = |nl: Vec3| {
        let nw = normal_from_local * nl;
        if nw.is_finite() {
            nw.normalize_or_zero()
        } else {
            Vec3::ZERO
        }
    };
    let Some(normals) = reader.read_normals() else {
        // Flat shading: every triangle gets its own corners, so the shared vertices are read
        // first (the rare case: scans and exporters write normals).
        let positions: Vec<Vec3> = reader
            .read_positions()
            .ok_or_else(no_positions)?
            .map(Vec3::from)
            .collect();
        check_count(
            path,
            "POSITION",
            prim.get(&gltf::Semantic::Positions),
            positions.len(),
        )?;
        if positions.iter().any(|p| !p.is_finite()) {
            return Err(non_finite());
        }
        let n = positions.len();
        let indices: Vec<u32> = match reader.read_indices() {
            Some(ix) => ix.into_u32().collect(),
            None => (0..n as u32).collect(),
        };
        check_indices(path, what, prim, n, indices.len(), indices.iter().copied())?;
        let (mut uvs, mut colors) = (Vec::new(), Vec::new());
        let has_uvs = read_uvs(path, what, &reader, (texcoord_set, mat), n, &mut uvs)?;
        let has_colors = read_colors(path, what, &reader, n, &mut colors)?;
        let world_positions: Vec<Vec3> = positions.into_iter().map(to_world).collect();
        mesh.push_colored(
            &world_positions,
            None,
            has_uvs.then_some(&uvs[..]),
            has_colors.then_some(&colors[..]),
            &indices,
            material,
        );
        return Ok(());
    };
    // Smooth shading: each attribute goes straight from the buffer into the mesh, checked
    // there (a scan's attributes are tens of MB each: no copy of them is made on the way).
    let base = mesh.positions.len();
    mesh.positions.extend(
        reader
            .read_positions()
            .ok_or_else(no_positions)?
            .map(Vec3::from),
    );
    let n = mesh.positions.len() - base;
    check_count(path, "POSITION", prim.get(&gltf::Semantic::Positions), n)?;
    let placed = &mut mesh.positions[base..];
    if placed.iter().any(|p| !p.is_finite()) {
        return Err(non_finite());
    }
    placed.iter_mut().for_each(|p| *p = to_world(*p));
    mesh.normals
        .extend(normals.map(|nl| normal_to_world(Vec3::from(nl))));
    if mesh.normals.len() - base != n {
        return Err(Error::file(
            path,
            format!(
                "{what} has {} normals for {n} vertices",
                mesh.normals.len() - base
            ),
        ));
    }
    let first_triangle = mesh.triangles.len();
    let count = match reader.read_indices() {
        Some(ix) => {
            let mut count = 0;
            let mut corners = ix.into_u32().inspect(|_| count += 1);
            while let (Some(a), Some(b), Some(c)) = (corners.next(), corners.next(), corners.next())
            {
                mesh.triangles.push([a, b, c]);
            }
            // A trailing partial triangle's indices were counted and are refused below.
            count
        }
        None => {
            mesh.triangles
                .extend((0..n as u32 / 3).map(|t| [3 * t, 3 * t + 1, 3 * t + 2]));
            n
        }
    };
    let corners = mesh.triangles[first_triangle..].iter().flatten().copied();
    check_indices(path, what, prim, n, count, corners)?;
    let offset = base as u32;
    mesh.triangles[first_triangle..]
        .iter_mut()
        .flatten()
        .for_each(|i| *i += offset);
    let triangles = mesh.triangles.len() - first_triangle;
    mesh.triangle_material
        .extend(std::iter::repeat_n(material, triangles));
    if !read_uvs(path, what, &reader, (texcoord_set, mat), n, &mut mesh.uvs)? {
        mesh.uvs.extend(std::iter::repeat_n(Vec2::ZERO, n));
    }
    if !read_colors(path, what, &reader, n, &mut mesh.colors)? {
        mesh.colors.extend(std::iter::repeat_n(Vec3::ONE, n));
    }
    Ok(())
}

/// Checks that `accessor` (named `what` in the error) holds the `got` elements read from it:
/// the reader stops at the end of a buffer view, and an accessor that claims more is broken.
fn check_count(
    path: &Path,
    what: &str,
    accessor: Option<gltf::Accessor>,
    got: usize,
) -> Result<()> {
    match accessor {
        Some(a) if a.count() != got => Err(Error::file(
            path,
            format!(
                "{what} accessor #{} claims {} elements but its buffer view holds {got}",
                a.index(),
                a.count()
            ),
        )),
        _ => Ok(()),
    }
}

/// Checks a primitive's `count` indices (`corners`, those it read) against its `n`
/// vertices: as many as its accessor claims, whole triangles, each naming a vertex.
fn check_indices(
    path: &Path,
    what: &str,
    prim: &gltf::Primitive,
    n: usize,
    count: usize,
    mut corners: impl Iterator<Item = u32>,
) -> Result<()> {
    check_count(path, "index", prim.indices(), count)?;
    if !count.is_multiple_of(3) {
        return Err(Error::file(
            path,
            format!("{what} has {count} indices, not a multiple of 3"),
        ));
    }
    if let Some(bad) = corners.find(|&i| i as usize >= n) {
        return Err(Error::file(
            path,
            format!("{what} has index {bad} but only {n} vertices"),
        ));
    }
    Ok(())
}

/// Appends the primitive's texture coordinates of set `texcoord_set` to `into`, checked to be
/// `n`; false if it has none (an error if `mat` is textured).
fn read_uvs<'a, 's, F>(
    path: &Path,
    what: &str,
    reader: &gltf::mesh::Reader<'a, 's, F>,
    (texcoord_set, mat): (u32, &Material),
    n: usize,
    into: &mut Vec<Vec2>,
) -> Result<bool>
where
    F: Clone + Fn(gltf::Buffer<'a>) -> Option<&'s [u8]>,
{
    let Some(uvs) = reader.read_tex_coords(texcoord_set) else {
        if matches!(mat.albedo, Albedo::Texture { .. }) {
            return Err(Error::file(
                path,
                format!(
                    "{what} uses textured material {:?} but has no TEXCOORD_{texcoord_set}",
                    mat.name
                ),
            ));
        }
        return Ok(false);
    };
    let start = into.len();
    into.extend(uvs.into_f32().map(Vec2::from));
    if into.len() - start != n {
        return Err(Error::file(
            path,
            format!(
                "{what} has {} texture coordinates for {n} vertices",
                into.len() - start
            ),
        ));
    }
    Ok(true)
}

/// Appends the primitive's `COLOR_0` to `into`, checked to be `n` finite values and clamped to
/// [0, 1]; false if it has none. COLOR_0 is linear RGB(A); alpha plays no part in a Lambertian
/// albedo.
fn read_colors<'a, 's, F>(
    path: &Path,
    what: &str,
    reader: &gltf::mesh::Reader<'a, 's, F>,
    n: usize,
    into: &mut Vec<Vec3>,
) -> Result<bool>
where
    F: Clone + Fn(gltf::Buffer<'a>) -> Option<&'s [u8]>,
{
    let Some(colors) = reader.read_colors(0) else {
        return Ok(false);
    };
    let start = into.len();
    into.extend(colors.into_rgb_f32().map(Vec3::from));
    let read = &mut into[start..];
    if read.len() != n {
        return Err(Error::file(
            path,
            format!("{what} has {} COLOR_0 values for {n} vertices", read.len()),
        ));
    }
    if let Some(bad) = read.iter().find(|v| !v.is_finite()) {
        return Err(Error::file(
            path,
            format!("{what} has a non-finite COLOR_0 value {bad}"),
        ));
    }
    read.iter_mut()
        .for_each(|v| *v = v.clamp(Vec3::ZERO, Vec3::ONE));
    Ok(true)
}

/// Checks that each attribute's accessor has the type the spec requires before reading it
/// (the gltf crate's reader assumes it: found by fuzzing).
/// Checks a sparse accessor's indices: each must name an element of the accessor (the
/// gltf crate's reader does not check, and substitutes nothing for one past the end).
fn check_sparse(
    path: &Path,
    what: &str,
    accessor: &gltf::Accessor,
    buffers: &[gltf::buffer::Data],
) -> Result<()> {
    let Some(sparse) = accessor.sparse() else {
        return Ok(());
    };
    let indices = sparse.indices();
    let view = indices.view();
    let size = match indices.index_type() {
        gltf::accessor::sparse::IndexType::U8 => 1,
        gltf::accessor::sparse::IndexType::U16 => 2,
        gltf::accessor::sparse::IndexType::U32 => 4,
    };
    let fail = |why: String| {
        Error::file(
            path,
            format!("{what}: sparse accessor #{} {why}", accessor.index()),
        )
    };
    let start = view.offset() + indices.offset();
    let end = sparse
        .count()
        .checked_mul(size)
        .and_then(|n| n.checked_add(start))
        .filter(|&end| end <= view.offset() + view.length())
        .ok_or_else(|| fail("has more indices than its buffer view holds".into()))?;
    let bytes = buffers
        .get(view.buffer().index())
        .and_then(|b| b.0.get(start..end))
        .ok_or_else(|| fail("has indices past the end of its buffer".into()))?;
    for (k, chunk) in bytes.chunks_exact(size).enumerate() {
        let mut word = [0u8; 4];
        word[..size].copy_from_slice(chunk);
        let i = u32::from_le_bytes(word) as usize;
        if i >= accessor.count() {
            return Err(fail(format!(
                "substitutes element {i} (index {k}), but the accessor has {} elements",
                accessor.count()
            )));
        }
    }
    Ok(())
}

fn check_accessor_types(
    path: &Path,
    what: &str,
    prim: &gltf::Primitive,
    texcoord_set: u32,
) -> Result<()> {
    use gltf::accessor::{DataType as D, Dimensions as Dim};
    let check = |name: &str,
                 a: Option<gltf::Accessor>,
                 dims: Dim,
                 ok: &dyn Fn(D, bool) -> bool|
     -> Result<()> {
        match a {
            Some(a) if a.dimensions() != dims || !ok(a.data_type(), a.normalized()) => {
                Err(Error::file(
                    path,
                    format!(
                        "{what}: {name} accessor #{} is {:?} {:?}, not a valid {name}",
                        a.index(),
                        a.dimensions(),
                        a.data_type()
                    ),
                ))
            }
            _ => Ok(()),
        }
    };
    check(
        "POSITION",
        prim.get(&gltf::Semantic::Positions),
        Dim::Vec3,
        &|d, _| d == D::F32,
    )?;
    check(
        "NORMAL",
        prim.get(&gltf::Semantic::Normals),
        Dim::Vec3,
        &|d, _| d == D::F32,
    )?;
    check(
        "TEXCOORD",
        prim.get(&gltf::Semantic::TexCoords(texcoord_set)),
        Dim::Vec2,
        &|d, n| d == D::F32 || (n && matches!(d, D::U8 | D::U16)),
    )?;
    // COLOR_0: VEC3 or VEC4 of floats or normalised unsigned bytes or shorts.
    if let Some(a) = prim.get(&gltf::Semantic::Colors(0)) {
        let dims_ok = matches!(a.dimensions(), Dim::Vec3 | Dim::Vec4);
        let d = a.data_type();
        let type_ok = d == D::F32 || (a.normalized() && matches!(d, D::U8 | D::U16));
        if !(dims_ok && type_ok) {
            return Err(Error::file(
                path,
                format!(
                    "{what}: COLOR_0 accessor #{} is {:?} {:?}, not a valid COLOR_0",
                    a.index(),
                    a.dimensions(),
                    d
                ),
            ));
        }
    }
    check("index", prim.indices(), Dim::Scalar, &|d, n| {
        !n && matches!(d, D::U8 | D::U16 | D::U32)
    })
}

/// Converts a decoded glTF image to a linear texture (baseColor images are sRGB-encoded).
fn decode_image(img: &gltf::image::Data) -> Texture {
    use gltf::image::Format;
    let (w, h) = (img.width, img.height);
    let px = &img.pixels;
    match img.format {
        Format::R8 => Texture::from_srgb8(w, h, 1, px),
        Format::R8G8 => Texture::from_srgb8(w, h, 2, px),
        Format::R8G8B8 => Texture::from_srgb8(w, h, 3, px),
        Format::R8G8B8A8 => Texture::from_srgb8(w, h, 4, px),
        // 16-bit and float images: reduce to 8-bit sRGB first (precision is ample for albedo).
        other => {
            let (channels, bytes_per) = match other {
                Format::R16 => (1, 2),
                Format::R16G16 => (2, 2),
                Format::R16G16B16 => (3, 2),
                Format::R16G16B16A16 => (4, 2),
                Format::R32G32B32FLOAT => (3, 4),
                _ => (4, 4),
            };
            let bytes: Vec<u8> = px
                .chunks_exact(bytes_per)
                .map(|c| match bytes_per {
                    2 => (u16::from_le_bytes([c[0], c[1]]) >> 8) as u8,
                    _ => (f32::from_le_bytes([c[0], c[1], c[2], c[3]]).clamp(0.0, 1.0) * 255.0)
                        .round() as u8,
                })
                .collect();
            Texture::from_srgb8(w, h, channels, &bytes)
        }
    }
}
