//! A glTF file as a scene by itself: its cameras are the views, its `KHR_lights_punctual`
//! lights the reference lights, its image size the camera's aspect at `--height` or the
//! references'; what the Lambertian model leaves out of its materials is said, not dropped.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightprobe"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn ok(o: &Output) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "{err}");
    err
}

fn fails(o: &Output) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "{err}");
    err
}

/// A floor (4 m square at y = 0) and a closed cube (0.6 m) on it, seen by two cameras with
/// aspect ratio 1.5, lit by `lights` (KHR_lights_punctual light objects, JSON) on nodes at
/// `positions`. The floor's material is Lambertian as glTF can say it (metallic 0,
/// roughness 1); the cube's is glTF's default metal-less-than-said: metallic and roughness
/// unset (both 1) and an emissive factor, which the model leaves out.
fn lit_scene(dir: &Path, lights: &[&str], positions: &[[f32; 3]]) -> PathBuf {
    let mut bin: Vec<u8> = Vec::new();
    let push_f32 =
        |bin: &mut Vec<u8>, v: &[f32]| v.iter().for_each(|x| bin.extend(x.to_le_bytes()));
    // Floor: 4 vertices, 6 indices.
    let floor = [
        [-2.0f32, 0.0, -2.0],
        [2.0, 0.0, -2.0],
        [2.0, 0.0, 2.0],
        [-2.0, 0.0, 2.0],
    ];
    for p in floor {
        push_f32(&mut bin, &p);
    }
    let floor_idx = [0u32, 2, 1, 0, 3, 2];
    for i in floor_idx {
        bin.extend(i.to_le_bytes());
    }
    // Cube: 8 corners, 12 triangles, flat shaded (no normals).
    let h = 0.3f32;
    let corners: Vec<[f32; 3]> = (0..8)
        .map(|i| {
            [
                if i & 1 == 0 { -h } else { h },
                if i & 2 == 0 { 0.0 } else { 2.0 * h },
                if i & 4 == 0 { -h } else { h },
            ]
        })
        .collect();
    let cube_at = bin.len();
    for p in &corners {
        push_f32(&mut bin, p);
    }
    let cube_idx: [u32; 36] = [
        0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4,
        1, 5, 7, 1, 7, 3,
    ];
    let cube_idx_at = bin.len();
    for i in cube_idx {
        bin.extend(i.to_le_bytes());
    }
    std::fs::write(dir.join("lit.bin"), &bin).unwrap();
    let light_nodes: Vec<String> = positions
        .iter()
        .enumerate()
        .map(|(k, p)| {
            format!(
                r#"{{"name": "lamp{k}", "translation": [{}, {}, {}], "extensions": {{"KHR_lights_punctual": {{"light": {k}}}}}}}"#,
                p[0], p[1], p[2]
            )
        })
        .collect();
    let node_ids: Vec<String> = (0..4 + positions.len()).map(|i| i.to_string()).collect();
    let gltf = format!(
        r#"{{"asset": {{"version": "2.0"}},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {{"KHR_lights_punctual": {{"lights": [{lights}]}}}},
        "buffers": [{{"uri": "lit.bin", "byteLength": {len}}}],
        "bufferViews": [{{"buffer": 0, "byteOffset": 0, "byteLength": 48}},
                        {{"buffer": 0, "byteOffset": 48, "byteLength": 24}},
                        {{"buffer": 0, "byteOffset": {cube_at}, "byteLength": 96}},
                        {{"buffer": 0, "byteOffset": {cube_idx_at}, "byteLength": 144}}],
        "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                        "min": [-2, 0, -2], "max": [2, 0, 2]}},
                      {{"bufferView": 1, "componentType": 5125, "count": 6, "type": "SCALAR"}},
                      {{"bufferView": 2, "componentType": 5126, "count": 8, "type": "VEC3",
                        "min": [-0.3, 0, -0.3], "max": [0.3, 0.6, 0.3]}},
                      {{"bufferView": 3, "componentType": 5125, "count": 36, "type": "SCALAR"}}],
        "materials": [{{"name": "floor", "pbrMetallicRoughness": {{"baseColorFactor": [0.6, 0.6, 0.6, 1], "metallicFactor": 0, "roughnessFactor": 1}}}},
                      {{"name": "cube", "pbrMetallicRoughness": {{"baseColorFactor": [0.8, 0.3, 0.2, 1]}}, "emissiveFactor": [0.1, 0, 0]}}],
        "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1, "material": 0}}]}},
                   {{"primitives": [{{"attributes": {{"POSITION": 2}}, "indices": 3, "material": 1}}]}}],
        "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "aspectRatio": 1.5, "znear": 0.01}}}}],
        "nodes": [{{"mesh": 0}}, {{"mesh": 1}},
                  {{"name": "front", "camera": 0, "translation": [0, 1.2, 3], "rotation": [-0.19509, 0, 0, 0.98079]}},
                  {{"name": "side", "camera": 0, "translation": [3, 1.2, 0], "rotation": [-0.13795, 0.69352, 0.13795, 0.69352]}}
                  {comma}{light_nodes}],
        "scenes": [{{"nodes": [{node_ids}]}}], "scene": 0}}"#,
        lights = lights.join(", "),
        len = bin.len(),
        comma = if positions.is_empty() { "" } else { "," },
        light_nodes = light_nodes.join(", "),
        node_ids = node_ids.join(", "),
    );
    let path = dir.join("lit.gltf");
    std::fs::write(&path, gltf).unwrap();
    path
}

const KEY: &str = r#"{"type": "point", "color": [1.0, 0.9, 0.8], "intensity": 2000}"#;
const FILL: &str =
    r#"{"type": "point", "color": [0.5, 0.6, 1.0], "intensity": 800, "extras": {"radius": 0.1}}"#;

fn lit(dir: &Path) -> PathBuf {
    lit_scene(dir, &[KEY, FILL], &[[-1.0, 2.5, 1.5], [1.8, 1.2, -1.0]])
}

fn info(args: &[&str]) -> serde_json::Value {
    let o = run(&[&["info"], args].concat());
    ok(&o);
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn a_gltf_alone_gives_views_lights_and_what_its_materials_leave_out() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit(tmp.path());
    let s = scene.to_str().unwrap();
    let o = run(&["info", s]);
    let err = ok(&o);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // Views: every camera node, 480 high at the camera's aspect ratio 1.5.
    let cams = v["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), 2);
    assert_eq!(
        (&cams[0]["name"], &cams[1]["name"]),
        (&"front".into(), &"side".into())
    );
    assert_eq!(
        (&cams[0]["width"], &cams[0]["height"]),
        (&720.into(), &480.into())
    );
    let v30 = info(&[s, "--height", "30"]);
    assert_eq!(v30["cameras"][1]["width"], 45);
    assert_eq!(v30["settings"]["height"], 30);
    // Lights: candela / 683 W/sr, times the colour; the second a sphere of that intensity.
    let lights = v["lights"].as_array().unwrap();
    assert_eq!(lights.len(), 2);
    assert_eq!(lights[0]["radius"], 0.0);
    let key = lights[0]["intensity"].as_array().unwrap();
    for (c, want) in key.iter().zip([1.0, 0.9, 0.8]) {
        let want = want * 2000.0 / 683.0;
        assert!((c.as_f64().unwrap() - want).abs() < 1e-4 * want, "{key:?}");
    }
    assert_eq!(lights[0]["center"], serde_json::json!([-1.0, 2.5, 1.5]));
    let fill = &lights[1];
    assert!((fill["radius"].as_f64().unwrap() - 0.1).abs() < 1e-7);
    let radiance = fill["radiance"][2].as_f64().unwrap();
    let want = 800.0 / 683.0 / (std::f64::consts::PI * 0.01);
    assert!((radiance - want).abs() < 1e-4 * want, "{fill}");
    // The cube's material: glTF's defaults (metallic 1, roughness 1) and its emission are left
    // out, said once on stderr and listed; the floor is Lambertian already.
    let ignored = v["ignored"].as_array().unwrap();
    assert_eq!(ignored.len(), 1, "{ignored:?}");
    assert_eq!(ignored[0]["what"], "material \"cube\"");
    let props = ignored[0]["properties"].to_string();
    assert!(
        props.contains("metallic 1") && props.contains("emission"),
        "{props}"
    );
    assert_eq!(err.matches("note:").count(), 1, "{err}");
    assert!(
        err.contains("lit.gltf") && err.contains("\"cube\""),
        "{err}"
    );
}

#[test]
fn gltf_lights_render_as_the_same_lights_written_in_a_sidecar() {
    // The glTF's point light and sphere light, and a sidecar naming the same glTF with those
    // lights written out (Point intensity = colour × cd / 683; Sphere radiance = that / πr²),
    // render the same bytes: the conversion is the documented one.
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit(tmp.path());
    let ron = tmp.path().join("same.ron");
    // The loader's arithmetic, in its order: colour × (cd / 683), then / (π r r).
    let k = 2000.0f32 / 683.0;
    let f = |c: f32| c * (800.0f32 / 683.0) / (std::f32::consts::PI * 0.1f32 * 0.1f32);
    std::fs::write(
        &ron,
        format!(
            "Scene(gltf: \"lit.gltf\", image: (width: 36, height: 24), lights: [\
             Point(center: (-1.0, 2.5, 1.5), intensity: ({}, {}, {})), \
             Sphere(center: (1.8, 1.2, -1.0), radius: 0.1, radiance: ({}, {}, {}))])",
            1.0 * k,
            0.9f32 * k,
            0.8f32 * k,
            f(0.5),
            f(0.6),
            f(1.0)
        ),
    )
    .unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    for (src, out) in [(&scene, &a), (&ron, &b)] {
        ok(&run(&[
            "render-reference",
            src.to_str().unwrap(),
            "--height",
            "24",
            "--spp",
            "16",
            "--out",
            out.to_str().unwrap(),
            "--quiet",
        ]));
    }
    for view in ["front", "side"] {
        let x = std::fs::read(a.join(format!("{view}.exr"))).unwrap();
        let y = std::fs::read(b.join(format!("{view}.exr"))).unwrap();
        assert!(
            x == y,
            "{view}: the glTF's lights and the sidecar's render differently"
        );
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("render.json")).unwrap()).unwrap();
    assert_eq!(
        report["image"],
        serde_json::json!({"width": 36, "height": 24})
    );
    assert_eq!(report["views"][1]["width"], 36);
    // The point light lights the floor: the image is not black.
    let mean = report["views"][0]["mean_rgb"][0].as_f64().unwrap();
    assert!(mean > 1e-3, "{report}");
}

#[test]
fn estimate_takes_a_gltf_and_sizes_its_views_from_the_references() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit(tmp.path());
    let s = scene.to_str().unwrap();
    let refs = tmp.path().join("refs");
    ok(&run(&[
        "render-reference",
        s,
        "--height",
        "18",
        "--spp",
        "64",
        "--out",
        refs.to_str().unwrap(),
        "--quiet",
    ]));
    // No --height: the views take the references' 27×18.
    let out = tmp.path().join("out");
    let o = run(&[
        "estimate",
        s,
        "--reference",
        refs.to_str().unwrap(),
        "--spp",
        "16",
        "--rings",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--json",
        "--quiet",
    ]);
    ok(&o);
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["views"].as_array().unwrap().len(), 2);
    // 16 spp, 3 rings: measured 0.25 (floor 0.056).
    assert!(report["rel_mae"].as_f64().unwrap() < 0.4, "{report}");
    assert_eq!(report["ignored"][0]["what"], "material \"cube\"");
    let envmap = std::fs::read_to_string(out.join("envmap.ron")).unwrap();
    assert!(envmap.contains("rings: 3"), "{envmap}");
    // A reference whose shape the camera's aspect ratio cannot have is refused by name.
    let bad = tmp.path().join("bad");
    std::fs::create_dir(&bad).unwrap();
    std::fs::copy(refs.join("front.exr"), bad.join("front.exr")).unwrap();
    let square = tmp.path().join("sq");
    ok(&run(&[
        "render-reference",
        s,
        "--height",
        "18",
        "--spp",
        "1",
        "--out",
        square.to_str().unwrap(),
        "--quiet",
    ]));
    let ron = tmp.path().join("sq.ron");
    std::fs::write(
        &ron,
        "Scene(gltf: \"lit.gltf\", image: (width: 18, height: 18))",
    )
    .unwrap();
    let sq = tmp.path().join("sqr");
    ok(&run(&[
        "render-reference",
        ron.to_str().unwrap(),
        "--spp",
        "1",
        "--out",
        sq.to_str().unwrap(),
        "--quiet",
    ]));
    std::fs::copy(sq.join("side.exr"), bad.join("side.exr")).unwrap();
    let out2 = tmp.path().join("out2");
    let err = fails(&run(&[
        "estimate",
        s,
        "--reference",
        bad.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
        "--quiet",
    ]));
    assert!(
        err.contains("side.exr") && err.contains("18×18") && err.contains("aspect ratio 1.5"),
        "{err}"
    );
    assert!(!out2.exists(), "a refused estimate left {out2:?}");
    // Without references, the glTF's own lights render them (here at --height 12).
    let out3 = tmp.path().join("out3");
    let o = run(&[
        "estimate",
        s,
        "--height",
        "12",
        "--spp",
        "8",
        "--rings",
        "3",
        "--fit-only",
        "--out",
        out3.to_str().unwrap(),
        "--quiet",
    ]);
    ok(&o);
    assert!(out3.join("reference/front.exr").exists());
}

#[test]
fn lights_lightprobe_cannot_render_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    for (light, needle) in [
        (
            r#"{"type": "spot", "name": "torch", "spot": {"outerConeAngle": 0.5}}"#,
            "\"torch\" on node \"lamp0\" (#4) is a spot light",
        ),
        (
            r#"{"type": "directional", "name": "sun"}"#,
            "is a directional light",
        ),
        (
            r#"{"type": "point", "extras": {"radius": -1}}"#,
            "extras radius -1 is not a length",
        ),
        (
            r#"{"type": "point", "intensity": -5}"#,
            "intensity -5: each must be finite and ≥ 0",
        ),
    ] {
        let scene = lit_scene(tmp.path(), &[light], &[[0.0, 2.0, 0.0]]);
        let err = fails(&run(&["info", scene.to_str().unwrap()]));
        assert!(
            err.contains("lit.gltf") && err.contains(needle),
            "{light}\n-> {err}"
        );
        assert_eq!(err.lines().count(), 1, "{err}");
    }
    // A glTF without lights renders nothing: said, with what to do.
    let scene = lit_scene(tmp.path(), &[], &[]);
    let out = tmp.path().join("out");
    let err = fails(&run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--height",
        "8",
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(
        err.contains("no sphere or point lights") && err.contains("--reference"),
        "{err}"
    );
}

/// `Sphere(center: (x, y, z), radius: r, radiance: (a, b, c))` entries of a lights.ron.
fn spheres_in(text: &str) -> Vec<[f64; 7]> {
    text.lines()
        .filter(|l| l.trim_start().starts_with("Sphere("))
        .map(|l| {
            let nums: Vec<f64> = l
                .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == 'e'))
                .filter_map(|t| t.parse().ok())
                .collect();
            nums.try_into().unwrap_or_else(|n| panic!("{l}: {n:?}"))
        })
        .collect()
}

#[test]
fn estimate_writes_the_scene_back_as_gltf_with_the_estimate_in_it() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit_scene(tmp.path(), &[KEY], &[[-1.0, 2.5, 1.5]]);
    let s = scene.to_str().unwrap();
    let out = tmp.path().join("out");
    ok(&run(&[
        "estimate",
        s,
        "--height",
        "24",
        "--spp",
        "64",
        "--rings",
        "3",
        "--model",
        "spheres:1",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]));
    // spheres/scene.gltf: the source's buffer beside it, its light the fitted one (the
    // source's own light gone), read back through the loader.
    let export = out.join("spheres/scene.gltf");
    assert!(out.join("spheres/lit.bin").exists());
    let fitted = spheres_in(&std::fs::read_to_string(out.join("spheres/lights.ron")).unwrap());
    assert_eq!(fitted.len(), 1);
    let back = info(&[export.to_str().unwrap(), "--height", "24"]);
    let lights = back["lights"].as_array().unwrap();
    assert_eq!(lights.len(), 1, "{back}");
    let l = &lights[0];
    let f = fitted[0];
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * b.abs().max(1e-3);
    for k in 0..3 {
        assert!(
            close(l["center"][k].as_f64().unwrap(), f[k]),
            "{l} vs {f:?}"
        );
        assert!(
            close(l["radiance"][k].as_f64().unwrap(), f[4 + k]),
            "{l} vs {f:?}"
        );
    }
    assert!(close(l["radius"].as_f64().unwrap(), f[3]), "{l} vs {f:?}");
    let source = info(&[s, "--height", "24"]);
    assert_eq!(back["triangles"], source["triangles"]);
    assert_eq!(back["cameras"], source["cameras"]);
    assert_eq!(back["materials"], source["materials"]);
    // scene.gltf: no lights, the envmap named in the scene's extras.
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("scene.gltf")).unwrap()).unwrap();
    let note = &doc["scenes"][0]["extras"]["lightprobe_envmap"];
    assert_eq!(note["exr"], "envmap.exr");
    assert_eq!(note["rings"], 3);
    let plain = info(&[out.join("scene.gltf").to_str().unwrap(), "--height", "24"]);
    assert_eq!(plain["lights"], serde_json::json!([]));
}

#[test]
fn a_glb_is_written_back_as_a_glb_with_its_binary_chunk() {
    let tmp = tempfile::tempdir().unwrap();
    let glb = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb");
    let ron = tmp.path().join("s.ron");
    std::fs::write(
        &ron,
        format!(
            "Scene(gltf: {glb:?}, image: (width: 32, height: 24), \
             lights: [Point(center: (-1.8, 3.2, 1.5), intensity: (80.0, 70.0, 60.0))], \
             render: (spp: 4))"
        ),
    )
    .unwrap();
    let out = tmp.path().join("out");
    ok(&run(&[
        "estimate",
        ron.to_str().unwrap(),
        "--rings",
        "3",
        "--fit-only",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]));
    let written = std::fs::read(out.join("scene.glb")).unwrap();
    let source = std::fs::read(glb).unwrap();
    // The binary chunk is the source's, byte for byte (it ends both files).
    let bin_len = {
        let j = u32::from_le_bytes(source[12..16].try_into().unwrap()) as usize;
        u32::from_le_bytes(source[20 + j..24 + j].try_into().unwrap()) as usize
    };
    assert_eq!(
        written[written.len() - bin_len..],
        source[source.len() - bin_len..]
    );
    let a = info(&[out.join("scene.glb").to_str().unwrap(), "--height", "24"]);
    let b = info(&[glb, "--height", "24"]);
    for k in ["triangles", "vertices", "materials", "cameras", "bounds"] {
        assert_eq!(a[k], b[k], "{k}");
    }
}

/// `lit_scene`'s JSON as a GLB without a binary chunk (its buffer stays in `lit.bin`).
fn as_glb_with_external_buffer(gltf: &Path) -> PathBuf {
    let mut json = std::fs::read(gltf).unwrap();
    json.resize(json.len().next_multiple_of(4), b' ');
    let mut out = Vec::new();
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((20 + json.len() as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&json);
    let path = gltf.with_extension("glb");
    std::fs::write(&path, out).unwrap();
    path
}

#[test]
fn outputs_stay_where_they_belong() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let scene = lit(d);
    // A camera whose name would write outside the output folder, or over another view's
    // files, is refused by name.
    let text = std::fs::read_to_string(&scene).unwrap();
    for (name, needle) in [
        ("../evil", "cannot name a view's files"),
        ("", "cannot name a view's files"),
        ("front.error", "would write over each other's files"),
    ] {
        let bad = d.join("bad.gltf");
        std::fs::write(&bad, text.replace("\"side\"", &format!("{name:?}"))).unwrap();
        let err = fails(&run(&["info", bad.to_str().unwrap()]));
        assert!(
            err.contains("bad.gltf") && err.contains(needle),
            "{name}: {err}"
        );
    }
    // `estimate` refuses to write its glTF over the scene it read.
    let glb = as_glb_with_external_buffer(&scene);
    let copy = d.join("scene.glb");
    std::fs::copy(&glb, &copy).unwrap();
    let before = std::fs::read(&copy).unwrap();
    let err = fails(&run(&[
        "estimate",
        copy.to_str().unwrap(),
        "--height",
        "12",
        "--spp",
        "4",
        "--rings",
        "3",
        "--fit-only",
        "--out",
        d.to_str().unwrap(),
        "--quiet",
    ]));
    assert!(
        err.contains("would write") && err.contains("scene.glb"),
        "{err}"
    );
    assert_eq!(std::fs::read(&copy).unwrap(), before);
    // A GLB that refers to an outside buffer is written back with a copy of it.
    let out = d.join("out");
    ok(&run(&[
        "estimate",
        glb.to_str().unwrap(),
        "--height",
        "12",
        "--spp",
        "4",
        "--rings",
        "3",
        "--fit-only",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]));
    assert!(out.join("lit.bin").exists());
    let back = info(&[out.join("scene.glb").to_str().unwrap(), "--height", "12"]);
    assert_eq!(back["triangles"], 14);
    // Point lights are out of reach of BSDF sampling alone: said, not rendered black.
    let err = fails(&run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--height",
        "12",
        "--strategy",
        "bsdf-only",
        "--out",
        d.join("bsdf").to_str().unwrap(),
    ]));
    assert!(err.contains("only light sampling reaches"), "{err}");
    assert!(!d.join("bsdf").exists());
    // A light beyond what can be rendered is refused, naming it.
    let hot = lit_scene(
        d,
        &[r#"{"type": "point", "name": "sun", "intensity": 1e30}"#],
        &[[0.0, 2.0, 0.0]],
    );
    let err = fails(&run(&["info", hot.to_str().unwrap()]));
    assert!(
        err.contains("\"sun\"") && err.contains("beyond the 1e15"),
        "{err}"
    );
}

#[test]
fn references_are_found_as_cameras_name_them() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit(tmp.path());
    let s = scene.to_str().unwrap();
    let refs = tmp.path().join("refs");
    ok(&run(&[
        "render-reference",
        s,
        "--height",
        "12",
        "--spp",
        "8",
        "--out",
        refs.to_str().unwrap(),
        "--quiet",
    ]));
    // `FRONT.EXR`-style capitals: the extension in capitals is found.
    for v in ["front", "side"] {
        std::fs::rename(refs.join(format!("{v}.exr")), refs.join(format!("{v}.EXR"))).unwrap();
        std::fs::remove_file(refs.join(format!("{v}.png"))).unwrap();
    }
    ok(&run(&[
        "estimate",
        s,
        "--reference",
        refs.to_str().unwrap(),
        "--spp",
        "4",
        "--rings",
        "3",
        "--fit-only",
        "--out",
        tmp.path().join("o").to_str().unwrap(),
        "--quiet",
    ]));
    // --linear and --saturation mean nothing without references: refused.
    let o = run(&[
        "estimate",
        s,
        "--linear",
        "--out",
        tmp.path().join("p").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn primitives_without_a_material_are_said_to_lose_the_default_materials_metal() {
    // glTF's default material is metallic 1, roughness 1; lightprobe renders it white
    // diffuse, and says so like any other material's left-out properties.
    let tmp = tempfile::tempdir().unwrap();
    let scene = lit(tmp.path());
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&scene).unwrap()).unwrap();
    let prims = doc["meshes"][0]["primitives"].as_array_mut().unwrap();
    assert!(
        prims[0]
            .as_object_mut()
            .unwrap()
            .remove("material")
            .is_some()
    );
    let bare = tmp.path().join("bare.gltf");
    std::fs::write(&bare, doc.to_string()).unwrap();
    let v = info(&[bare.to_str().unwrap()]);
    let ignored = v["ignored"].as_array().unwrap();
    assert_eq!(
        ignored[0]["what"],
        "glTF's default material (primitives without one)"
    );
    assert!(ignored[0]["properties"].to_string().contains("metallic 1"));
    // The scene as written has a material on every primitive: no such entry.
    let v = info(&[scene.to_str().unwrap()]);
    assert!(!v["ignored"].to_string().contains("default material"));
}

/// The bundled glTF with `cameras` (RON text) added by a sidecar in `dir`, and `views`.
fn posed(dir: &Path, views: &str, cameras: &str) -> PathBuf {
    let sidecar = dir.join("posed.ron");
    std::fs::write(
        &sidecar,
        format!(
            "Scene(gltf: {:?}, views: [{views}], image: (width: 32, height: 24),\n cameras: [{cameras}],\n lights: [Point(center: (0, 3, 0), intensity: (5, 5, 5))])",
            concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb")
        ),
    )
    .unwrap();
    sidecar
}

#[test]
fn a_sidecar_adds_views_by_pose_as_a_look_at_or_a_matrix() {
    // The bundled glTF's two cameras, given again by pose (as SLAM or structure from motion
    // would give them): a look-at and a camera-to-world matrix built from `info`'s axes must
    // come out as the same cameras.
    let tmp = tempfile::tempdir().unwrap();
    let glb = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb");
    let truth = info(&[glb]);
    let cam = |i: usize, key: &str| -> [f64; 3] {
        serde_json::from_value(truth["cameras"][i][key].clone()).unwrap()
    };
    let (o, f, u) = (cam(0, "origin"), cam(0, "forward"), cam(0, "up"));
    let look_at = format!(
        "(name: \"front_again\", yfov: 0.7, pose: LookAt(eye: ({}, {}, {}), target: ({}, {}, {}), up: ({}, {}, {})))",
        o[0],
        o[1],
        o[2],
        o[0] + f[0],
        o[1] + f[1],
        o[2] + f[2],
        u[0],
        u[1],
        u[2]
    );
    let (o, r, u, f) = (
        cam(1, "origin"),
        cam(1, "right"),
        cam(1, "up"),
        cam(1, "forward"),
    );
    // Columns: +X = right, +Y = up, +Z = back (−forward), position.
    let rows: Vec<String> = (0..3)
        .map(|k| format!("({}, {}, {}, {})", r[k], u[k], -f[k], o[k]))
        .collect();
    let matrix = format!(
        "(name: \"side_again\", yfov: 0.7, aspect_ratio: 1.3333334, pose: Matrix(({}, (0, 0, 0, 1))))",
        rows.join(", ")
    );
    let sidecar = posed(
        tmp.path(),
        "\"front_again\", \"side_again\", \"cam_front\"",
        &format!("{look_at}, {matrix}"),
    );
    let v = info(&[sidecar.to_str().unwrap()]);
    let cams = v["cameras"].as_array().unwrap();
    let names: Vec<&str> = cams.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["front_again", "side_again", "cam_front"]);
    for (got, want) in [(0, 0), (1, 1)] {
        for key in ["origin", "forward", "up", "right"] {
            let a: [f64; 3] = serde_json::from_value(cams[got][key].clone()).unwrap();
            let b: [f64; 3] = serde_json::from_value(truth["cameras"][want][key].clone()).unwrap();
            let d = (0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f64::max);
            assert!(d < 1e-5, "{key} of {}: {a:?} vs {b:?}", names[got]);
        }
        assert_eq!(
            (&cams[got]["width"], &cams[got]["height"]),
            (&32.into(), &24.into())
        );
    }
    // Views by pose render like any other.
    let out = tmp.path().join("out");
    ok(&run(&[
        "render-reference",
        sidecar.to_str().unwrap(),
        "--spp",
        "4",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]));
    assert!(out.join("side_again.exr").is_file());
}

#[test]
fn bad_camera_poses_are_refused_with_the_sidecar_and_camera_named() {
    let tmp = tempfile::tempdir().unwrap();
    let look = |eye: &str, target: &str, up: &str| {
        format!("(name: \"v\", yfov: 0.7, pose: LookAt(eye: {eye}, target: {target}, up: {up}))")
    };
    let matrix = |rows: &str| format!("(name: \"v\", yfov: 0.7, pose: Matrix({rows}))");
    for (camera, views, needle) in [
        (
            look("(0, 1, 2)", "(0, 1, 2)", "(0, 1, 0)"),
            "",
            "its eye is its target",
        ),
        (
            look("(0, 1, 2)", "(0, 0, 0)", "(0, 1, 2)"),
            "",
            "along its line of sight",
        ),
        (
            "(name: \"v\", yfov: 3.5, pose: LookAt(eye: (0, 1, 2), target: (0, 0, 0)))".into(),
            "",
            "yfov must be in (0, π)",
        ),
        (
            matrix("((-1, 0, 0, 0), (0, 1, 0, 1), (0, 0, 1, 2), (0, 0, 0, 1))"),
            "",
            "a reflection",
        ),
        (
            matrix("((0, 0, 0, 0), (0, 1, 0, 1), (0, 0, 1, 2), (0, 0, 0, 1))"),
            "",
            "scales by 0",
        ),
        (
            matrix("((1, 0, 0, 0), (0, 1, 0, 1), (0, 0, 1, 2), (0, 0, 1, 1))"),
            "",
            "last row",
        ),
        (
            matrix("((1, 0, 0, 0), (0, 1, 0, NaN), (0, 0, 1, 2), (0, 0, 0, 1))"),
            "",
            "not finite",
        ),
        (
            "(name: \"cam_front\", yfov: 0.7, pose: LookAt(eye: (0, 1, 2), target: (0, 0, 0)))"
                .into(),
            "",
            "named twice",
        ),
        (
            look("(0, 1, 2)", "(0, 0, 0)", "(0, 1, 0)"),
            "\"w\"",
            "nor one of the sidecar's `cameras`",
        ),
    ] {
        let sidecar = posed(tmp.path(), views, &camera);
        let o = run(&["info", sidecar.to_str().unwrap()]);
        let err = fails(&o);
        assert!(
            err.contains("posed.ron") && err.contains(needle),
            "{camera}\n-> {err}"
        );
    }
}

#[test]
fn a_rerun_into_the_same_folder_leaves_nothing_of_the_last_run() {
    // A sphere model over all views, then the envmap over one view, into one folder: the
    // sphere model's files and the dropped view's images go; a file of the user's stays.
    let tmp = tempfile::tempdir().unwrap();
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.ron");
    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    let small = ["--height", "24", "--spp", "16", "--quiet", "--out", out_s];
    ok(&run(&[
        &["estimate", scene, "--model", "spheres:1"],
        &small[..],
    ]
    .concat()));
    for f in [
        "spheres/lights.ron",
        "spheres/blender.py",
        "spheres/mitsuba/scene.xml",
        "estimate/cam_side.exr",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    std::fs::create_dir(out.join("spheres/renders")).unwrap();
    std::fs::write(out.join("spheres/renders/mine.txt"), "mine").unwrap();
    ok(&run(&[
        &["estimate", scene, "--views", "cam_front"],
        &small[..],
    ]
    .concat()));
    for f in [
        "spheres/lights.ron",
        "spheres/blender.py",
        "spheres/mitsuba",
        "spheres/cam_front.exr",
        "estimate/cam_side.exr",
        "estimate/cam_side.error.png",
        "reference/cam_side.exr",
    ] {
        assert!(!out.join(f).exists(), "{f} is left from the last run");
    }
    assert!(out.join("spheres/renders/mine.txt").is_file());
    assert!(
        out.join("estimate/cam_front.exr").is_file() && out.join("mitsuba/scene.xml").is_file()
    );
}
