//! The scene written back as glTF with an estimate in it, for the user's own tools: sphere
//! lights as `KHR_lights_punctual` point lights (colour and candela, the radius in the light's
//! `extras`), an envmap named in the scene's `extras` with its convention (glTF has no
//! standard environment light). The source's own lights are dropped (they were the reference
//! illumination); all else is kept as the source has it: a GLB's binary chunk byte for byte, a
//! `.gltf`'s buffers and images copied beside the written file.

pub mod blender;
pub mod mitsuba;

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::SphereLight;
use super::gltf::{LUMENS_PER_WATT, percent_decode};
use crate::error::{Error, Result};

/// The albedo a textured material has, as lightprobe looks it up: the texture times the
/// factor, clamped to [0, 1] (written as a linear float EXR for other renderers).
fn albedo_image(texture: &super::Texture, factor: glam::Vec3) -> crate::imageio::Image {
    crate::imageio::Image {
        width: texture.width,
        height: texture.height,
        rgb: texture
            .texels
            .iter()
            .map(|t| (*t * factor).clamp(glam::Vec3::ZERO, glam::Vec3::ONE))
            .collect(),
        alpha: None,
    }
}

/// The file a fitted texture of material `m` (the scene's index) named `name` is written to,
/// relative to the glTF that refers to it.
pub fn albedo_texture_file(m: usize, name: &str) -> String {
    let safe: String = name
        .chars()
        .take(40)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("albedo_textures/{m}_{safe}.png")
}

/// An envmap written beside the glTF, named in its scene's `extras.lightprobe_envmap`.
#[derive(Debug, Clone)]
pub struct EnvmapNote {
    /// The lat-long EXR, relative to the written glTF.
    pub exr: String,
    /// The ring envmap (`envmap.ron`), relative to the written glTF.
    pub ron: String,
    pub rings: u32,
}

/// How the lat-long EXR beside an export is laid out (what `extras` says of it).
const LATLONG_CONVENTION: &str = "lat-long, linear RGB radiance, Mitsuba 3 envmap convention in glTF's frame (+Y up): column u = atan2(x, -z) / 2pi, the first and last rows are the poles; load it as Mitsuba's `envmap` emitter, or in Blender with `lightprobe export-envmap --target blender`";

/// Per light (or none at all), a radius the images do not identify: its 95% interval factor
/// (×/÷; infinite where they hold no measure of it). The exports keep the fitted radius and
/// say that it is not identified, with the interval.
pub type RadiusDoubts<'a> = &'a [Option<f64>];

/// The doubt over light `k`'s radius, if any.
fn doubt(doubts: RadiusDoubts, k: usize) -> Option<f64> {
    doubts.get(k).copied().flatten()
}

/// Widest 95% factor an export writes as an interval: beyond it the images say next to
/// nothing of the radius, and only that it is not identified is written.
pub const WIDEST_STATED_DOUBT: f64 = 100.0;

/// The 95% interval (metres) an export states for radius `r` with 95% factor `factor`.
fn stated_interval(r: f32, factor: f64) -> Option<[f64; 2]> {
    (factor <= WIDEST_STATED_DOUBT).then(|| [r as f64 / factor, r as f64 * factor])
}

/// A comment's words on a radius `r` (metres) the images do not identify, with the 95% factor.
pub fn radius_doubt_words(r: f32, factor: f64) -> String {
    if factor <= WIDEST_STATED_DOUBT {
        format!(
            "radius not identified by the images: any from {:.4} to {:.4} m (95%) fits them; {r} is the fit's value",
            r as f64 / factor,
            r as f64 * factor
        )
    } else if factor.is_finite() {
        format!(
            "radius not identified by the images, which hold next to no measure of it (95% interval ×/÷ {factor:.3e}); {r} is the fit's value"
        )
    } else {
        format!(
            "radius not identified by the images, which hold no measure of it; {r} is the fit's value"
        )
    }
}

/// Writes `source` (a `.glb` or `.gltf`) into `dir` as `scene.glb` or `scene.gltf` (with
/// copies of the files it refers to) with `lights` and `envmap` in it, and with `albedo`
/// (the scene's materials as given, then fitted) as its materials' baseColorFactor where the
/// fit changed them ([`put_albedo`]). Returns the path written and what the file could not
/// hold.
pub fn write_with_lights(
    source: &Path,
    dir: &Path,
    lights: &[SphereLight],
    doubts: RadiusDoubts,
    envmap: Option<&EnvmapNote>,
    albedo: Option<(&[super::Material], &[super::Material])>,
) -> Result<(PathBuf, Vec<String>)> {
    let bytes = crate::memory::read_input(source)?;
    let bad = |why: String| Error::file(source, format!("cannot be written back: {why}"));
    let glb_source = bytes.starts_with(b"glTF");
    let (json, bin) = if glb_source {
        glb_chunks(&bytes).map_err(bad)?
    } else {
        (&bytes[..], &[][..])
    };
    let mut doc: Value = serde_json::from_slice(json).map_err(|e| bad(e.to_string()))?;
    put_lights(&mut doc, lights, doubts, envmap).map_err(bad)?;
    let mut notes = match albedo {
        Some((given, fitted)) => put_albedo(&mut doc, given, fitted).map_err(bad)?,
        None => Vec::new(),
    };
    // Files the source refers to go beside the copy (a GLB may refer to some too). The loader
    // refused URIs that leave the source's folder, so they stay inside `dir`.
    let from = source.parent().unwrap_or(Path::new(""));
    for uri in external_uris(&doc) {
        let rel = percent_decode(&uri);
        let target = dir.join(&rel);
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        let data = crate::memory::read_input(&from.join(&rel))?;
        crate::imageio::write_bytes(&target, &data)?;
    }
    if let Some((given, fitted)) = albedo {
        notes.extend(put_textures(&mut doc, dir, given, fitted)?);
    }
    let out = dir.join(written_name(source));
    if glb_source {
        crate::imageio::write_bytes(&out, &glb(&doc, bin))?;
    } else {
        let text = serde_json::to_string_pretty(&doc).map_err(|e| bad(e.to_string()))?;
        crate::imageio::write_bytes(&out, text.as_bytes())?;
    }
    Ok((out, notes))
}

/// Sets the baseColorFactor (RGB; alpha kept) of each glTF material whose albedo the fit
/// changed (`fitted` against `given`, the scene's materials) to the fitted albedo: the
/// constant, or the texture's factor. `materials[0]` is glTF's default material, which the
/// file cannot name; `materials[i]` is the file's material i − 1. Returns what the file could
/// not take: glTF's factors end at 1, so a texture's factor above 1 is written as 1; an
/// albedo the sidecar gave in place of the file's (a texture for a constant or the other
/// way) is not written.
fn put_albedo(
    doc: &mut Value,
    given: &[super::Material],
    materials: &[super::Material],
) -> std::result::Result<Vec<String>, String> {
    let mut notes = Vec::new();
    let factor_of = |m: &super::Material| match &m.albedo {
        super::Albedo::Constant(c) => (*c, false),
        super::Albedo::Texture { factor, .. } => (*factor, true),
    };
    let lists = lists_ok(doc);
    let list = doc.get_mut("materials").and_then(Value::as_array_mut);
    let list = match list {
        Some(l) => l,
        None if materials.len() <= 1 => return Ok(notes),
        None => return Err("it has no materials to write the albedo into".into()),
    };
    if list.len() + 1 != materials.len() {
        return Err(format!(
            "it has {} materials, the fitted albedo {}",
            list.len(),
            materials.len() - 1
        ));
    }
    for ((m, g), gm) in materials[1..].iter().zip(&given[1..]).zip(list.iter_mut()) {
        let (factor, textured) = factor_of(m);
        if factor == factor_of(g).0 || (texture_changed(g, m) && takes_texture(gm, lists)) {
            // A corrected texture carries its factor ([`put_textures`]).
            continue;
        }
        let file_textured = gm
            .pointer("/pbrMetallicRoughness/baseColorTexture")
            .is_some();
        if textured != file_textured {
            notes.push(format!(
                "material {:?}: its albedo came from the sidecar, not the glTF, so the fitted \
                 one is in report.json only",
                m.name
            ));
            continue;
        }
        if factor.max_element() > 1.0 {
            notes.push(format!(
                "material {:?}: its fitted texture factor {:.3} {:.3} {:.3} is above glTF's 1, \
                 written as 1 (the texture itself would have to be brightened)",
                m.name, factor.x, factor.y, factor.z
            ));
        }
        let f = factor.clamp(glam::Vec3::ZERO, glam::Vec3::ONE);
        let gm = gm.as_object_mut().ok_or("a material is not an object")?;
        let pbr = gm
            .entry("pbrMetallicRoughness")
            .or_insert_with(|| json!({}));
        let pbr = pbr
            .as_object_mut()
            .ok_or("a material's pbrMetallicRoughness is not an object")?;
        let alpha = pbr
            .get("baseColorFactor")
            .and_then(|v| v.get(3))
            .and_then(Value::as_f64)
            .unwrap_or(1.0);
        pbr.insert(
            "baseColorFactor".into(),
            json!([f.x as f64, f.y as f64, f.z as f64, alpha]),
        );
    }
    Ok(notes)
}

/// Whether the glTF's images and textures are lists (or absent), as [`put_textures`] needs.
fn lists_ok(doc: &Value) -> bool {
    ["images", "textures"]
        .iter()
        .all(|k| doc.get(k).is_none_or(Value::is_array))
}

/// Whether [`put_textures`] points glTF material `gm` at a corrected texture: it has a
/// baseColorTexture, no alpha of its own (alphaMode OPAQUE, the default), and the file's
/// images and textures are lists (`lists`).
fn takes_texture(gm: &Value, lists: bool) -> bool {
    lists
        && gm
            .pointer("/pbrMetallicRoughness/baseColorTexture")
            .is_some()
        && gm
            .get("alphaMode")
            .and_then(Value::as_str)
            .is_none_or(|a| a == "OPAQUE")
}

/// Whether `fitted`'s texture is not `given`'s (`--fit-albedo texels` corrected it).
fn texture_changed(given: &super::Material, fitted: &super::Material) -> bool {
    use super::Albedo;
    match (&given.albedo, &fitted.albedo) {
        (Albedo::Texture { texture: was, .. }, Albedo::Texture { texture, .. }) => {
            !std::sync::Arc::ptr_eq(was, texture)
        }
        _ => false,
    }
}

/// Writes each texture the fit corrected ([`texture_changed`]) into `dir`
/// ([`albedo_texture_file`]: 8-bit sRGB PNG of texel × factor, clamped to [0, 1] as lightprobe
/// renders it) and points the glTF material's baseColorTexture at it (a new image and texture,
/// the old texture's sampler and the material's texCoord kept), its baseColorFactor RGB set
/// to 1 (alpha kept). Returns what the file could not take: a material the glTF gives no
/// texture (its texture came from the sidecar) and one whose alpha its texture holds (the PNG
/// has none) keep the file's; the corrected texture is written all the same.
fn put_textures(
    doc: &mut Value,
    dir: &Path,
    given: &[super::Material],
    fitted: &[super::Material],
) -> Result<Vec<String>> {
    let mut notes = Vec::new();
    for (m, (f, g)) in fitted.iter().zip(given).enumerate() {
        if !texture_changed(g, f) {
            continue;
        }
        let super::Albedo::Texture { texture, factor } = &f.albedo else {
            continue;
        };
        let file = albedo_texture_file(m, &f.name);
        let path = dir.join(&file);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        crate::imageio::write_png(&path, &albedo_image(texture, *factor), 1.0)?;
        // materials[0] is glTF's default material, which has no texture in the file.
        let Some(slot) = m.checked_sub(1) else {
            continue;
        };
        let base = format!("/materials/{slot}/pbrMetallicRoughness");
        let lists = lists_ok(doc);
        let material = doc.pointer(&format!("/materials/{slot}")).cloned();
        if !material.as_ref().is_some_and(|gm| takes_texture(gm, lists)) {
            let why = match material
                .as_ref()
                .and_then(|gm| gm.get("alphaMode"))
                .and_then(Value::as_str)
            {
                _ if material
                    .as_ref()
                    .and_then(|gm| gm.pointer("/pbrMetallicRoughness/baseColorTexture"))
                    .is_none() =>
                {
                    "its texture came from the sidecar, not the glTF".to_string()
                }
                Some(a) if a != "OPAQUE" => format!(
                    "its alpha ({a}) lives in its texture, which lightprobe reads without alpha"
                ),
                _ => "the glTF's images or textures are not lists".to_string(),
            };
            notes.push(format!(
                "material {:?}: {why}; the glTF keeps its own texture (with the fitted factor \
                 where it has one), the corrected texture is {file}",
                f.name
            ));
            continue;
        }
        let sampler = doc
            .pointer(&format!("{base}/baseColorTexture/index"))
            .and_then(Value::as_u64)
            .and_then(|t| doc.pointer(&format!("/textures/{t}/sampler")).cloned());
        let push = |doc: &mut Value, key: &str, item: Value| -> Option<usize> {
            let list = doc
                .as_object_mut()?
                .entry(key)
                .or_insert_with(|| json!([]))
                .as_array_mut()?;
            list.push(item);
            Some(list.len() - 1)
        };
        let not_lists = || {
            format!(
                "material {:?}: the glTF's images or textures are not lists; the corrected \
                 texture is {file}, which the glTF does not use",
                f.name
            )
        };
        let Some(image) = push(
            doc,
            "images",
            json!({ "uri": file, "mimeType": "image/png" }),
        ) else {
            notes.push(not_lists());
            continue;
        };
        let mut item = json!({ "source": image, "name": format!("lightprobe {file}") });
        if let Some(s) = sampler {
            item["sampler"] = s;
        }
        let Some(index) = push(doc, "textures", item) else {
            notes.push(not_lists());
            continue;
        };
        if let Some(i) = doc.pointer_mut(&format!("{base}/baseColorTexture/index")) {
            *i = json!(index);
        }
        if let Some(pbr) = doc.pointer_mut(&base).and_then(Value::as_object_mut) {
            let alpha = pbr
                .get("baseColorFactor")
                .and_then(|v| v.get(3))
                .and_then(Value::as_f64)
                .unwrap_or(1.0);
            pbr.insert("baseColorFactor".into(), json!([1.0, 1.0, 1.0, alpha]));
        }
    }
    Ok(notes)
}

/// The name [`write_with_lights`] gives the copy of `source`: `scene.glb` for binary glTF,
/// `scene.gltf` for JSON (as the file's first bytes say; unreadable: by its extension).
pub fn written_name(source: &Path) -> &'static str {
    let mut head = [0u8; 4];
    let glb = match std::fs::File::open(source)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
    {
        Ok(()) => &head == b"glTF",
        Err(_) => source
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("glb")),
    };
    if glb { "scene.glb" } else { "scene.gltf" }
}

/// The JSON and (if any) binary chunk of a GLB.
fn glb_chunks(bytes: &[u8]) -> std::result::Result<(&[u8], &[u8]), String> {
    let word = |at: usize| -> std::result::Result<usize, String> {
        bytes
            .get(at..at + 4)
            .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]) as usize)
            .ok_or_else(|| "truncated GLB".to_string())
    };
    let json_len = word(12)?;
    if bytes.get(16..20) != Some(b"JSON") {
        return Err("the GLB's first chunk is not JSON".into());
    }
    let json = bytes.get(20..20 + json_len).ok_or("truncated GLB")?;
    let at = 20 + json_len;
    if at >= bytes.len() {
        return Ok((json, &[]));
    }
    let bin_len = word(at)?;
    let bin = bytes.get(at + 8..at + 8 + bin_len).ok_or("truncated GLB")?;
    Ok((json, bin))
}

/// A GLB of `doc` and the binary chunk `bin` (empty: none).
fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
    let mut json = doc.to_string().into_bytes();
    json.resize(json.len().next_multiple_of(4), b' ');
    let bin_padded = bin.len().next_multiple_of(4);
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin_padded };
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&json);
    if !bin.is_empty() {
        out.extend((bin_padded as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(bin);
        out.resize(total, 0);
    }
    out
}

/// The relative URIs of `doc`'s buffers and images (data URIs are inside the file).
fn external_uris(doc: &Value) -> Vec<String> {
    ["buffers", "images"]
        .iter()
        .filter_map(|k| doc.get(k)?.as_array())
        .flatten()
        .filter_map(|item| item.get("uri")?.as_str())
        .filter(|u| !u.starts_with("data:"))
        .map(str::to_string)
        .collect()
}

/// A USD stage (`.usda`, +Y up, metres, as glTF) of the lights: each sphere light a
/// `SphereLight` at its centre (`inputs:radius`; `inputs:color` × `inputs:intensity` = its
/// radiance, `normalize` off, exposure 0), and with `dome` (the lat-long EXR in OpenEXR's
/// convention, relative to the stage) a `DomeLight` of intensity 1.
pub fn usda(lights: &[SphereLight], doubts: RadiusDoubts, dome: Option<&str>) -> String {
    let mut s = String::from(
        "#usda 1.0\n(\n    doc = \"Lights estimated by lightprobe: linear RGB radiance, W/(sr m^2); SphereLight color x intensity is the sphere's radiance (normalize off)\"\n    metersPerUnit = 1\n    upAxis = \"Y\"\n    defaultPrim = \"Lights\"\n)\n\ndef Xform \"Lights\"\n{\n",
    );
    if let Some(file) = dome {
        s += &format!(
            "    def DomeLight \"Environment\"\n    {{\n        asset inputs:texture:file = @{file}@\n        token inputs:texture:format = \"latlong\"\n        float inputs:intensity = 1\n        float inputs:exposure = 0\n        color3f inputs:color = (1, 1, 1)\n    }}\n"
        );
    }
    for (k, l) in lights.iter().enumerate() {
        let peak = l.radiance.max_element().max(0.0);
        let c = if peak > 0.0 {
            l.radiance / peak
        } else {
            glam::Vec3::ONE
        };
        // Unidentified: a comment, and custom attributes a pipeline can read.
        let (note, attributes) = match doubt(doubts, k) {
            Some(f) => (
                format!("    # {}\n", radius_doubt_words(l.radius, f)),
                match stated_interval(l.radius, f) {
                    Some([lo, hi]) => format!(
                        "        custom bool lightprobe:radiusIdentified = 0\n        custom float2 lightprobe:radius95 = ({lo}, {hi})\n"
                    ),
                    None => "        custom bool lightprobe:radiusIdentified = 0\n".to_string(),
                },
            ),
            None => (String::new(), String::new()),
        };
        s += &format!(
            "{note}    def SphereLight \"Light{k}\"\n    {{\n        float inputs:radius = {}\n        float inputs:intensity = {peak}\n        float inputs:exposure = 0\n        color3f inputs:color = ({}, {}, {})\n        bool inputs:normalize = 0\n{attributes}        double3 xformOp:translate = ({}, {}, {})\n        uniform token[] xformOpOrder = [\"xformOp:translate\"]\n    }}\n",
            l.radius, c.x, c.y, c.z, l.center.x, l.center.y, l.center.z
        );
    }
    s + "}\n"
}

/// A sphere light as a KHR_lights_punctual point light: colour = intensity over its largest
/// channel, `intensity` = that channel × 683 candela, the radius in `extras` (with
/// `radius_identified: false` and its 95% interval where the images do not identify it).
pub fn punctual_light(k: usize, l: &SphereLight, doubt: Option<f64>) -> Value {
    let i = l.intensity();
    let peak = i.max_element();
    let color = if peak > 0.0 {
        i / peak
    } else {
        glam::Vec3::ONE
    };
    json!({
        "name": format!("lightprobe_{k}"),
        "type": "point",
        "color": color.to_array(),
        "intensity": peak.max(0.0) * LUMENS_PER_WATT,
        "extras": match doubt.map(|f| stated_interval(l.radius, f)) {
            None => json!({ "radius": l.radius }),
            Some(Some(interval)) => json!({
                "radius": l.radius,
                "radius_identified": false,
                "radius_95_interval": interval,
            }),
            Some(None) => json!({ "radius": l.radius, "radius_identified": false }),
        },
    })
}

/// Replaces `doc`'s lights with `lights` (new root nodes of its default scene) and names
/// `envmap` in that scene's `extras`.
fn put_lights(
    doc: &mut Value,
    lights: &[SphereLight],
    doubts: RadiusDoubts,
    envmap: Option<&EnvmapNote>,
) -> std::result::Result<(), String> {
    const EXT: &str = "KHR_lights_punctual";
    let root = doc.as_object_mut().ok_or("its JSON is not an object")?;
    // The source's lights were the reference illumination: unhooked from their nodes.
    if let Some(nodes) = root.get_mut("nodes").and_then(Value::as_array_mut) {
        for n in nodes {
            if let Some(ext) = n.get_mut("extensions").and_then(Value::as_object_mut) {
                ext.remove(EXT);
            }
        }
    }
    let scene = root.get("scene").and_then(Value::as_u64).unwrap_or(0) as usize;
    let mut node_ids = Vec::new();
    if !lights.is_empty() {
        let used = root.entry("extensionsUsed").or_insert_with(|| json!([]));
        if let Some(used) = used.as_array_mut()
            && !used.iter().any(|u| u == EXT)
        {
            used.push(json!(EXT));
        }
        let ext = root.entry("extensions").or_insert_with(|| json!({}));
        let ext = ext
            .as_object_mut()
            .ok_or("its extensions are not an object")?;
        ext.insert(
            EXT.into(),
            json!({ "lights": lights.iter().enumerate().map(|(k, l)| punctual_light(k, l, doubt(doubts, k))).collect::<Vec<_>>() }),
        );
        let nodes = root.entry("nodes").or_insert_with(|| json!([]));
        let nodes = nodes.as_array_mut().ok_or("its nodes are not an array")?;
        for (k, l) in lights.iter().enumerate() {
            node_ids.push(nodes.len());
            nodes.push(json!({
                "name": format!("lightprobe_light_{k}"),
                "translation": l.center.to_array(),
                "extensions": { EXT: { "light": k } },
            }));
        }
    } else {
        if let Some(ext) = root.get_mut("extensions").and_then(Value::as_object_mut) {
            ext.remove(EXT);
        }
        for key in ["extensionsUsed", "extensionsRequired"] {
            if let Some(list) = root.get_mut(key).and_then(Value::as_array_mut) {
                list.retain(|u| u != EXT);
            }
        }
    }
    let scenes = root
        .get_mut("scenes")
        .and_then(Value::as_array_mut)
        .ok_or("it has no scenes")?;
    let scene = scenes
        .get_mut(scene)
        .ok_or("its default scene is missing")?;
    let scene = scene.as_object_mut().ok_or("its scene is not an object")?;
    let roots = scene.entry("nodes").or_insert_with(|| json!([]));
    let roots = roots
        .as_array_mut()
        .ok_or("its scene's nodes are not an array")?;
    roots.extend(node_ids.into_iter().map(|i| json!(i)));
    if let Some(e) = envmap {
        let extras = scene.entry("extras").or_insert_with(|| json!({}));
        if let Some(extras) = extras.as_object_mut() {
            extras.insert(
                "lightprobe_envmap".into(),
                json!({
                    "exr": e.exr, "ron": e.ron, "rings": e.rings,
                    "convention": LATLONG_CONVENTION,
                    "units": "linear RGB radiance, W·sr⁻¹·m⁻² per channel",
                }),
            );
        }
    }
    Ok(())
}
