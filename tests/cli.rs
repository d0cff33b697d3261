//! The real `lightprobe` binary, run in temporary folders: outputs, determinism, and a table of
//! bad inputs that must each give one clear error line, a non-zero exit and no output files.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use glam::Vec3;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lightprobe"))
}

mod common;

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("the binary runs")
}

fn bundled_glb() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/tabletop/tabletop.glb")
}

/// A small, fast variant of the bundled scene in `dir`, with `extra` fields appended.
/// The bundled scene's key light.
const KEY_LIGHT: &str =
    "Sphere(center: (-1.8, 3.2, 1.5), radius: 0.25, radiance: (400.0, 360.0, 300.0))";

/// A sidecar of the bundled glTF at `width × height` and `spp`, with `lights` (none: the
/// field is left out) and `extra` fields.
fn bundled_sidecar((width, height): (u32, u32), spp: u32, lights: &str, extra: &str) -> String {
    let lights = if lights.is_empty() {
        String::new()
    } else {
        format!("    lights: [{lights}],\n")
    };
    format!(
        "Scene(\n    gltf: {:?},\n    image: (width: {width}, height: {height}),\n{lights}    render: (spp: {spp}, max_bounces: 2, seed: 1),\n{extra})\n",
        bundled_glb()
    )
}

fn small_scene(dir: &Path, extra: &str) -> PathBuf {
    let p = dir.join("scene.ron");
    std::fs::write(&p, bundled_sidecar((32, 24), 4, KEY_LIGHT, extra)).unwrap();
    p
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = match std::fs::read_dir(dir) {
        Ok(rd) => rd
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect(),
        Err(_) => Vec::new(),
    };
    v.sort();
    v
}

#[test]
fn render_reference_writes_images_aovs_and_report() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let out = tmp.path().join("out");
    let o = run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--aov",
        "depth,normal,albedo",
        "--quiet",
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(!stderr.contains(": started"), "--quiet: {stderr}");
    let want = [
        "cam_front.albedo.exr",
        "cam_front.depth.exr",
        "cam_front.exr",
        "cam_front.normal.exr",
        "cam_front.png",
        "cam_side.albedo.exr",
        "cam_side.depth.exr",
        "cam_side.exr",
        "cam_side.normal.exr",
        "cam_side.png",
        "render.json",
    ];
    assert_eq!(files_in(&out), want, "exactly these files, no temporaries");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("render.json")).unwrap()).unwrap();
    assert_eq!(report["views"].as_array().unwrap().len(), 2);
    assert_eq!(report["settings"]["spp"], 4);
    assert_eq!(report["triangles"], 95780);
    let img = lightprobe::imageio::read_exr(&out.join("cam_front.exr")).unwrap();
    assert_eq!((img.width, img.height), (32, 24));
    let mean = img.mean();
    assert!(mean.min_element() > 0.0 && mean.is_finite());
    assert_eq!(
        report["views"][0]["mean_rgb"][0].as_f64().unwrap() as f32,
        mean.x
    );
    // The buffers' contents, at pixel centres: where the centre sees geometry (all samples
    // of a pixel did: coverage 1) depth is a positive distance within the scene's reach, the
    // normal a unit vector and the albedo a reflectance in (0, 1]; where no sample did
    // (coverage 0), all three are zero.
    let read = |name: &str| lightprobe::imageio::read_exr(&out.join(name)).unwrap();
    for view in ["cam_front", "cam_side"] {
        let radiance = read(&format!("{view}.exr"));
        let coverage = radiance.alpha.as_ref().unwrap();
        let (depth, normal, albedo) = (
            read(&format!("{view}.depth.exr")),
            read(&format!("{view}.normal.exr")),
            read(&format!("{view}.albedo.exr")),
        );
        let (mut hit, mut miss) = (0, 0);
        for (i, &covered) in coverage.iter().enumerate() {
            let (d, n, a) = (depth.rgb[i], normal.rgb[i], albedo.rgb[i]);
            if covered == 1.0 {
                hit += 1;
                assert!(
                    d.x > 0.1 && d.x < 30.0 && d.x == d.y && d.y == d.z,
                    "{view} {i}: depth {d}"
                );
                assert!((n.length() - 1.0).abs() < 1e-3, "{view} {i}: normal {n}");
                assert!(
                    a.min_element() > 0.0 && a.max_element() <= 1.0,
                    "{view} {i}: albedo {a}"
                );
            } else if covered == 0.0 {
                miss += 1;
                assert!(
                    d == Vec3::ZERO && n == Vec3::ZERO && a == Vec3::ZERO,
                    "{view} {i}"
                );
            }
        }
        assert!(
            hit > 100 && miss > 10,
            "{view}: {hit} pixels on geometry, {miss} off it"
        );
    }
}

#[test]
fn same_bytes_at_one_and_two_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let mut outputs = Vec::new();
    for threads in ["1", "2"] {
        let out = tmp.path().join(format!("t{threads}"));
        let o = bin()
            .args([
                "render-reference",
                scene.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--quiet",
            ])
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap();
        assert!(o.status.success());
        outputs.push((
            std::fs::read(out.join("cam_front.exr")).unwrap(),
            std::fs::read(out.join("cam_side.exr")).unwrap(),
        ));
    }
    assert!(
        outputs[0] == outputs[1],
        "EXR bytes differ between 1 and 2 threads"
    );
}

#[test]
fn a_view_renders_the_same_alone_or_with_others() {
    // A view's random stream comes from its name, not its place in the list.
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let mut side = Vec::new();
    for (dir, views) in [
        ("all", None),
        ("side", Some("cam_side")),
        ("rev", Some("cam_side,cam_front")),
    ] {
        let out = tmp.path().join(dir);
        let mut args = vec![
            "render-reference",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--quiet",
        ];
        if let Some(v) = views {
            args.extend(["--views", v]);
        }
        let o = run(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        side.push(std::fs::read(out.join("cam_side.exr")).unwrap());
    }
    assert!(
        side[0] == side[1] && side[1] == side[2],
        "cam_side differs with the selection"
    );
}

#[test]
fn compare_reports_metrics_and_heatmap() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let s = scene.to_str().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    assert!(
        run(&[
            "render-reference",
            s,
            "--out",
            a.to_str().unwrap(),
            "--quiet"
        ])
        .status
        .success()
    );
    assert!(
        run(&[
            "render-reference",
            s,
            "--out",
            b.to_str().unwrap(),
            "--quiet",
            "--seed",
            "2"
        ])
        .status
        .success()
    );
    let (fa, fb) = (a.join("cam_front.exr"), b.join("cam_front.exr"));
    let heat = tmp.path().join("heat.png");
    let o = run(&[
        "compare",
        fb.to_str().unwrap(),
        fa.to_str().unwrap(),
        "--json",
        "--heatmap",
        heat.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rel = m["rel_mae"].as_f64().unwrap();
    // Two 4-spp renders differ by their noise only: measured 0.121–0.135 for seed 1 against
    // seeds 2–5 (cam_front, 32×24).
    assert!(
        (0.08..0.2).contains(&rel),
        "two seeds differ by noise only: {rel}"
    );
    assert!(
        m["masked_out"].as_u64().unwrap() > 0,
        "the background is masked"
    );
    // The heat map's contents: the 32×24 image zoomed 8× at the layout's corner, each pixel
    // the diverging colour map at its signed error (channel mean, over the reference's mean
    // radiance) over the scale, grey where masked out.
    let (png, _) = lightprobe::imageio::read_photo(
        &heat,
        lightprobe::imageio::Decoding {
            linear: true,
            saturation: None,
        },
    )
    .unwrap();
    let layout = lightprobe::output::figure::HeatMapLayout::of(32, 24);
    assert_eq!(layout.zoom, 8);
    assert!(png.width >= layout.left + 32 * 8 && png.height >= layout.top + 24 * 8);
    let scale = m["heatmap"]["scale"].as_f64().unwrap() as f32;
    let (x, r) = (
        lightprobe::imageio::read_exr(&fb).unwrap(),
        lightprobe::imageio::read_exr(&fa).unwrap(),
    );
    let alpha = r.alpha.as_ref().unwrap();
    let (sum, n) = (0..r.rgb.len())
        .filter(|&i| alpha[i] > 0.0)
        .fold((0.0f64, 0), |(s, n), i| {
            (s + r.rgb[i].element_sum() as f64 / 3.0, n + 1)
        });
    let mean = (sum / n as f64) as f32;
    let byte = |v: f32| (v * 255.0).round() as i32;
    let mut worst = 0;
    for py in 0..24usize {
        for px in 0..32usize {
            let i = py * 32 + px;
            let (sx, sy) = (
                layout.left as usize + px * 8 + 4,
                layout.top as usize + py * 8 + 4,
            );
            let shown = png.rgb[sy * png.width as usize + sx];
            let want = if alpha[i] > 0.0 {
                let err = (x.rgb[i] - r.rgb[i]).element_sum() / 3.0 / mean;
                lightprobe::output::figure::diverging(err / scale).map(|c| c as i32)
            } else {
                lightprobe::output::figure::MASKED.map(|c| c as i32)
            };
            for c in 0..3 {
                worst = worst.max((byte(shown[c]) - want[c]).abs());
            }
        }
    }
    assert!(
        worst <= 1,
        "a heat-map pixel is {worst} off its error's colour"
    );
    let o = run(&[
        "compare",
        fa.to_str().unwrap(),
        fa.to_str().unwrap(),
        "--json",
    ]);
    let m: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(m["rel_mae"].as_f64().unwrap(), 0.0);
}

#[test]
fn help_is_available_for_every_command() {
    for cmd in [
        &["--help"][..],
        &["render-reference", "--help"],
        &["compare", "--help"],
        &["estimate", "--help"],
        &["export-envmap", "--help"],
        &["import-envmap", "--help"],
        &["info", "--help"],
        &["scenarios", "--help"],
        &["sweep", "--help"],
        &["report", "--help"],
        &["schema", "--help"],
    ] {
        let o = run(cmd);
        assert!(o.status.success());
        assert!(String::from_utf8_lossy(&o.stdout).contains("Usage"));
    }
}

#[test]
fn committed_schema_is_up_to_date() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/scene.schema.json");
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    let o = run(&["schema"]);
    assert!(o.status.success());
    assert!(
        committed == String::from_utf8(o.stdout).unwrap(),
        "schemas/scene.schema.json is stale: run `cargo run -- schema > schemas/scene.schema.json`"
    );
}

/// One bad-input case: files to create (name → content), arguments (with `{d}` for the
/// temporary folder), and a fragment the error line must contain.
struct Case {
    name: &'static str,
    files: Vec<(&'static str, Vec<u8>)>,
    args: Vec<&'static str>,
    expect: &'static str,
}

/// An EXR with a single luminance channel "Y" (no R, G, B).
fn luminance_only_exr() -> Vec<u8> {
    use exr::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("y.exr");
    let channel = AnyChannel::new("Y", FlatSamples::F32(vec![0.5f32; 12]));
    let layer = Layer::new(
        (4, 3),
        LayerAttributes::default(),
        Encoding::UNCOMPRESSED,
        AnyChannels::sort(vec![channel].into()),
    );
    Image::from_layer(layer).write().to_file(&p).unwrap();
    std::fs::read(p).unwrap()
}

/// An RGB EXR of `w × h` pixels, all `value`.
fn tiny_exr(w: u32, h: u32, value: f32) -> Vec<u8> {
    exr_bytes(w, h, value, None)
}

/// An RGB EXR of `w × h` pixels, all `value`, whose alpha (coverage) is zero everywhere.
fn uncovered_exr(w: u32, h: u32, value: f32) -> Vec<u8> {
    exr_bytes(w, h, value, Some(0.0))
}

/// The bytes of a `w × h` EXR of one RGB `value`, with a constant alpha if given.
fn exr_bytes(w: u32, h: u32, value: f32, alpha: Option<f32>) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.exr");
    let n = (w * h) as usize;
    let img = lightprobe::imageio::Image {
        width: w,
        height: h,
        rgb: vec![glam::Vec3::splat(value); n],
        alpha: alpha.map(|a| vec![a; n]),
    };
    lightprobe::imageio::write_exr(&p, &img).unwrap();
    std::fs::read(p).unwrap()
}

/// An 8×6 sidecar over `sky.gltf` (SKY_GLTF) lit by LIGHT, at `spp`.
fn sky_sidecar(spp: u32) -> String {
    format!(
        "Scene(gltf: \"sky.gltf\", image: (width: 8, height: 6), lights: [{LIGHT}], render: (spp: {spp}))"
    )
}

/// A glTF with one triangle at y = 0 and one camera above it looking up, away from it; its
/// material is Lambertian, so loading it says nothing.
const SKY_GLTF: &str = r#"{"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}], "nodes": [{"mesh": 0}, {"name": "up", "camera": 0, "translation": [0, 1, 0], "rotation": [0.70710678, 0, 0, 0.70710678]}], "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.01}}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}], "materials": [{"pbrMetallicRoughness": {"metallicFactor": 0}}], "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1]}], "bufferViews": [{"buffer": 0, "byteLength": 36}], "buffers": [{"byteLength": 36, "uri": "data:application/octet-stream;base64,AACAvwAAAAAAAIC/AACAPwAAAAAAAIC/AAAAAAAAAAAAAIA/"}]}"#;

fn sidecar(extra_fields: &str, lights: &str) -> Vec<u8> {
    format!(
        "Scene(\n  gltf: {:?},\n  image: (width: 16, height: 12),\n  lights: [{lights}],\n  render: (spp: 2),\n{extra_fields})\n",
        bundled_glb()
    )
    .into_bytes()
}

const ENV2: &str = "Envmap(rings: 2, radiance: [(1, 1, 1), (0.5, 0.5, 0.5)])";

const LIGHT: &str = "Sphere(center: (0, 3, 0), radius: 0.2, radiance: (10, 10, 10))";

fn cases() -> Vec<Case> {
    let glb = std::fs::read(bundled_glb()).unwrap();
    let render = vec![
        "render-reference",
        "{d}/scene.ron",
        "--out",
        "{d}/out",
        "--quiet",
    ];
    let c = |name, files, args: &Vec<&'static str>, expect| Case {
        name,
        files,
        args: args.clone(),
        expect,
    };
    vec![
        c(
            "missing sidecar",
            vec![],
            &render,
            "scene.ron: no such file",
        ),
        c(
            "unknown field",
            vec![("scene.ron", sidecar("  colour: 3,\n", LIGHT))],
            &render,
            "scene.ron:6:",
        ),
        c(
            "nan radius",
            vec![(
                "scene.ron",
                sidecar(
                    "",
                    "Sphere(center: (0, 3, 0), radius: NaN, radiance: (1, 1, 1))",
                ),
            )],
            &render,
            "scene.ron:4:",
        ),
        c(
            "negative radius",
            vec![(
                "scene.ron",
                sidecar(
                    "",
                    "Sphere(center: (0, 3, 0), radius: -1, radiance: (1, 1, 1))",
                ),
            )],
            &render,
            "must be a finite number > 0",
        ),
        c(
            "negative radiance",
            vec![(
                "scene.ron",
                sidecar(
                    "",
                    "Sphere(center: (0, 3, 0), radius: 1, radiance: (1, -1, 1))",
                ),
            )],
            &render,
            "radiance must be",
        ),
        c(
            "zero image size",
            vec![(
                "scene.ron",
                format!(
                    "Scene(gltf: {:?}, image: (width: 0, height: 12))",
                    bundled_glb()
                )
                .into_bytes(),
            )],
            &render,
            "image side",
        ),
        c(
            "syntax error",
            vec![(
                "scene.ron",
                b"Scene(gltf: \"a.glb\", image: (width: 4 height: 3))".to_vec(),
            )],
            &render,
            "scene.ron:1:",
        ),
        c(
            "wrong type",
            vec![(
                "scene.ron",
                b"Scene(gltf: 5, image: (width: 4, height: 3))".to_vec(),
            )],
            &render,
            "scene.ron:1:",
        ),
        c(
            "spp zero in sidecar",
            vec![(
                "scene.ron",
                String::from_utf8(sidecar("", LIGHT))
                    .unwrap()
                    .replace("spp: 2", "spp: 0")
                    .into_bytes(),
            )],
            &render,
            "spp must be",
        ),
        c(
            "scenarios from a glTF",
            vec![("scene.glb", glb.clone())],
            &vec!["scenarios", "--scene", "{d}/scene.glb", "--out", "{d}/out"],
            "scene.glb: is a glTF; scenarios copy a sidecar with new lights",
        ),
        c(
            "missing glb",
            vec![(
                "scene.ron",
                b"Scene(gltf: \"nope.glb\", image: (width: 4, height: 3))".to_vec(),
            )],
            &render,
            "nope.glb: no such file",
        ),
        c(
            "garbage glb",
            vec![
                ("bad.glb", b"glTF\x02\x00\x00\x00garbage-garbage".to_vec()),
                (
                    "scene.ron",
                    b"Scene(gltf: \"bad.glb\", image: (width: 4, height: 3))".to_vec(),
                ),
            ],
            &render,
            "bad.glb: not a valid glTF",
        ),
        c(
            "truncated glb",
            vec![
                ("cut.glb", glb[..4096].to_vec()),
                (
                    "scene.ron",
                    b"Scene(gltf: \"cut.glb\", image: (width: 4, height: 3))".to_vec(),
                ),
            ],
            &render,
            "cut.glb: not a valid glTF 2.0 file: truncated (the GLB declares",
        ),
        c(
            "gltf that is not json",
            vec![
                ("x.gltf", b"{ this is not json".to_vec()),
                (
                    "scene.ron",
                    b"Scene(gltf: \"x.gltf\", image: (width: 4, height: 3))".to_vec(),
                ),
            ],
            &render,
            "x.gltf: not a valid glTF",
        ),
        c(
            "gltf with no scene content",
            vec![
                (
                    "empty.gltf",
                    br#"{"asset":{"version":"2.0"},"scenes":[{"nodes":[]}],"scene":0}"#.to_vec(),
                ),
                (
                    "scene.ron",
                    b"Scene(gltf: \"empty.gltf\", image: (width: 4, height: 3))".to_vec(),
                ),
            ],
            &render,
            "empty.gltf: has no triangles",
        ),
        c(
            "missing albedo map",
            vec![(
                "scene.ron",
                sidecar("  albedo: { \"table\": Map(\"nope.png\") },\n", LIGHT),
            )],
            &render,
            "nope.png: no such file",
        ),
        c(
            "undecodable albedo map",
            vec![
                ("bad.png", b"\x89PNG\r\n\x1a\nnope".to_vec()),
                (
                    "scene.ron",
                    sidecar("  albedo: { \"table\": Map(\"bad.png\") },\n", LIGHT),
                ),
            ],
            &render,
            "bad.png: cannot decode",
        ),
        c(
            "albedo of unknown material",
            vec![(
                "scene.ron",
                sidecar(
                    "  albedo: { \"tabel\": Constant((0.5, 0.5, 0.5)) },\n",
                    LIGHT,
                ),
            )],
            &render,
            "\"tabel\"",
        ),
        c(
            "unknown view",
            vec![("scene.ron", sidecar("  views: [\"cam_top\"],\n", LIGHT))],
            &render,
            "\"cam_top\"",
        ),
        c(
            "output is a file",
            vec![
                ("scene.ron", sidecar("", LIGHT)),
                ("out", b"i am a file".to_vec()),
            ],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out/sub",
                "--quiet",
            ]
            .to_vec(),
            "out/sub",
        ),
        c(
            "spp zero flag",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--spp",
                "0",
            ]
            .to_vec(),
            "'--spp <SPP>': 0 is not in 1..=1048576",
        ),
        c(
            "compare missing image",
            vec![],
            &["compare", "{d}/a.exr", "{d}/b.exr"].to_vec(),
            "a.exr: no such file",
        ),
        c(
            "compare garbage exr",
            vec![
                ("a.exr", b"v/1\x01 garbage".to_vec()),
                ("b.exr", b"x".to_vec()),
            ],
            &["compare", "{d}/a.exr", "{d}/b.exr"].to_vec(),
            "a.exr: cannot read",
        ),
        c(
            "info missing sidecar",
            vec![],
            &["info", "{d}/scene.ron"].to_vec(),
            "scene.ron: no such file",
        ),
        c(
            "export width too small",
            vec![("e.ron", ENV2.into())],
            &[
                "export-envmap",
                "{d}/e.ron",
                "--out",
                "{d}/out/e.exr",
                "--width",
                "4",
            ]
            .to_vec(),
            "--width",
        ),
        c(
            "export width absurd",
            vec![("e.ron", ENV2.into())],
            &[
                "export-envmap",
                "{d}/e.ron",
                "--out",
                "{d}/out/e.exr",
                "--width",
                "100000",
            ]
            .to_vec(),
            "--width",
        ),
        c(
            "envmap wrong count",
            vec![("e.ron", b"Envmap(rings: 2, radiance: [(1, 1, 1)])".to_vec())],
            &["export-envmap", "{d}/e.ron", "--out", "{d}/out/e.exr"].to_vec(),
            "e.ron: 2 rings have 2 cells",
        ),
        c(
            "envmap zero rings",
            vec![("e.ron", b"Envmap(rings: 0, radiance: [])".to_vec())],
            &["export-envmap", "{d}/e.ron", "--out", "{d}/out/e.exr"].to_vec(),
            "e.ron:1:",
        ),
        c(
            "envmap too many rings",
            vec![("e.ron", b"Envmap(rings: 1001, radiance: [])".to_vec())],
            &["export-envmap", "{d}/e.ron", "--out", "{d}/out/e.exr"].to_vec(),
            "rings",
        ),
        c(
            "envmap nan",
            vec![(
                "e.ron",
                b"Envmap(rings: 2, radiance: [(1, 1, 1), (NaN, 1, 1)])".to_vec(),
            )],
            &["export-envmap", "{d}/e.ron", "--out", "{d}/out/e.exr"].to_vec(),
            "e.ron:1:",
        ),
        c(
            "envmap negative",
            vec![(
                "e.ron",
                b"Envmap(rings: 2, radiance: [(1, 1, 1), (1, -2, 1)])".to_vec(),
            )],
            &["export-envmap", "{d}/e.ron", "--out", "{d}/out/e.exr"].to_vec(),
            "radiance must be",
        ),
        c(
            "render with missing envmap",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--envmap",
                "{d}/nope.ron",
            ]
            .to_vec(),
            "nope.ron: no such file",
        ),
        c(
            "render with no light at all",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--no-sphere-lights",
            ]
            .to_vec(),
            "nothing lights the scene",
        ),
        c(
            "import rings zero",
            vec![],
            &[
                "import-envmap",
                "{d}/x.exr",
                "--rings",
                "0",
                "--out",
                "{d}/out/e.ron",
            ]
            .to_vec(),
            "--rings",
        ),
        c(
            "import missing exr",
            vec![],
            &[
                "import-envmap",
                "{d}/x.exr",
                "--rings",
                "5",
                "--out",
                "{d}/out/e.ron",
            ]
            .to_vec(),
            "x.exr: no such file",
        ),
        c(
            "estimate rings absurd for memory",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--rings",
                "1000",
                "--quiet",
            ]
            .to_vec(),
            "would need about",
        ),
        c(
            "estimate trusting the albedo of a material the scene lacks",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--fit-albedo",
                "materials",
                "--trust-albedo",
                "table,marble",
                "--quiet",
            ]
            .to_vec(),
            "scene.ron: --trust-albedo names material \"marble\", which the scene does not have",
        ),
        c(
            "estimate fitting the albedo and per-view exposures while choosing the model",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--fit-albedo",
                "materials",
                "--exposure",
                "per-view",
                "--model",
                "auto",
                "--quiet",
            ]
            .to_vec(),
            "fitting the albedo and per-view exposures together needs one light model",
        ),
        c(
            "estimate fitting the albedo without the evaluation",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--fit-albedo",
                "materials",
                "--fit-only",
                "--quiet",
            ]
            .to_vec(),
            "--fit-albedo compares each material's re-rendered pixels",
        ),
        c(
            "estimate reference of the wrong size",
            vec![
                ("scene.ron", sidecar("  views: [\"cam_front\"],\n", LIGHT)),
                ("ref/cam_front.exr", tiny_exr(8, 6, 0.5)),
            ],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--reference",
                "{d}/ref",
                "--quiet",
            ]
            .to_vec(),
            "cam_front.exr: is 8×6, but view \"cam_front\" renders 16×12",
        ),
        c(
            "view listed twice in the sidecar",
            vec![(
                "scene.ron",
                sidecar("  views: [\"cam_front\", \"cam_front\"],\n", LIGHT),
            )],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--quiet",
            ]
            .to_vec(),
            "scene.ron: view \"cam_front\" is listed twice",
        ),
        c(
            "view listed twice in --views",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--views",
                "cam_side,cam_side",
                "--quiet",
            ]
            .to_vec(),
            "view \"cam_side\" is listed twice in the views asked for",
        ),
        c(
            "estimate where no view sees geometry",
            vec![
                ("sky.gltf", SKY_GLTF.as_bytes().to_vec()),
                ("scene.ron", sky_sidecar(2).into_bytes()),
            ],
            &["estimate", "{d}/scene.ron", "--out", "{d}/out", "--quiet"].to_vec(),
            "scene.ron: no view has a pixel to fit (up: it sees no scene geometry)",
        ),
        c(
            "two cameras of one name",
            vec![
                (
                    "sky.gltf",
                    SKY_GLTF
                        .replace(
                            r#"{"mesh": 0}, "#,
                            r#"{"mesh": 0}, {"name": "up", "camera": 0}, "#,
                        )
                        .replace(r#"[{"nodes": [0, 1]}]"#, r#"[{"nodes": [0, 1, 2]}]"#)
                        .into_bytes(),
                ),
                ("scene.ron", sky_sidecar(2).into_bytes()),
            ],
            &render,
            "sky.gltf: has two camera nodes named \"up\"",
        ),
        c(
            "compare against a reference that covers nothing",
            vec![
                ("a.exr", tiny_exr(4, 3, 0.5)),
                ("b.exr", uncovered_exr(4, 3, 0.5)),
            ],
            &["compare", "{d}/a.exr", "{d}/b.exr"].to_vec(),
            "b.exr: its alpha (coverage) is zero everywhere, so no pixel is compared; pass --no-mask",
        ),
        c(
            "negative image size",
            vec![(
                "scene.ron",
                format!(
                    "Scene(gltf: {:?}, image: (width: -5, height: 3))",
                    bundled_glb()
                )
                .into_bytes(),
            )],
            &render,
            "integer out of range for this field (negative, or too large)",
        ),
        c(
            "--out names an existing file",
            vec![
                ("scene.ron", sidecar("", LIGHT)),
                ("taken", b"a file".to_vec()),
            ],
            &[
                "render-reference",
                "{d}/scene.ron",
                "--out",
                "{d}/taken",
                "--quiet",
            ]
            .to_vec(),
            "taken: exists and is not a folder",
        ),
        c(
            "--reference names a file",
            vec![
                ("scene.ron", sidecar("", LIGHT)),
                ("refs", b"a file".to_vec()),
            ],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--reference",
                "{d}/refs",
                "--quiet",
            ]
            .to_vec(),
            "refs: is not a folder",
        ),
        c(
            "time limit not a number",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--time-limit",
                "nan",
                "--quiet",
            ]
            .to_vec(),
            "--time-limit must be a positive number of seconds",
        ),
        c(
            "--rings-candidates out of range",
            vec![("scene.ron", sidecar("", LIGHT))],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--rings",
                "auto",
                "--rings-candidates",
                "0,3",
                "--quiet",
            ]
            .to_vec(),
            "--rings-candidates must be between 1 and",
        ),
        c(
            "report of a missing folder",
            vec![],
            &["report", "{d}/nothing"].to_vec(),
            "nothing: no such folder",
        ),
        c(
            "import into a missing folder",
            vec![("x.exr", tiny_exr(8, 4, 0.5))],
            &[
                "import-envmap",
                "{d}/x.exr",
                "--rings",
                "1",
                "--out",
                "{d}/none/e.ron",
            ]
            .to_vec(),
            "/none does not exist",
        ),
        c(
            "estimate reference with NaN",
            vec![
                ("scene.ron", sidecar("  views: [\"cam_front\"],\n", LIGHT)),
                ("ref/cam_front.exr", tiny_exr(16, 12, f32::NAN)),
            ],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--reference",
                "{d}/ref",
                "--quiet",
            ]
            .to_vec(),
            "is not finite",
        ),
        c(
            "estimate missing reference view",
            vec![
                ("scene.ron", sidecar("", LIGHT)),
                ("ref/cam_front.exr", tiny_exr(16, 12, 0.5)),
            ],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--reference",
                "{d}/ref",
                "--quiet",
            ]
            .to_vec(),
            "ref: has no reference for view \"cam_side\": expected cam_side.exr, .hdr, .png, .jpg or .jpeg",
        ),
        c(
            "compare exr without RGB channels",
            vec![
                ("y.exr", luminance_only_exr()),
                ("b.exr", tiny_exr(4, 3, 0.5)),
            ],
            &["compare", "{d}/y.exr", "{d}/b.exr"].to_vec(),
            "y.exr: cannot read",
        ),
        c(
            "compare truncated exr",
            vec![
                ("t.exr", {
                    let e = tiny_exr(16, 12, 0.5);
                    e[..e.len() / 2].to_vec()
                }),
                ("b.exr", tiny_exr(16, 12, 0.5)),
            ],
            &["compare", "{d}/t.exr", "{d}/b.exr"].to_vec(),
            "t.exr: cannot read",
        ),
        c(
            "compare sizes differ",
            vec![
                ("a.exr", tiny_exr(8, 6, 0.5)),
                ("b.exr", tiny_exr(16, 12, 0.5)),
            ],
            &["compare", "{d}/a.exr", "{d}/b.exr"].to_vec(),
            "is 8×6 but the reference",
        ),
        c(
            "estimate truncated reference",
            vec![
                ("scene.ron", sidecar("  views: [\"cam_front\"],\n", LIGHT)),
                ("ref/cam_front.exr", {
                    let e = tiny_exr(16, 12, 0.5);
                    e[..e.len() / 2].to_vec()
                }),
            ],
            &[
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--reference",
                "{d}/ref",
                "--quiet",
            ]
            .to_vec(),
            "cam_front.exr: cannot read",
        ),
    ]
}

#[test]
fn bad_inputs_fail_cleanly() {
    let mut failures = Vec::new();
    for case in cases() {
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        for (name, content) in &case.files {
            let p = d.join(name);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, content).unwrap();
        }
        let before = files_in(d);
        let args: Vec<String> = case
            .args
            .iter()
            .map(|a| a.replace("{d}", d.to_str().unwrap()))
            .collect();
        let o = bin().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        let mut why = Vec::new();
        if o.status.success() {
            why.push("exited 0".to_string());
        }
        if err.contains("panicked") || err.contains("RUST_BACKTRACE") {
            why.push("panicked".into());
        }
        if err.trim().lines().count() != 1 {
            why.push(format!("{} lines of error", err.trim().lines().count()));
        }
        if !err.contains(case.expect) {
            why.push(format!("no {:?}", case.expect));
        }
        let out = d.join("out");
        if out.is_dir() && !files_in(&out).is_empty() {
            why.push(format!("left output files {:?}", files_in(&out)));
        }
        let after: Vec<String> = files_in(d).into_iter().filter(|f| f != "out").collect();
        let before: Vec<String> = before.into_iter().filter(|f| f != "out").collect();
        if after != before {
            why.push(format!("left files {after:?}"));
        }
        if !why.is_empty() {
            failures.push(format!(
                "{}: {} — stderr: {}",
                case.name,
                why.join(", "),
                err.trim()
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "{} bad-input cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn envmap_export_import_round_trip_and_coarse_import_error() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let cells: Vec<String> = (0..26)
        .map(|i| format!("({}, {}, 0.25)", i as f32 * 0.5, 26 - i))
        .collect();
    std::fs::write(
        d.join("e.ron"),
        format!("Envmap(rings: 6, radiance: [{}])", cells.join(", ")),
    )
    .unwrap();
    let p = |f: &str| d.join(f).to_str().unwrap().to_string();
    for target in ["mitsuba", "blender", "pbrt-v3"] {
        let o = run(&[
            "export-envmap",
            &p("e.ron"),
            "--out",
            &p("e.exr"),
            "--width",
            "256",
            "--target",
            target,
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let o = run(&[
            "import-envmap",
            &p("e.exr"),
            "--rings",
            "6",
            "--out",
            &p("back.ron"),
            "--target",
            target,
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let a = lightprobe::envmap::Envmap::load(&d.join("e.ron")).unwrap();
        let b = lightprobe::envmap::Envmap::load(&d.join("back.ron")).unwrap();
        assert_eq!(a.radiance(), b.radiance(), "{target}");
    }
    let img = lightprobe::imageio::read_exr(&d.join("e.exr")).unwrap();
    assert_eq!((img.width, img.height), (256, 128));
    // Too coarse: a 256×128 image cannot fill 200 rings' cells.
    let o = run(&[
        "import-envmap",
        &p("e.exr"),
        "--rings",
        "200",
        "--out",
        &p("x.ron"),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("too coarse"));
    assert!(!d.join("x.ron").exists());
}

#[test]
fn unknown_enum_values_are_usage_errors() {
    for args in [
        &[
            "export-envmap",
            "e.ron",
            "--out",
            "x.exr",
            "--target",
            "maya",
        ][..],
        &[
            "export-envmap",
            "e.ron",
            "--out",
            "x.exr",
            "--filter",
            "gauss",
        ],
    ] {
        let o = run(args);
        assert_eq!(o.status.code(), Some(2));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("invalid value") && !err.contains("panicked"),
            "{err}"
        );
    }
}

#[test]
fn estimate_runs_end_to_end_and_reports() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let out = tmp.path().join("out");
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--rings",
        "5",
        "--spp",
        "16",
        "--quiet",
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["cells"], 18);
    assert_eq!(report["views"].as_array().unwrap().len(), 2);
    let rel = report["rel_mae"].as_f64().unwrap();
    let floor = report["noise_floor_rel_mae"].as_f64().unwrap();
    assert!(
        // 16 spp, 5 rings: measured 0.40 (floor 0.13); 1.5× that fails a regression.
        rel.is_finite() && rel > floor && rel < 0.6 && floor > 0.0,
        "{rel} {floor}"
    );
    assert!(
        report["channels"]
            .as_array()
            .unwrap()
            .iter()
            .all(|c| c["converged"] == true)
    );
    for f in [
        "envmap.ron",
        "envmap.exr",
        "report.json",
        "reference/cam_front.exr",
        "estimate/cam_front.exr",
        "estimate/cam_front.error.png",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    check_results_page(&out);
    let env = lightprobe::envmap::Envmap::load(&out.join("envmap.ron")).unwrap();
    assert_eq!(env.grid.rings(), 5);
    // Fitting the written references again (--reference) gives the same envmap: same seeds.
    let out2 = tmp.path().join("out2");
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
        "--rings",
        "5",
        "--spp",
        "16",
        "--reference",
        out.join("reference").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    // Not a terminal: a line as each phase starts and ends, up to the written outputs.
    for line in [
        "lightprobe: estimate: started",
        "lightprobe: estimate: 100% after",
        "lightprobe: writing outputs: started",
        "lightprobe: writing outputs: 100% after",
    ] {
        assert!(stderr.contains(line), "{line:?} not in {stderr}");
    }
    let env2 = lightprobe::envmap::Envmap::load(&out2.join("envmap.ron")).unwrap();
    assert_eq!(env.radiance(), env2.radiance());
    // --fit-only: the same envmap, no evaluation renders and no errors in the report.
    let out3 = tmp.path().join("out3");
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--out",
        out3.to_str().unwrap(),
        "--rings",
        "5",
        "--spp",
        "16",
        "--quiet",
        "--fit-only",
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(report["rel_mae"].is_null() && report["views"][0]["estimate"].is_null());
    assert!(!out3.join("estimate/cam_front.exr").exists());
    assert_eq!(
        lightprobe::envmap::Envmap::load(&out3.join("envmap.ron"))
            .unwrap()
            .radiance(),
        env.radiance()
    );
}

/// The results page of the estimate in `out`: every image it shows is a file there, and every
/// number it tags holds report.json's value at its path (what a browser shows is checked by
/// `scripts/check_page.py`).
fn check_results_page(out: &Path) {
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let attr = |tag: &str, name: &str| -> Option<String> {
        let i = tag.find(&format!("{name}=\""))? + name.len() + 2;
        Some(tag[i..i + tag[i..].find('"')?].to_string())
    };
    let mut images = 0;
    // The page's links are percent-encoded paths.
    let decode = |s: &str| -> String {
        let b = s.as_bytes();
        let (mut out, mut i) = (Vec::new(), 0);
        while i < b.len() {
            if b[i] == b'%' {
                out.push(u8::from_str_radix(&s[i + 1..i + 3], 16).unwrap());
                i += 3;
            } else {
                out.push(b[i]);
                i += 1;
            }
        }
        String::from_utf8(out).unwrap()
    };
    for tag in html.split("<img ").skip(1) {
        let src = decode(&attr(tag, "src").unwrap());
        assert!(
            out.join(&src).is_file(),
            "the page shows {src}, which is not there"
        );
        images += 1;
    }
    // Per view: reference, estimate, error; the envmap; per corrected texture: as given, as
    // fitted, the change.
    let textures = report["albedo"]["texels"].as_array().map_or(0, Vec::len);
    assert!(images == 2 * 3 + 1 + 3 * textures, "{images} images");
    let mut numbers = 0;
    for tag in html.split("<td class=\"num\" ").skip(1) {
        let path = attr(tag, "data-json").unwrap();
        let value: serde_json::Value =
            serde_json::from_str(&attr(tag, "data-value").unwrap().replace("&quot;", "\""))
                .unwrap();
        let want = path
            .split('.')
            .fold(&report, |v, k| match k.parse::<usize>() {
                Ok(i) => &v[i],
                Err(_) => &v[k],
            });
        assert_eq!(&value, want, "{path}");
        numbers += 1;
    }
    assert!(numbers >= 8, "{numbers} numbers");
    for must in ["rel_mae", "noise_floor_rel_mae", "views.1.estimate.rel_mae"] {
        assert!(html.contains(&format!("data-json=\"{must}\"")), "{must}");
    }
}

/// References of `scene` rendered into `dir/refs` under a warm 5-ring sky (a light a 5-ring
/// fit can match, with a key from one side).
fn sky_references(dir: &Path, scene: &Path) -> PathBuf {
    let grid = lightprobe::envmap::RingGrid::new(5);
    let sky: Vec<glam::Vec3> = (0..grid.cell_count() as u32)
        .map(|c| {
            let d = grid.center(c);
            let warm =
                glam::Vec3::new(3.0, 2.4, 1.6) * d.dot(glam::Vec3::new(-0.5, 0.8, 0.3)).max(0.0);
            glam::Vec3::new(0.3, 0.4, 0.6) * (0.4 + d.y.max(0.0)) + warm
        })
        .collect();
    let env = dir.join("sky.ron");
    lightprobe::envmap::Envmap::new(5, sky)
        .unwrap()
        .save(&env)
        .unwrap();
    let refs = dir.join("refs");
    let o = run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--out",
        refs.to_str().unwrap(),
        "--envmap",
        env.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    refs
}

#[test]
fn estimate_fits_the_albedo_and_writes_it_back() {
    // References rendered under a 5-ring sky (a light the 5-ring fit can match) with the
    // scene's own albedo: the fitted albedo must come back to it, be reported per material,
    // and go into the written glTF and the page.
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene.ron");
    std::fs::write(&scene, bundled_sidecar((96, 72), 128, "", "")).unwrap();
    let refs = sky_references(tmp.path(), &scene);
    let out = tmp.path().join("out");
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--reference",
        refs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--rings",
        "5",
        "--spp",
        "128",
        "--fit-albedo",
        "materials",
        "--trust-albedo",
        "table",
        "--quiet",
    ]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{stderr}");
    assert!(stdout.contains("albedo fitted per material"), "{stdout}");
    // --quiet: no phase is announced, none counted in tenths (stderr is not a terminal).
    assert!(
        !stderr.contains(": started") && !stderr.contains("% after"),
        "{stderr}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let albedo = &report["albedo"];
    assert_eq!(albedo["method"], "joint");
    assert_eq!(albedo["trusted"][0], "table");
    assert_eq!(albedo["converged"], true, "{albedo}");
    let materials = albedo["materials"].as_array().unwrap();
    let named = |n: &str| materials.iter().find(|m| m["name"] == n).unwrap();
    assert_eq!(named("table")["status"], "trusted");
    let fitted: Vec<&serde_json::Value> = materials
        .iter()
        .filter(|m| m["status"] == "fitted")
        .collect();
    assert!(fitted.len() >= 4, "{albedo}");
    for m in &fitted {
        for c in 0..3 {
            let k = m["multiplier"][c].as_f64().unwrap();
            assert!((k - 1.0).abs() < 0.03, "{m}");
        }
    }
    // The glTF written beside the estimate carries the fitted albedo.
    let doc = common::glb_json(&out.join("scene.glb"));
    let written = doc["materials"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "torus")
        .unwrap()["pbrMetallicRoughness"]["baseColorFactor"]
        .clone();
    for c in 0..3 {
        let fitted = named("torus")["fitted"][c].as_f64().unwrap();
        assert!(
            (written[c].as_f64().unwrap() - fitted).abs() < 1e-6,
            "{written}"
        );
    }
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert!(html.contains("Albedo (--fit-albedo)"));
    check_results_page(&out);
}

#[test]
fn estimate_takes_a_baked_shadow_out_of_a_texture() {
    // References of the bundled scene (true table texture) under a 5-ring sky; the estimate's
    // scene has the shadow-baked table texture (scenes/tabletop/baked_shadow). `--fit-albedo
    // texels` must correct the table's texture (its correction brightens the shadow toward
    // 1/0.4), write it beside the glTF, point the glTF at it, and show it on the page.
    let tmp = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let sidecar = |albedo: &str| bundled_sidecar((96, 72), 128, "", albedo);
    let truth = tmp.path().join("truth.ron");
    std::fs::write(&truth, sidecar("")).unwrap();
    let baked = tmp.path().join("baked.ron");
    let map = root.join("scenes/tabletop/baked_shadow/table_baked.png");
    std::fs::write(
        &baked,
        sidecar(&format!("albedo: {{ \"table\": Map({map:?}) }},")),
    )
    .unwrap();
    let refs = sky_references(tmp.path(), &truth);
    let out = tmp.path().join("out");
    let estimate = |extra: &[&str]| {
        let mut args = vec![
            "estimate",
            baked.to_str().unwrap(),
            "--reference",
            refs.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--rings",
            "5",
            "--spp",
            "128",
            "--quiet",
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    // The texel flags mean nothing without texels.
    let o = estimate(&["--fit-albedo", "materials", "--texel-grid", "16"]);
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("--fit-albedo texels"), "{stderr}");
    let o = estimate(&[
        "--fit-albedo",
        "texels",
        "--trust-albedo",
        "sphere_white",
        "--texel-grid",
        "16",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("texels corrected in"), "{stdout}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let albedo = &report["albedo"];
    assert_eq!(albedo["fit"], "texels");
    let texels = albedo["texels"].as_array().unwrap();
    assert_eq!(texels.len(), 1, "{albedo}");
    let t = &texels[0];
    assert_eq!(t["material"], "table");
    assert_eq!(t["grid"][0], 16);
    assert!(t["range"][1].as_f64().unwrap() > 1.5, "{t}");
    let file = t["file"].as_str().unwrap();
    assert!(out.join(file).is_file(), "{file}");
    // The written glTF uses it for the table.
    let doc = common::glb_json(&out.join("scene.glb"));
    let table = doc["materials"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "table")
        .unwrap();
    let index = table["pbrMetallicRoughness"]["baseColorTexture"]["index"]
        .as_u64()
        .unwrap() as usize;
    let source = doc["textures"][index]["source"].as_u64().unwrap() as usize;
    assert_eq!(doc["images"][source]["uri"], file);
    // The glTF's texture × factor is the albedo the Mitsuba export renders (its linear EXR),
    // within 8-bit sRGB.
    let back = lightprobe::scene::Scene::load(&out.join("scene.glb")).unwrap();
    let m = t["index"].as_u64().unwrap() as usize;
    let lightprobe::scene::Albedo::Texture { texture, factor } = &back.materials[m].albedo else {
        panic!("the exported table is textured");
    };
    let exr =
        lightprobe::imageio::read_exr(&out.join(format!("mitsuba/textures/{m}.exr"))).unwrap();
    assert_eq!((exr.width, exr.height), (texture.width, texture.height));
    let worst = texture
        .texels
        .iter()
        .zip(&exr.rgb)
        .map(|(a, b)| ((*a * *factor - *b).abs() / (*b + 0.01)).max_element())
        .fold(0.0f32, f32::max);
    assert!(worst < 0.06, "glTF and Mitsuba textures differ by {worst}");
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert!(html.contains("Texels (--fit-albedo texels)"));
    for f in ["given", "fitted", "change"] {
        assert!(
            out.join(format!("figures/texels_0_{f}.png")).is_file(),
            "{f}"
        );
    }
    check_results_page(&out);
}

#[test]
fn estimate_leaves_out_a_view_that_sees_nothing() {
    // SKY_GLTF plus a second camera above the triangle looking down at it.
    let gltf = SKY_GLTF
        .replace(
            r#""scenes": [{"nodes": [0, 1]}]"#,
            r#""scenes": [{"nodes": [0, 1, 2]}]"#,
        )
        .replace(
            r#"{"mesh": 0}, "#,
            r#"{"mesh": 0}, {"name": "down", "camera": 0, "translation": [0, 1, 0], "rotation": [-0.70710678, 0, 0, 0.70710678]}, "#,
        );
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::write(d.join("sky.gltf"), gltf).unwrap();
    std::fs::write(d.join("scene.ron"), sky_sidecar(4)).unwrap();
    let out = d.join("out");
    let o = run(&[
        "estimate",
        d.join("scene.ron").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--rings",
        "3",
        "--json",
        "--quiet",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains(
            "view \"up\" is left out of the fit and of the errors: it sees no scene geometry"
        ),
        "{err}"
    );
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["views_without_geometry"], serde_json::json!(["up"]));
    let views: Vec<&str> = report["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["view"].as_str().unwrap())
        .collect();
    assert_eq!(views, ["down"]);
    assert!(report["rel_mae"].as_f64().unwrap().is_finite());
    assert_eq!(files_in(&out.join("reference")), ["down.exr", "up.exr"]);

    // Given references: one whose alpha is zero everywhere is left out, and said to be so.
    let refs = d.join("refs");
    std::fs::create_dir(&refs).unwrap();
    std::fs::copy(out.join("reference/down.exr"), refs.join("down.exr")).unwrap();
    std::fs::write(refs.join("up.exr"), uncovered_exr(8, 6, 0.5)).unwrap();
    let o = run(&[
        "estimate",
        d.join("scene.ron").to_str().unwrap(),
        "--out",
        d.join("out2").to_str().unwrap(),
        "--reference",
        refs.to_str().unwrap(),
        "--rings",
        "3",
        "--quiet",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("\"up\" is left out of the fit and of the errors: its reference in"),
        "{err}"
    );
    assert!(
        err.contains("leaves no pixel to fit (zero alpha, saturated or masked out everywhere)"),
        "{err}"
    );
}

#[test]
fn estimate_references_are_render_reference_images() {
    // Both render each view with the sidecar's settings and the view's own stream.
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let (rr, es) = (tmp.path().join("rr"), tmp.path().join("es"));
    let o = run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--out",
        rr.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--out",
        es.to_str().unwrap(),
        "--rings",
        "3",
        "--fit-only",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for view in ["cam_front", "cam_side"] {
        let a = lightprobe::imageio::read_exr(&rr.join(format!("{view}.exr"))).unwrap();
        let b = lightprobe::imageio::read_exr(&es.join(format!("reference/{view}.exr"))).unwrap();
        assert!(a.rgb == b.rgb && a.alpha == b.alpha, "{view} differs");
    }
}

/// The committed corpus of broken glTF/GLB files (tests/bad/, written by
/// scripts/make_bad_corpus.py): each, named by a sidecar, must fail cleanly with this fragment.
#[test]
fn gltf_corpus_fails_cleanly() {
    let bad = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad");
    let cases = [
        ("glb_bad_magic.glb", "not a GLB file"),
        ("glb_bad_chunk_length.glb", "not a valid glTF"),
        ("glb_json_not_json.glb", "not a valid glTF"),
        ("glb_truncated.glb", "not a valid glTF 2.0 file: truncated"),
        ("glb_length_underflow.glb", "declares a length of 5 bytes"),
        ("glb_version_1.glb", "GLB version 1"),
        (
            "gltf_missing_buffer.gltf",
            "\"missing.bin\", which does not exist",
        ),
        ("gltf_buffer_outside.gltf", "points outside"),
        ("gltf_buffer_absolute.gltf", "points outside"),
        (
            "gltf_accessor_out_of_range.gltf",
            "gltf_accessor_out_of_range.gltf",
        ),
        ("gltf_lines.gltf", "only triangle lists"),
        ("gltf_wrong_accessor_type.gltf", "not a valid TEXCOORD"),
        (
            "gltf_dangling_accessor.gltf",
            "refers to objects that do not exist",
        ),
        ("gltf_no_camera.gltf", "has no perspective camera"),
        ("gltf_no_mesh.gltf", "has no triangles"),
        (
            "gltf_missing_texture.gltf",
            "\"missing.png\", which does not exist",
        ),
        ("gltf_bad_texture.gltf", "not a valid glTF"),
        ("gltf_not_json.gltf", "not a valid glTF"),
        (
            "gltf_index_out_of_range.gltf",
            "has index 7 but only 3 vertices",
        ),
    ];
    let mut failures = Vec::new();
    for (file, expect) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        std::fs::copy(bad.join(file), d.join(file)).unwrap();
        std::fs::write(d.join("s.ron"), format!("Scene(gltf: {file:?}, image: (width: 8, height: 6), lights: [{LIGHT}], render: (spp: 1))")).unwrap();
        for cmd in [
            &["render-reference", "s.ron", "--out", "out", "--quiet"][..],
            &["info", "s.ron"],
        ] {
            let o = bin().args(cmd).current_dir(d).output().unwrap();
            let err = String::from_utf8_lossy(&o.stderr).into_owned();
            let ok = !o.status.success()
                && err.trim().lines().count() == 1
                && err.contains(expect)
                && !err.contains("panicked")
                && !d.join("out").join("cam.exr").exists();
            if !ok || files_in(&d.join("out")).iter().any(|f| !f.starts_with('.')) {
                failures.push(format!(
                    "{file} ({}): exit {:?}, stderr: {}",
                    cmd[0],
                    o.status.code(),
                    err.trim()
                ));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} corpus cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
    // The control case of the corpus renders.
    let tmp = tempfile::tempdir().unwrap();
    std::fs::copy(
        bad.join("good_triangle.gltf"),
        tmp.path().join("good_triangle.gltf"),
    )
    .unwrap();
    std::fs::write(tmp.path().join("s.ron"), format!("Scene(gltf: \"good_triangle.gltf\", image: (width: 8, height: 6), lights: [{LIGHT}], render: (spp: 1))")).unwrap();
    let o = bin()
        .args(["render-reference", "s.ron", "--out", "out", "--quiet"])
        .current_dir(tmp.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn estimate_is_bit_identical_at_one_and_two_threads() {
    // 7 rings: the transport's dense products; 25 rings at 16 spp: its sparse updates.
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    for rings in ["7", "25"] {
        let mut outs = Vec::new();
        for threads in ["1", "2", "3"] {
            let out = tmp.path().join(format!("r{rings}t{threads}"));
            let o = bin()
                .args([
                    "estimate",
                    scene.to_str().unwrap(),
                    "--out",
                    out.to_str().unwrap(),
                    "--rings",
                    rings,
                    "--spp",
                    "16",
                    "--quiet",
                ])
                .env("RAYON_NUM_THREADS", threads)
                .output()
                .unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            outs.push((
                std::fs::read(out.join("envmap.ron")).unwrap(),
                std::fs::read(out.join("envmap.exr")).unwrap(),
                std::fs::read(out.join("estimate/cam_side.exr")).unwrap(),
            ));
        }
        for (k, other) in outs.iter().enumerate().skip(1) {
            assert!(
                outs[0].0 == other.0,
                "{rings} rings: envmap.ron differs between 1 and {} threads",
                k + 1
            );
            assert!(
                outs[0].1 == other.1 && outs[0].2 == other.2,
                "{rings} rings: EXR outputs differ between 1 and {} threads",
                k + 1
            );
        }
    }
}

#[test]
fn committed_report_schema_is_up_to_date() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/report.schema.json");
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    let o = run(&["schema", "--report"]);
    assert!(o.status.success());
    assert!(
        committed == String::from_utf8(o.stdout).unwrap(),
        "schemas/report.schema.json is stale: run `cargo run -- schema --report > schemas/report.schema.json`"
    );
}

/// Checks `value` against the part of a JSON Schema (draft 2020-12, as schemars writes it)
/// that `report.json` uses: `$ref` into `$defs`, `type` (one or a list), `properties` with
/// `required` and no others, `items`, `anyOf`/`oneOf`/`allOf`, `enum`/`const`. Returns the
/// JSON paths that break it.
fn schema_errors(
    root: &serde_json::Value,
    schema: &serde_json::Value,
    value: &serde_json::Value,
    path: &str,
) -> Vec<String> {
    check(root, schema, value, path, true)
}

/// [`schema_errors`]; `strict`: a field the object's schema does not list is an error (JSON
/// Schema allows it unless `additionalProperties` is false; we want every field documented).
/// The alternatives of a flattened enum list only their own fields, so they are not strict.
fn check(
    root: &serde_json::Value,
    schema: &serde_json::Value,
    value: &serde_json::Value,
    path: &str,
    strict: bool,
) -> Vec<String> {
    use serde_json::Value;
    let mut errors = Vec::new();
    if let Some(r) = schema.get("$ref").and_then(Value::as_str) {
        let name = r.trim_start_matches("#/$defs/");
        return check(root, &root["$defs"][name], value, path, strict);
    }
    let fits = |s: &Value| check(root, s, value, path, false).is_empty();
    if let Some(any) = schema
        .get("anyOf")
        .or_else(|| schema.get("oneOf"))
        .and_then(Value::as_array)
        && !any.iter().any(fits)
    {
        errors.push(format!("{path}: fits none of its alternatives: {value}"));
    }
    for s in schema
        .get("allOf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
    {
        errors.extend(check(root, s, value, path, false));
    }
    if let Some(c) = schema.get("const")
        && c != value
    {
        errors.push(format!("{path}: {value} is not {c}"));
    }
    if let Some(e) = schema.get("enum").and_then(Value::as_array)
        && !e.contains(value)
    {
        errors.push(format!("{path}: {value} is not one of {e:?}"));
    }
    if let Some(t) = schema.get("type") {
        let types: Vec<&str> = match t {
            Value::String(s) => vec![s.as_str()],
            Value::Array(a) => a.iter().filter_map(Value::as_str).collect(),
            _ => vec![],
        };
        let is = |ty: &str| match ty {
            "null" => value.is_null(),
            "boolean" => value.is_boolean(),
            "string" => value.is_string(),
            "array" => value.is_array(),
            "object" => value.is_object(),
            "number" => value.is_number(),
            "integer" => value.is_i64() || value.is_u64(),
            _ => false,
        };
        if !types.iter().any(|ty| is(ty)) {
            errors.push(format!("{path}: {value} is not of type {types:?}"));
        }
    }
    if let (Some(props), Some(obj)) = (
        schema.get("properties").and_then(Value::as_object),
        value.as_object(),
    ) {
        for (k, v) in obj {
            match props.get(k) {
                Some(s) => errors.extend(check(root, s, v, &format!("{path}.{k}"), true)),
                // A flattened, internally tagged enum (`oneOf` beside) owns its own fields.
                None if !strict || schema.get("oneOf").is_some() => {}
                None => errors.push(format!("{path}.{k}: not in the schema")),
            }
        }
        for r in schema
            .get("required")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            if !obj.contains_key(r.as_str().unwrap_or("")) {
                errors.push(format!("{path}: misses required {r}"));
            }
        }
    }
    if let (Some(items), Some(arr)) = (schema.get("items"), value.as_array()) {
        for (i, v) in arr.iter().enumerate() {
            errors.extend(check(root, items, v, &format!("{path}[{i}]"), true));
        }
    }
    errors
}

#[test]
fn a_sphere_fit_asked_for_fewer_pixels_fits_whole_blocks_and_scores_every_pixel() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene.ron");
    std::fs::write(&scene, bundled_sidecar((160, 120), 16, KEY_LIGHT, "")).unwrap();
    let out = tmp.path().join("out");
    let estimate = |extra: &[&str]| {
        let mut args = vec![
            "estimate",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--rings",
            "3",
            "--spp",
            "16",
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    for (extra, expected) in [
        (
            &["--model", "spheres:1", "--sphere-pixels", "1000"][..],
            "--sphere-pixels must be at least 4096, got 1000",
        ),
        (
            &["--sphere-pixels", "5000"][..],
            "with --model envmap there is none",
        ),
    ] {
        let o = estimate(extra);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && stderr.contains(expected),
            "{extra:?}: {stderr}"
        );
    }
    let o = estimate(&["--model", "spheres:1", "--sphere-pixels", "4096"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let s = &report["spheres"];
    let (fit, seen) = (
        s["fit_pixels"].as_u64().unwrap(),
        s["seen_pixels"].as_u64().unwrap(),
    );
    // Whole 4×4 blocks up to the limit; the re-render is scored on every seen pixel.
    assert!(fit <= 4096 && fit > 4096 - 16 && seen > 3 * fit, "{s}");
    let scored: u64 = s["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["pixels"].as_u64().unwrap())
        .sum();
    assert_eq!(scored, seen, "{s}");
    assert!(
        stdout.contains(&format!("fitted on {fit} of the {seen} seen pixels")),
        "{stdout}"
    );
    // Still close to the one light.
    let error = s["recovery"][0]["centre_error_fraction_of_distance"]
        .as_f64()
        .unwrap();
    assert!(error < 0.1, "{s}");
}

#[test]
fn report_json_follows_its_committed_schema() {
    // The envmap alone, and the model chosen from the data (sphere candidates, the
    // selection, fitted lights with their statuses): every field the report can hold.
    let schema: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/report.schema.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    for (i, extra) in [&["--oracle"][..], &["--model", "spheres"]]
        .iter()
        .enumerate()
    {
        let out = tmp.path().join(format!("out{i}"));
        let mut args = vec![
            "estimate",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--rings",
            "3",
            "--spp",
            "8",
            "--quiet",
        ];
        args.extend_from_slice(extra);
        let o = run(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        let errors = schema_errors(&schema, &schema, &report, "report");
        assert!(errors.is_empty(), "{extra:?}: {errors:#?}");
        if i == 1 {
            assert!(report["spheres"].is_object() && report["model_selection"].is_object());
        }
    }
    // The validator itself must catch a wrong type and an unknown field.
    let bad = serde_json::json!({ "rings": "nine", "surprise": 1 });
    let errors = schema_errors(&schema, &schema, &bad, "report");
    assert!(
        errors.iter().any(|e| e.contains("report.rings")),
        "{errors:?}"
    );
    assert!(
        errors.iter().any(|e| e.contains("report.surprise")),
        "{errors:?}"
    );
}

#[test]
fn renders_are_bit_identical_on_the_portable_and_the_detected_kernels() {
    // The BVH's AVX kernels (chosen at run time) and its portable ones compute the same
    // operations in the same order: the images must not depend on the CPU.
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path(), "");
    let render = |isa: Option<&str>, out: &str| {
        let mut cmd = bin();
        cmd.args([
            "render-reference",
            scene.to_str().unwrap(),
            "--out",
            tmp.path().join(out).to_str().unwrap(),
            "--spp",
            "16",
            "--quiet",
        ]);
        cmd.env_remove("LIGHTPROBE_ISA");
        if let Some(isa) = isa {
            cmd.env("LIGHTPROBE_ISA", isa);
        }
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    render(None, "detected");
    render(Some("portable"), "portable");
    let kernels = |out: &str| {
        let text = std::fs::read_to_string(tmp.path().join(out).join("render.json")).unwrap();
        let report: serde_json::Value = serde_json::from_str(&text).unwrap();
        report["kernels"].as_str().unwrap().to_string()
    };
    // The comparison means something only where the CPU has the vector kernels.
    #[cfg(target_arch = "x86_64")]
    let avx2 = {
        use std::arch::is_x86_feature_detected as has;
        has!("avx2")
            && has!("fma")
            && has!("bmi1")
            && has!("bmi2")
            && has!("lzcnt")
            && has!("popcnt")
    };
    #[cfg(not(target_arch = "x86_64"))]
    let avx2 = false;
    assert_eq!(kernels("portable"), "portable");
    assert_eq!(kernels("detected"), if avx2 { "avx2" } else { "portable" });
    if !avx2 {
        eprintln!("no x86-64-v3 on this CPU: both renders used the portable kernels");
    }
    for view in ["cam_front.exr", "cam_side.exr"] {
        let a = std::fs::read(tmp.path().join("detected").join(view)).unwrap();
        let b = std::fs::read(tmp.path().join("portable").join(view)).unwrap();
        assert!(a == b, "{view} differs between the kernels");
    }
}

/// A glTF quad in front of a camera, its vertices coloured by COLOR_0 (`color_type`:
/// "VEC4" normalised bytes, or anything else to test a bad accessor), base colour 0.5.
fn colored_quad(dir: &Path, color_type: &str) -> PathBuf {
    let mut bin: Vec<u8> = Vec::new();
    for p in [
        [-1.0f32, -1.0, 0.0],
        [1.0, -1.0, 0.0],
        [1.0, 1.0, 0.0],
        [-1.0, 1.0, 0.0],
    ] {
        p.iter().for_each(|v| bin.extend(v.to_le_bytes()));
    }
    // One colour for every vertex: (51, 128, 255)/255.
    for _ in 0..4 {
        bin.extend([51u8, 128, 255, 255]);
    }
    for i in [0u32, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    std::fs::write(dir.join("q.bin"), &bin).unwrap();
    let gltf = format!(
        r#"{{"asset": {{"version": "2.0"}},
        "buffers": [{{"uri": "q.bin", "byteLength": {len}}}],
        "bufferViews": [{{"buffer": 0, "byteOffset": 0, "byteLength": 48}},
                        {{"buffer": 0, "byteOffset": 48, "byteLength": 16}},
                        {{"buffer": 0, "byteOffset": 64, "byteLength": 24}}],
        "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                        "min": [-1, -1, 0], "max": [1, 1, 0]}},
                      {{"bufferView": 1, "componentType": 5121, "normalized": true, "count": 4,
                        "type": "{color_type}"}},
                      {{"bufferView": 2, "componentType": 5125, "count": 6, "type": "SCALAR"}}],
        "materials": [{{"name": "scan", "pbrMetallicRoughness": {{"baseColorFactor": [0.5, 0.5, 0.5, 1]}}}}],
        "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0, "COLOR_0": 1}}, "indices": 2, "material": 0}}]}}],
        "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.5, "znear": 0.01}}}}],
        "nodes": [{{"mesh": 0}}, {{"name": "cam", "camera": 0, "translation": [0, 0, 3]}}],
        "scenes": [{{"nodes": [0, 1]}}], "scene": 0}}"#,
        len = bin.len()
    );
    let path = dir.join("q.gltf");
    std::fs::write(&path, gltf).unwrap();
    path
}

#[test]
fn vertex_colors_multiply_the_base_colour_unless_the_sidecar_overrides_it() {
    use lightprobe::render::{Lights, Renderer};
    use lightprobe::scene::Scene;
    let tmp = tempfile::tempdir().unwrap();
    colored_quad(tmp.path(), "VEC4");
    let albedo_at_centre = |overrides: &str| {
        let ron = tmp.path().join("q.ron");
        std::fs::write(
            &ron,
            format!(
                "Scene(gltf: \"q.gltf\", image: (width: 8, height: 6), albedo: {{{overrides}}})"
            ),
        )
        .unwrap();
        let scene = Scene::load(&ron).unwrap();
        let lights = Lights::new(Vec::new());
        let aovs = Renderer::new(&scene, &lights).aovs(&scene.cameras[0]);
        aovs.albedo.rgb[3 * 8 + 4]
    };
    // glTF: albedo = baseColorFactor × COLOR_0 (linear), here 0.5 × (0.2, 0.502, 1).
    let a = albedo_at_centre("");
    let want = [0.5 * 51.0 / 255.0, 0.5 * 128.0 / 255.0, 0.5];
    for (got, want) in a.to_array().iter().zip(want) {
        assert!((got - want).abs() < 1e-4, "albedo {a}, want {want:?}");
    }
    // An override is the whole albedo.
    let a = albedo_at_centre("\"scan\": Constant((0.3, 0.3, 0.3))");
    assert!(
        (a - glam::Vec3::splat(0.3)).abs().max_element() < 1e-6,
        "albedo {a}"
    );
    // `info` says the mesh carries colours.
    let ron = tmp.path().join("q.ron");
    std::fs::write(
        &ron,
        "Scene(gltf: \"q.gltf\", image: (width: 8, height: 6))",
    )
    .unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_lightprobe"))
        .args(["info", ron.to_str().unwrap()])
        .output()
        .unwrap();
    let info: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(info["vertex_colors"], true, "{info}");
    // A COLOR_0 of the wrong type is refused, naming the file and the accessor.
    colored_quad(tmp.path(), "SCALAR");
    let o = Command::new(env!("CARGO_BIN_EXE_lightprobe"))
        .args(["info", ron.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("q.gltf") && err.contains("COLOR_0"), "{err}");
}

#[test]
fn estimate_views_picks_the_views_it_fits() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.ron");
    let out = tmp.path().join("out");
    let run = |views: &str| {
        Command::new(env!("CARGO_BIN_EXE_lightprobe"))
            .args([
                "estimate",
                scene,
                "--out",
                out.to_str().unwrap(),
                "--spp",
                "8",
            ])
            .args(["--views", views, "--fit-only", "--quiet"])
            .output()
            .unwrap()
    };
    let o = run("cam_side");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let views: Vec<&str> = report["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["view"].as_str().unwrap())
        .collect();
    assert_eq!(views, ["cam_side"]);
    assert!(out.join("reference/cam_side.exr").exists());
    assert!(!out.join("reference/cam_front.exr").exists());
    for (views, expect) in [
        ("cam_top", "\"cam_top\" is not a perspective camera node of"),
        ("cam_side,cam_side", "listed twice"),
    ] {
        let o = run(views);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains(expect), "{err}");
    }
}

#[test]
fn colour_together_with_the_gradient_solver_is_refused_before_any_work() {
    // The gradient solver fits each channel on its own: asking it to keep colour together
    // would be silently ignored, so it is an error naming the setting, with no output written.
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path(), "");
    let out = dir.path().join("out");
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--solver",
        "gradient",
        "--colour",
        "together",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("colour") && err.contains("per-channel"),
        "{err}"
    );
    assert!(!out.join("report.json").exists());
    // And together with NNLS runs, saying so in its report.
    let o = run(&[
        "estimate",
        scene.to_str().unwrap(),
        "--colour",
        "together",
        "--fit-only",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["colour"], "together");
    // Its clusters' intervals were not calibrated (which cells are lit flips as a whole), so
    // none is stated, and the summary says why; the same run per channel states them.
    for (colour, stated) in [("together", false), ("per-channel", true)] {
        let o = run(&[
            "estimate",
            scene.to_str().unwrap(),
            "--colour",
            colour,
            "--fit-only",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        let clusters = report["clusters"].as_array().unwrap();
        assert!(!clusters.is_empty());
        for c in clusters {
            assert_eq!(
                !c["direction_sigma_degrees"].is_null(),
                stated,
                "{colour}: {c}"
            );
        }
        let summary = String::from_utf8_lossy(&o.stdout);
        assert_eq!(
            summary.contains("no intervals"),
            !stated,
            "{colour}: {summary}"
        );
        let page = std::fs::read_to_string(out.join("index.html")).unwrap();
        assert_eq!(page.contains("No σ"), !stated, "{colour}");
    }
}
