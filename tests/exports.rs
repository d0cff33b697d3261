//! The scene written for other renderers: Mitsuba's `scene.xml` (with its PLY meshes and
//! textures) and Blender's `blender.py` hold the scene, the views and the lights lightprobe
//! renders. Whether Mitsuba and Cycles render them as lightprobe does is checked in CI by
//! `scripts/check_roundtrip.py`; here, what the files say.

use std::path::Path;

use glam::Vec3;
use lightprobe::envmap::Envmap;
use lightprobe::scene::export::{blender, mitsuba};
use lightprobe::scene::{Albedo, Material, Scene, SphereLight};

mod common;

fn tabletop() -> Scene {
    Scene::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/tabletop/tabletop.ron"
    )))
    .unwrap()
}

/// A PLY as [`mitsuba::write`] writes it: (property names, vertex rows, faces).
fn read_ply(path: &Path) -> (Vec<String>, Vec<Vec<f32>>, Vec<[usize; 3]>) {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap();
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
    let count = |element: &str| -> usize {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("element {element} ")))
            .unwrap()
            .parse()
            .unwrap()
    };
    let props: Vec<String> = header
        .lines()
        .filter_map(|l| l.strip_prefix("property float "))
        .map(str::to_string)
        .collect();
    let (nv, nf) = (count("vertex"), count("face"));
    let mut at = end;
    let f32_at = |at: &mut usize| {
        let v = f32::from_le_bytes(bytes[*at..*at + 4].try_into().unwrap());
        *at += 4;
        v
    };
    let vertices: Vec<Vec<f32>> = (0..nv)
        .map(|_| (0..props.len()).map(|_| f32_at(&mut at)).collect())
        .collect();
    let faces = (0..nf)
        .map(|_| {
            assert_eq!(bytes[at], 3, "a face has 3 corners");
            at += 1;
            [0, 1, 2].map(|_| {
                let i = i32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
                at += 4;
                assert!((0..nv as i32).contains(&i), "index {i} of {nv} vertices");
                i as usize
            })
        })
        .collect();
    assert_eq!(at, bytes.len(), "{}: bytes after the faces", path.display());
    (props, vertices, faces)
}

type Node<'a, 'i> = roxmltree::Node<'a, 'i>;

/// The children of `n` with tag `tag`.
fn children<'a, 'i>(n: Node<'a, 'i>, tag: &str) -> Vec<Node<'a, 'i>> {
    n.children().filter(|c| c.has_tag_name(tag)).collect()
}

/// The first element under `n` whose `name` attribute is `name`.
fn named<'a, 'i>(n: Node<'a, 'i>, name: &str) -> Node<'a, 'i> {
    n.descendants()
        .find(|c| c.attribute("name") == Some(name))
        .unwrap_or_else(|| panic!("no {name}"))
}

/// The `value` of the element named `name` under `n`.
fn value(n: Node<'_, '_>, name: &str) -> String {
    named(n, name).attribute("value").unwrap().to_string()
}

fn floats(s: &str) -> Vec<f32> {
    s.split(',').map(|x| x.trim().parse().unwrap()).collect()
}

#[test]
fn the_mitsuba_scene_holds_the_meshes_views_and_lights() {
    let scene = tabletop();
    let dir = tempfile::tempdir().unwrap();
    let lights = [
        SphereLight {
            center: Vec3::new(1.0, 2.0, 3.0),
            radius: 0.2,
            radiance: Vec3::new(10.0, 20.0, 30.0),
        },
        SphereLight::point(Vec3::new(-1.0, 2.5, 0.5), Vec3::new(4.0, 5.0, 6.0)),
    ];
    let env = Envmap::constant(5, Vec3::new(0.5, 0.6, 0.7));
    let render = mitsuba::Render {
        spp: 64,
        max_bounces: 3,
    };
    let notes = mitsuba::write(dir.path(), &scene, &lights, &[], Some(&env), render).unwrap();
    assert!(notes.is_empty(), "{notes:?}");
    let text = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
    let doc = roxmltree::Document::parse(&text).unwrap();
    let root = doc.root_element();
    // Integrator: lightprobe's bounces are scattering events, Mitsuba's depth counts the
    // emitter too; Russian roulette starts past the last depth.
    let integrator = children(root, "integrator")[0];
    assert_eq!(value(integrator, "max_depth"), "4");
    assert_eq!(value(integrator, "rr_depth"), "5");
    assert_eq!(value(integrator, "hide_emitters"), "true");

    // One sensor per camera, in order, with its pose, field of view and size.
    let sensors = children(root, "sensor");
    assert_eq!(sensors.len(), scene.cameras.len());
    for (s, cam) in sensors.iter().zip(&scene.cameras) {
        assert_eq!(s.attribute("id"), Some(cam.name.as_str()));
        let fov: f32 = value(*s, "fov").parse().unwrap();
        assert!((fov.to_radians() - cam.yfov).abs() < 1e-6);
        assert_eq!(value(*s, "width"), cam.width.to_string());
        assert_eq!(value(*s, "height"), cam.height.to_string());
        let look = s.descendants().find(|c| c.has_tag_name("lookat")).unwrap();
        let origin = Vec3::from_slice(&floats(look.attribute("origin").unwrap()));
        let target = Vec3::from_slice(&floats(look.attribute("target").unwrap()));
        let up = Vec3::from_slice(&floats(look.attribute("up").unwrap()));
        assert!(origin.distance(cam.origin_world) < 1e-5);
        let forward = -cam.world_from_camera.z_axis;
        assert!((target - origin).normalize().distance(forward) < 1e-5);
        assert!(up.distance(cam.world_from_camera.y_axis) < 1e-5);
        assert_eq!(value(*s, "sample_count"), "$spp");
    }
    let spp = children(root, "default")[0];
    assert_eq!(
        (spp.attribute("name"), spp.attribute("value")),
        (Some("spp"), Some("64"))
    );

    // The meshes: every triangle once, with its area, under its material's albedo.
    let shapes = children(root, "shape");
    let (mut triangles, mut area) = (0, 0.0f64);
    for s in shapes.iter().filter(|s| s.attribute("type") == Some("ply")) {
        let file = value(*s, "filename");
        let m: usize = file
            .trim_start_matches("meshes/")
            .trim_end_matches(".ply")
            .parse()
            .unwrap();
        let (props, vertices, faces) = read_ply(&dir.path().join(&file));
        assert_eq!(props, ["x", "y", "z", "nx", "ny", "nz", "u", "v"]);
        triangles += faces.len();
        for f in &faces {
            let p = f.map(|i| Vec3::from_slice(&vertices[i][..3]));
            area += 0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length() as f64;
        }
        match &scene.materials[m].albedo {
            Albedo::Constant(c) => {
                let rgb = floats(&value(*s, "reflectance"));
                assert!(Vec3::from_slice(&rgb).distance(*c) < 1e-6);
            }
            Albedo::Texture { texture, factor } => {
                let bitmap = s
                    .descendants()
                    .find(|c| c.attribute("type") == Some("bitmap"))
                    .unwrap();
                let path = dir.path().join(value(bitmap, "filename"));
                let img = lightprobe::imageio::read_exr(&path).unwrap();
                assert_eq!((img.width, img.height), (texture.width, texture.height));
                let want = texture.texels[7] * *factor;
                assert!(img.rgb[7].distance(want.clamp(Vec3::ZERO, Vec3::ONE)) < 1e-6);
            }
        }
    }
    assert_eq!(triangles, scene.mesh.triangle_count());
    let want = scene.mesh.surface_area();
    assert!((area / want - 1.0).abs() < 1e-5, "area {area} vs {want}");

    // The lights: the sphere as an area-lit sphere, the point as a point emitter of its
    // intensity, the envmap as Mitsuba's envmap emitter.
    let sphere = shapes
        .iter()
        .find(|s| s.attribute("type") == Some("sphere"))
        .unwrap();
    assert_eq!(floats(&value(*sphere, "center")), [1.0, 2.0, 3.0]);
    assert_eq!(value(*sphere, "radius"), "0.2");
    assert_eq!(floats(&value(*sphere, "radiance")), [10.0, 20.0, 30.0]);
    let emitters = children(root, "emitter");
    let point = emitters
        .iter()
        .find(|e| e.attribute("type") == Some("point"))
        .unwrap();
    assert_eq!(floats(&value(*point, "position")), [-1.0, 2.5, 0.5]);
    assert_eq!(floats(&value(*point, "intensity")), [4.0, 5.0, 6.0]);
    let envmap = emitters
        .iter()
        .find(|e| e.attribute("type") == Some("envmap"))
        .unwrap();
    let lat_long =
        lightprobe::imageio::read_exr(&dir.path().join(value(*envmap, "filename"))).unwrap();
    assert!(lat_long.mean().distance(Vec3::new(0.5, 0.6, 0.7)) < 1e-5);
}

#[test]
fn vertex_colours_reach_mitsuba_and_a_texture_with_them_is_named() {
    // A constant albedo with vertex colours: the PLY carries colour × factor as r g b, read
    // by a `mesh_attribute` texture. A texture with vertex colours cannot be multiplied in
    // Mitsuba's scene: it keeps the texture, and the note says so.
    let mut scene = tabletop();
    let mut mesh = common::plane(1.0, 0.0);
    let tri: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let colour_at = |p: Vec3| Vec3::new(0.3 + 0.1 * p.x, 0.5 + 0.2 * p.z, 1.0);
    let colors: Vec<Vec3> = mesh.positions.iter().map(|&p| colour_at(p)).collect();
    let positions = mesh.positions.clone();
    mesh = Default::default();
    mesh.push_colored(&positions, None, None, Some(&colors), &tri, 0);
    let textured = scene
        .materials
        .iter()
        .position(|m| matches!(m.albedo, Albedo::Texture { .. }))
        .unwrap();
    mesh.push_colored(&positions, None, None, Some(&colors), &tri, 1);
    scene.materials = vec![
        Material {
            name: "painted".into(),
            albedo: Albedo::Constant(Vec3::new(0.5, 1.0, 1.0)),
        },
        Material {
            name: "textured".into(),
            albedo: scene.materials[textured].albedo.clone(),
        },
    ];
    scene.mesh = mesh;
    let dir = tempfile::tempdir().unwrap();
    let render = mitsuba::Render {
        spp: 4,
        max_bounces: 1,
    };
    let notes = mitsuba::write(dir.path(), &scene, &[], &[], None, render).unwrap();
    assert_eq!(notes.len(), 1, "{notes:?}");
    assert!(notes[0].contains("\"textured\"") && notes[0].contains("vertex colours"));
    let text = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
    assert!(text.contains("<texture type=\"mesh_attribute\" name=\"reflectance\">"));
    assert!(!text.contains("type=\"envmap\""));
    let (props, vertices, _) = read_ply(&dir.path().join("meshes/0.ply"));
    assert_eq!(props[8..], ["r", "g", "b"]);
    let want: Vec<Vec3> = vertices
        .iter()
        .map(|v| colour_at(Vec3::from_slice(&v[..3])) * Vec3::new(0.5, 1.0, 1.0))
        .collect();
    for (v, w) in vertices.iter().zip(want) {
        assert!(Vec3::from_slice(&v[8..11]).distance(w) < 1e-6);
    }
    let (props, _, _) = read_ply(&dir.path().join("meshes/1.ply"));
    assert_eq!(props.len(), 8, "the textured mesh carries no colours");
}

#[test]
fn blender_py_carries_the_views_materials_and_settings() {
    let mut scene = tabletop();
    // A quote in a name must not end the script's raw string.
    scene.materials[0].name = "it's '''here".into();
    let dir = tempfile::tempdir().unwrap();
    let env = Envmap::constant(3, Vec3::ONE);
    blender::write(dir.path(), "scene.glb", &scene, Some(&env), 128, 2).unwrap();
    let text = std::fs::read_to_string(dir.path().join("blender.py")).unwrap();
    let start = text.find("DATA = json.loads(r'''").unwrap() + "DATA = json.loads(r'''".len();
    let end = start + text[start..].find("''')").unwrap();
    let data: serde_json::Value = serde_json::from_str(&text[start..end]).unwrap();
    assert_eq!(data["gltf"], "scene.glb");
    assert_eq!(data["spp"], 128);
    assert_eq!(data["max_bounces"], 2);
    assert_eq!(data["envmap"], "envmap_blender.exr");
    assert!(dir.path().join("envmap_blender.exr").is_file());
    let views = data["views"].as_array().unwrap();
    assert_eq!(views.len(), scene.cameras.len());
    for (v, cam) in views.iter().zip(&scene.cameras) {
        assert_eq!(v["name"], cam.name.as_str());
        assert_eq!(
            (v["width"].as_u64(), v["height"].as_u64()),
            (Some(cam.width as u64), Some(cam.height as u64))
        );
        let back: Vec<f32> = serde_json::from_value(v["back"].clone()).unwrap();
        assert!(Vec3::from_slice(&back).distance(cam.world_from_camera.z_axis) < 1e-6);
    }
    for m in &scene.materials {
        let spec = &data["materials"][m.name.as_str()];
        match &m.albedo {
            Albedo::Constant(c) => {
                let got: Vec<f32> = serde_json::from_value(spec["color"].clone()).unwrap();
                assert!(Vec3::from_slice(&got).distance(*c) < 1e-6);
                assert!(spec["texture"].is_null());
            }
            Albedo::Texture { .. } => {
                let file = spec["texture"].as_str().unwrap();
                assert!(dir.path().join(file).is_file(), "{file}");
            }
        }
    }
}

#[test]
fn a_corrected_texture_goes_into_the_gltf_and_comes_back() {
    // The table's texture corrected (a gradient across it, as `--fit-albedo texels` would
    // write): the written GLB points the table at a new PNG beside it (sampler and texCoord
    // kept, the original image still in the file), and lightprobe's own loader reads back the
    // corrected texels within 8-bit sRGB quantisation.
    use lightprobe::scene::Texture;
    use lightprobe::scene::export;
    let given = tabletop();
    let table = given
        .materials
        .iter()
        .position(|m| m.name == "table")
        .unwrap();
    let Albedo::Texture { texture, factor } = &given.materials[table].albedo else {
        panic!("the bundled table is textured");
    };
    let w = texture.width;
    let corrected = Texture {
        width: texture.width,
        height: texture.height,
        texels: texture
            .texels
            .iter()
            .enumerate()
            .map(|(i, t)| *t * (0.6 + 0.8 * (i as u32 % w) as f32 / w as f32))
            .map(|t| t.min(Vec3::ONE))
            .collect(),
    };
    let mut fitted = given.materials.clone();
    fitted[table].albedo = Albedo::Texture {
        texture: std::sync::Arc::new(corrected.clone()),
        factor: *factor,
    };
    let dir = tempfile::tempdir().unwrap();
    let (written, notes) = export::write_with_lights(
        &given.gltf,
        dir.path(),
        &[],
        &[],
        None,
        Some((&given.materials, &fitted)),
    )
    .unwrap();
    assert!(notes.is_empty(), "{notes:?}");
    let file = export::albedo_texture_file(table, "table");
    assert!(dir.path().join(&file).is_file());
    let back = Scene::load(&written).unwrap();
    let Albedo::Texture { texture: read, .. } = &back.materials[table].albedo else {
        panic!("the written table is textured");
    };
    assert_eq!(
        (read.width, read.height),
        (corrected.width, corrected.height)
    );
    let worst = read
        .texels
        .iter()
        .zip(&corrected.texels)
        .map(|(a, b)| ((*a - *b).abs() / (*b + 0.01)).max_element())
        .fold(0.0f32, f32::max);
    assert!(worst < 0.06, "worst texel off by {worst}");
    // The other materials are as they were, and the file keeps its own image.
    let doc = common::glb_json(&written);
    assert_eq!(doc["images"].as_array().unwrap().len(), 2);
    assert_eq!(doc["images"][1]["uri"], file.as_str());
    let t = doc["materials"][table - 1]["pbrMetallicRoughness"]["baseColorTexture"]["index"]
        .as_u64()
        .unwrap() as usize;
    assert_eq!(doc["textures"][t]["source"], 1);
    assert_eq!(doc["textures"][t]["sampler"], doc["textures"][0]["sampler"]);
    for (m, (a, b)) in back.materials.iter().zip(&given.materials).enumerate() {
        if m != table {
            assert!((a.mean_albedo() - b.mean_albedo()).abs().max_element() < 1e-6);
        }
    }
}

#[test]
fn a_corrected_texture_with_alpha_leaves_the_gltf_its_own_and_the_fitted_factor() {
    // The table made alphaMode MASK: its alpha lives in its texture, which lightprobe reads
    // without alpha, so the glTF keeps its own texture and takes the fitted factor instead,
    // with a note naming the corrected texture.
    use lightprobe::scene::Texture;
    use lightprobe::scene::export;
    let given = tabletop();
    let bytes = std::fs::read(&given.gltf).unwrap();
    let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let mut doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + len]).unwrap();
    let table = given
        .materials
        .iter()
        .position(|m| m.name == "table")
        .unwrap();
    doc["materials"][table - 1]["alphaMode"] = "MASK".into();
    // Reassemble the GLB: the JSON chunk padded with spaces, the binary chunk as it was.
    let mut json = serde_json::to_vec(&doc).unwrap();
    json.resize(json.len().next_multiple_of(4), b' ');
    let bin = &bytes[20 + len..];
    let mut glb = Vec::new();
    glb.extend_from_slice(b"glTF");
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&((12 + 8 + json.len() + bin.len()) as u32).to_le_bytes());
    glb.extend_from_slice(&(json.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json);
    glb.extend_from_slice(bin);
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("masked.glb");
    std::fs::write(&source, &glb).unwrap();
    let Albedo::Texture { texture, factor } = &given.materials[table].albedo else {
        panic!("the bundled table is textured");
    };
    let mut fitted = given.materials.clone();
    let fitted_factor = *factor * Vec3::new(0.8, 0.9, 0.7);
    fitted[table].albedo = Albedo::Texture {
        texture: std::sync::Arc::new(Texture {
            texels: texture.texels.iter().map(|t| *t * 0.9).collect(),
            ..(**texture).clone()
        }),
        factor: fitted_factor,
    };
    let out = dir.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    let (written, notes) = export::write_with_lights(
        &source,
        &out,
        &[],
        &[],
        None,
        Some((&given.materials, &fitted)),
    )
    .unwrap();
    let file = export::albedo_texture_file(table, "table");
    assert!(
        notes
            .iter()
            .any(|n| n.contains("MASK") && n.contains(&file)),
        "{notes:?}"
    );
    assert!(out.join(&file).is_file());
    let doc = common::glb_json(&written);
    let pbr = &doc["materials"][table - 1]["pbrMetallicRoughness"];
    assert_eq!(pbr["baseColorTexture"]["index"], 0);
    assert_eq!(doc["images"].as_array().unwrap().len(), 1);
    for c in 0..3 {
        let f = pbr["baseColorFactor"][c].as_f64().unwrap() as f32;
        assert!((f - fitted_factor[c]).abs() < 1e-6, "{pbr}");
    }
}
