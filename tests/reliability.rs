//! Hostile inputs and hostile surroundings, run on the real binary: inputs that declare more
//! than memory holds, limits on the process (`--memory-limit`, `ulimit -v`), output streams
//! that fail, interrupts, two runs into one folder, and inputs that are invalid in ways a
//! parser accepts. Each must end in one clear line and a non-zero exit (or, for a closed pipe,
//! a quiet exit), never a panic, an abort or a hang, and never leave a partial output.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lightprobe"))
}

/// Runs the binary with `args` to the end.
fn run(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

/// Asserts that `o` exited 0, showing its stderr otherwise.
fn succeeded(o: &Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `dir/name` as a string argument.
fn arg(dir: &Path, name: &str) -> String {
    dir.join(name).to_str().unwrap().to_string()
}

fn bundled() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/tabletop/tabletop.ron")
}

fn bundled_glb() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/tabletop/tabletop.glb")
}

/// Every file under `dir`, relative, sorted (lock files, which a run leaves on purpose,
/// excepted).
fn files_under(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else if !p.to_string_lossy().ends_with(".lock") {
                out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

/// Checks that `o` is a clean failure: non-zero exit (not a crash), one line on stderr that
/// contains `expect`, no panic.
fn clean_failure(o: &Output, expect: &str) -> Result<(), String> {
    let err = String::from_utf8_lossy(&o.stderr);
    let mut why = Vec::new();
    match o.status.code() {
        Some(0) => why.push("exited 0".to_string()),
        Some(1) | Some(2) => {}
        other => why.push(format!("exit {other:?} (a crash or a signal)")),
    }
    if err.contains("panicked") || err.contains("RUST_BACKTRACE") {
        why.push("panicked".into());
    }
    if err.trim().lines().count() != 1 {
        why.push(format!("{} lines of error", err.trim().lines().count()));
    }
    if !err.contains(expect) {
        why.push(format!("no {expect:?}"));
    }
    if why.is_empty() {
        Ok(())
    } else {
        Err(format!("{}: {}", why.join(", "), err.trim()))
    }
}

/// A sidecar over the bundled glTF at 16×12, lit by one sphere light.
fn small_sidecar() -> String {
    format!(
        "Scene(gltf: {:?}, image: (width: 16, height: 12), lights: [Sphere(center: (0, 3, 0), radius: 0.2, radiance: (10, 10, 10))], render: (spp: 2))",
        bundled_glb()
    )
}

/// A glTF whose nodes instance one triangle through `levels` levels of two shared children:
/// 2^levels instances from a few kilobytes.
fn dag_bomb(levels: usize) -> String {
    let mut nodes = Vec::new();
    for level in 0..levels {
        for _ in 0..2 {
            if level + 1 < levels {
                nodes.push(format!(
                    "{{\"children\": [{}, {}]}}",
                    2 * (level + 1),
                    2 * (level + 1) + 1
                ));
            } else {
                nodes.push("{\"mesh\": 0}".to_string());
            }
        }
    }
    let camera = 2 * levels;
    nodes.push("{\"camera\": 0, \"translation\": [0, 0.5, 3]}".to_string());
    format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [0, 1, {camera}]}}], "nodes": [{}], "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "znear": 0.01}}}}], "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}}], "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1]}}], "bufferViews": [{{"buffer": 0, "byteLength": 36}}], "buffers": [{{"byteLength": 36, "uri": "data:application/octet-stream;base64,AACAvwAAAAAAAIC/AACAPwAAAAAAAIC/AAAAAAAAAAAAAIA/"}}]}}"#,
        nodes.join(", ")
    )
}

/// A one-triangle glTF (`good_triangle.gltf`'s geometry) with `camera_extra` fields on its
/// camera node and `position_extra` fields on its POSITION accessor.
fn triangle_gltf(camera_extra: &str, position_extra: &str) -> String {
    format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [0, 1]}}], "nodes": [{{"mesh": 0}}, {{"camera": 0, "translation": [0.3, 0.5, 2]{camera_extra}}}], "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "znear": 0.01}}}}], "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}}], "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1]{position_extra}}}, {{"bufferView": 1, "componentType": 5125, "count": 1, "type": "SCALAR"}}, {{"bufferView": 0, "componentType": 5126, "count": 1, "type": "VEC3"}}], "bufferViews": [{{"buffer": 0, "byteLength": 36}}, {{"buffer": 0, "byteOffset": 36, "byteLength": 4}}], "buffers": [{{"byteLength": 40, "uri": "data:application/octet-stream;base64,AACAvwAAAAAAAIC/AACAPwAAAAAAAIC/AAAAAAAAAAAAAIA/BQAAAA=="}}]}}"#
    )
}

/// A glTF whose one triangle's POSITION accessor declares `count` vertices through a sparse
/// block and no buffer view (the reader allocates `count` × 12 bytes for it).
fn sparse_without_view(count: u64) -> String {
    format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [0, 1]}}], "nodes": [{{"mesh": 0}}, {{"camera": 0, "translation": [0, 0.5, 3]}}], "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "znear": 0.01}}}}], "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}], "accessors": [{{"componentType": 5126, "count": {count}, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1], "sparse": {{"count": 1, "indices": {{"bufferView": 1, "componentType": 5125}}, "values": {{"bufferView": 0}}}}}}, {{"bufferView": 1, "componentType": 5125, "count": 1, "type": "SCALAR"}}], "bufferViews": [{{"buffer": 0, "byteLength": 36}}, {{"buffer": 0, "byteOffset": 36, "byteLength": 4}}], "buffers": [{{"byteLength": 40, "uri": "data:application/octet-stream;base64,AACAvwAAAAAAAIC/AACAPwAAAAAAAIC/AAAAAAAAAAAAAIA/AAAAAA=="}}]}}"#
    )
}

/// The header of a scan-line EXR (RGB f32, `compression` 0 none or 3 ZIP) declaring a
/// `w × h` image, followed by `table_bytes` zero bytes standing for the offset table.
fn exr_header(w: i32, h: i32, compression: u8, table_bytes: usize) -> Vec<u8> {
    let mut b = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
    let mut attr = |name: &str, kind: &str, value: &[u8]| {
        b.extend_from_slice(name.as_bytes());
        b.push(0);
        b.extend_from_slice(kind.as_bytes());
        b.push(0);
        b.extend_from_slice(&(value.len() as i32).to_le_bytes());
        b.extend_from_slice(value);
    };
    let mut channels = Vec::new();
    for c in ["B", "G", "R"] {
        channels.extend_from_slice(c.as_bytes());
        channels.push(0);
        channels.extend_from_slice(&2i32.to_le_bytes()); // f32
        channels.extend_from_slice(&[0, 0, 0, 0]);
        channels.extend_from_slice(&1i32.to_le_bytes());
        channels.extend_from_slice(&1i32.to_le_bytes());
    }
    channels.push(0);
    attr("channels", "chlist", &channels);
    attr("compression", "compression", &[compression]);
    let window: Vec<u8> = [0i32, 0, w - 1, h - 1]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    attr("dataWindow", "box2i", &window);
    attr("displayWindow", "box2i", &window);
    attr("lineOrder", "lineOrder", &[0]);
    attr("pixelAspectRatio", "float", &1f32.to_le_bytes());
    attr(
        "screenWindowCenter",
        "v2f",
        &[0f32.to_le_bytes(), 0f32.to_le_bytes()].concat(),
    );
    attr("screenWindowWidth", "float", &1f32.to_le_bytes());
    b.push(0);
    b.extend(std::iter::repeat_n(0u8, table_bytes));
    b
}

/// The bytes of a `w × h` RGB EXR of one `value`, with a constant alpha if given.
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

struct Case {
    name: &'static str,
    files: Vec<(&'static str, Vec<u8>)>,
    args: Vec<&'static str>,
    expect: &'static str,
}

fn estimate_with_reference() -> Vec<&'static str> {
    vec![
        "estimate",
        "{d}/scene.ron",
        "--out",
        "{d}/out",
        "--reference",
        "{d}/ref",
        "--quiet",
    ]
}

fn cases() -> Vec<Case> {
    let scene = || ("scene.ron", small_sidecar().into_bytes());
    let on = |gltf: &str| {
        (
            "s.ron",
            format!(
                "Scene(gltf: {gltf:?}, image: (width: 8, height: 6), lights: [Sphere(center: (0, 3, 0), radius: 0.2, radiance: (10, 10, 10))], render: (spp: 1))"
            )
            .into_bytes(),
        )
    };
    let render_s = vec![
        "render-reference",
        "{d}/s.ron",
        "--out",
        "{d}/out",
        "--quiet",
    ];
    let compare = |reference: &'static str| vec!["compare", "{d}/img.exr", reference];
    vec![
        Case {
            name: "a glTF DAG instancing a mesh 2^40 times",
            files: vec![("bomb.gltf", dag_bomb(40).into_bytes()), on("bomb.gltf")],
            args: render_s.clone(),
            expect: "node instances",
        },
        Case {
            name: "a glTF camera node scaled by 0",
            files: vec![
                ("cam.gltf", triangle_gltf(", \"scale\": [0, 0, 0]", "").into_bytes()),
                on("cam.gltf"),
            ],
            args: render_s.clone(),
            expect: "degenerate transform",
        },
        Case {
            name: "a glTF camera node mirrored by its scale",
            files: vec![
                ("cam.gltf", triangle_gltf(", \"scale\": [-1, 1, 1]", "").into_bytes()),
                on("cam.gltf"),
            ],
            args: render_s.clone(),
            expect: "is mirrored by its node transforms",
        },
        Case {
            name: "a sparse accessor substituting past its end",
            files: vec![
                (
                    "sparse.gltf",
                    triangle_gltf(
                        "",
                        ", \"sparse\": {\"count\": 1, \"indices\": {\"bufferView\": 1, \"componentType\": 5125}, \"values\": {\"bufferView\": 0}}",
                    )
                    .into_bytes(),
                ),
                on("sparse.gltf"),
            ],
            args: render_s.clone(),
            expect: "substitutes element 5",
        },
        Case {
            name: "an empty .glb",
            files: vec![("e.glb", Vec::new()), on("e.glb")],
            args: render_s.clone(),
            expect: "e.glb: is empty",
        },
        Case {
            name: "a .glb that is text",
            files: vec![("t.glb", b"hello, not a scene".to_vec()), on("t.glb")],
            args: render_s.clone(),
            expect: "not a GLB file",
        },
        Case {
            name: "an EXR header declaring 45000² pixels (compare)",
            files: vec![
                ("img.exr", exr_header(45000, 45000, 0, 64)),
                ("ref.exr", exr_bytes(4, 3, 1.0, None)),
            ],
            args: compare("{d}/ref.exr"),
            expect: "at most 16384×16384",
        },
        Case {
            name: "an EXR declaring more chunks than the file holds (import-envmap)",
            files: vec![("sky.exr", exr_header(16000, 8000, 0, 64))],
            args: vec![
                "import-envmap",
                "{d}/sky.exr",
                "--rings",
                "9",
                "--out",
                "{d}/out/env.ron",
            ],
            expect: "truncated",
        },
        Case {
            name: "an EXR of 16384² under a 1 GiB limit (estimate --reference)",
            files: vec![scene(), ("ref/cam_front.exr", exr_header(16384, 16384, 3, 8192)),
                ("ref/cam_side.exr", exr_bytes(16, 12, 0.5, None)),],
            args: {
                let mut a = estimate_with_reference();
                a.splice(0..0, ["--memory-limit", "1G"]);
                a
            },
            expect: "would need about 4.0 GiB",
        },
        Case {
            name: "a reference with pixels of 3e38",
            files: vec![scene(), ("ref/cam_front.exr", exr_bytes(16, 12, 3e38, None)),
                ("ref/cam_side.exr", exr_bytes(16, 12, 0.5, None)),],
            args: estimate_with_reference(),
            expect: "exceeds 1e15",
        },
        Case {
            name: "a reference with negative pixels",
            files: vec![scene(), ("ref/cam_front.exr", exr_bytes(16, 12, -0.5, None)),
                ("ref/cam_side.exr", exr_bytes(16, 12, 0.5, None)),],
            args: estimate_with_reference(),
            expect: "is negative",
        },
        Case {
            name: "a reference with NaN alpha",
            files: vec![
                scene(),
                ("ref/cam_front.exr", exr_bytes(16, 12, 0.5, Some(f32::NAN))),
                ("ref/cam_side.exr", exr_bytes(16, 12, 0.5, None)),
            ],
            args: estimate_with_reference(),
            expect: "has alpha NaN",
        },
        Case {
            name: "compare against a black reference",
            files: vec![
                ("img.exr", exr_bytes(4, 3, 1.0, None)),
                ("ref.exr", exr_bytes(4, 3, 0.0, None)),
            ],
            args: compare("{d}/ref.exr"),
            expect: "is black",
        },
        Case {
            name: "an envmap of 3e38",
            files: vec![
                scene(),
                (
                    "env.ron",
                    b"Envmap(rings: 2, radiance: [(3e38, 1, 1), (1, 1, 1)])".to_vec(),
                ),
            ],
            args: vec![
                "render-reference",
                "{d}/scene.ron",
                "--envmap",
                "{d}/env.ron",
                "--out",
                "{d}/out",
                "--quiet",
            ],
            expect: "between 0 and 1e15",
        },
        Case {
            name: "--threads far beyond the cores",
            files: vec![scene()],
            args: vec!["--threads", "100000", "info", "{d}/scene.ron"],
            expect: "--threads must be between 1 and",
        },
        Case {
            name: "sphere lights whose camera paths outgrow --memory-limit",
            files: vec![(
                "big.ron",
                small_sidecar()
                    .replace("width: 16, height: 12", "width: 4000, height: 3000")
                    .into_bytes(),
            )],
            args: vec![
                "--memory-limit",
                "2G",
                "estimate",
                "{d}/big.ron",
                "--out",
                "{d}/out",
                "--model",
                "spheres:1",
                "--quiet",
            ],
            expect: "keeps its camera paths per pixel",
        },
        Case {
            name: "an estimate beyond --memory-limit",
            files: vec![scene()],
            args: vec![
                "--memory-limit",
                "64M",
                "estimate",
                "{d}/scene.ron",
                "--out",
                "{d}/out",
                "--rings",
                "200",
                "--quiet",
            ],
            expect: "under the memory limit set",
        },
        Case {
            name: "a 1 KB glTF declaring 2^27 sparse vertices (no buffer view)",
            files: vec![("big.gltf", sparse_without_view(1 << 27).into_bytes()), on("big.gltf")],
            args: vec!["--memory-limit", "200M", "info", "{d}/s.ron"],
            expect: "would need about",
        },
        Case {
            name: "a device as an input image",
            files: vec![("ref.exr", exr_bytes(4, 3, 1.0, None))],
            args: vec!["compare", "/dev/zero", "{d}/ref.exr"],
            expect: "/dev/zero: is not a regular file",
        },
        Case {
            name: "a device as the scene's glTF",
            files: vec![on("/dev/zero")],
            args: render_s.clone(),
            expect: "/dev/zero: is not a regular file",
        },
        Case {
            name: "an export over its own input",
            files: vec![("env.ron", b"Envmap(rings: 2, radiance: [(1, 1, 1), (0.5, 0.5, 0.5)])".to_vec())],
            args: vec!["export-envmap", "{d}/env.ron", "--out", "{d}/env.ron", "--width", "8"],
            expect: "is the input",
        },
        Case {
            name: "an export beyond --memory-limit",
            files: vec![("env.ron", b"Envmap(rings: 2, radiance: [(1, 1, 1), (0.5, 0.5, 0.5)])".to_vec())],
            args: vec!["--memory-limit", "100M", "export-envmap", "{d}/env.ron", "--out", "{d}/big.exr", "--width", "16384"],
            expect: "a 16384×8192 lat-long image would need about",
        },
        Case {
            name: "a sweep with --spheres 0",
            files: vec![scene()],
            args: vec!["sweep", "{d}/scene.ron", "--out", "{d}/out", "--spheres", "0", "--quiet"],
            expect: "--spheres must be between 1 and 1000",
        },
        Case {
            name: "a memory limit of a kilobyte is stated in bytes, not as 0.0 GiB",
            files: vec![scene()],
            args: vec!["--memory-limit", "1K", "estimate", "{d}/scene.ron", "--out", "{d}/out", "--quiet"],
            expect: "but only 0 bytes is left under the memory limit set",
        },
        Case {
            name: "a malformed --memory-limit",
            files: vec![],
            args: vec!["--memory-limit", "lots", "info", "x.ron"],
            expect: "expected a size such as 4G",
        },
    ]
}

#[test]
fn hostile_inputs_fail_cleanly() {
    let mut failures = Vec::new();
    for case in cases() {
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        for (name, content) in &case.files {
            let p = d.join(name);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, content).unwrap();
        }
        let before = files_under(d);
        let args: Vec<String> = case
            .args
            .iter()
            .map(|a| a.replace("{d}", d.to_str().unwrap()))
            .collect();
        let t = Instant::now();
        let o = bin().args(&args).output().unwrap();
        let mut why = clean_failure(&o, case.expect)
            .err()
            .into_iter()
            .collect::<Vec<_>>();
        if t.elapsed() > Duration::from_secs(60) {
            why.push(format!("took {:.0?}", t.elapsed()));
        }
        if files_under(d) != before {
            why.push(format!("left files {:?}", files_under(d)));
        }
        if !why.is_empty() {
            failures.push(format!("{}: {}", case.name, why.join("; ")));
        }
    }
    assert!(
        failures.is_empty(),
        "{} hostile cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn textures_beyond_the_memory_limit_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    // good_triangle.gltf with a 4096² base-colour texture: 200 MB as linear f32 RGB.
    let bad = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad/good_triangle.gltf");
    let mut gltf: serde_json::Value = serde_json::from_slice(&std::fs::read(bad).unwrap()).unwrap();
    gltf["images"] = serde_json::json!([{"uri": "big.png"}]);
    gltf["textures"] = serde_json::json!([{"source": 0}]);
    gltf["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] =
        serde_json::json!({"index": 0});
    std::fs::write(d.join("t.gltf"), gltf.to_string()).unwrap();
    image::RgbImage::new(4096, 4096)
        .save(d.join("big.png"))
        .unwrap();
    std::fs::write(
        d.join("s.ron"),
        "Scene(gltf: \"t.gltf\", image: (width: 8, height: 6), lights: [Sphere(center: (0, 3, 0), radius: 0.2, radiance: (10, 10, 10))], render: (spp: 1))",
    )
    .unwrap();
    let info = |limit: &str| run(&["--memory-limit", limit, "info", &arg(d, "s.ron")]);
    clean_failure(&info("150M"), "its 1 textures (16777216 texels)").unwrap();
    let o = info("2G");
    succeeded(&o);
}

#[test]
fn a_sweep_beyond_memory_is_refused_before_it_starts() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::write(d.join("s00.ron"), small_sidecar()).unwrap();
    for extra in [
        &["--rings", "1000"][..],
        &["--rings", "3,1000", "--auto"],
        &["--rings", "3", "--spheres", "1000"],
    ] {
        let out = d.join("out");
        let o = bin()
            .args([
                "sweep",
                &arg(d, "s00.ron"),
                "--out",
                out.to_str().unwrap(),
                "--quiet",
            ])
            .args(extra)
            .output()
            .unwrap();
        clean_failure(&o, "would need about").unwrap_or_else(|e| panic!("{extra:?}: {e}"));
        assert!(
            files_under(&out).is_empty(),
            "{extra:?} left {:?}",
            files_under(&out)
        );
    }
}

#[test]
fn failing_standard_output_is_an_error_and_a_closed_pipe_is_quiet() {
    // A full disk: one line, exit 1.
    if Path::new("/dev/full").exists() {
        for args in [&["schema"][..], &["info", bundled().to_str().unwrap()]] {
            let o = bin()
                .args(args)
                .stdout(std::fs::File::create("/dev/full").unwrap())
                .output()
                .unwrap();
            clean_failure(&o, "cannot write to standard output")
                .unwrap_or_else(|e| panic!("{args:?} > /dev/full: {e}"));
        }
    }
    // A reader that goes away: nothing on stderr, exit 0, as `| head -c1` expects.
    let mut child = bin()
        .args(["schema"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        o.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Starts a render slow enough to be caught in the act, into `out`; waits until it holds the
/// folder.
fn slow_render(out: &Path) -> std::process::Child {
    let child = bin()
        .args([
            "render-reference",
            bundled().to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spp",
            "65536",
            "--quiet",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let lock = out.join(".lightprobe.lock");
    let t = Instant::now();
    while !std::fs::read_to_string(&lock).is_ok_and(|s| s.trim() == child.id().to_string()) {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "the render never locked {}",
            out.display()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child
}

#[test]
#[cfg(unix)]
fn a_second_run_into_a_held_folder_is_refused_and_an_interrupt_cleans_up() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    // A temporary of a process that died long ago (PIDs above 2^22 never run).
    let stale = out.join(".cam_front.exr.4194305.tmp");
    std::fs::write(&stale, b"half an image").unwrap();
    let mut first = slow_render(&out);
    assert!(!stale.exists(), "the stale temporary was not removed");

    let o = run(&[
        "estimate",
        bundled().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    clean_failure(
        &o,
        &format!(
            "is in use by another lightprobe run (process {})",
            first.id()
        ),
    )
    .unwrap();

    // SIGINT: exit 130, no temporary left, no output under its final name.
    let status = Command::new("kill")
        .args(["-INT", &first.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let t = Instant::now();
    let status = loop {
        if let Some(s) = first.try_wait().unwrap() {
            break s;
        }
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "SIGINT did not stop the render"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(first.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert_eq!(status.code(), Some(130), "{err}");
    assert!(err.contains("interrupted"), "{err}");
    let left = files_under(&out);
    assert!(left.iter().all(|f| !f.ends_with(".tmp")), "{left:?}");

    // The folder is free again.
    let o = run(&[
        "render-reference",
        bundled().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--spp",
        "1",
        "--quiet",
    ]);
    succeeded(&o);
}

/// Runs `args` under an address-space limit (`ulimit -v`, KiB) through the shell.
#[cfg(unix)]
fn under_ulimit(kib: u64, args: &[&str]) -> Output {
    let mut line = format!(
        "ulimit -v {kib} && exec '{}'",
        env!("CARGO_BIN_EXE_lightprobe")
    );
    for a in args {
        line.push_str(&format!(" '{a}'"));
    }
    Command::new("sh").args(["-c", &line]).output().unwrap()
}

#[test]
#[cfg(target_os = "linux")]
fn address_space_limits_give_clean_errors_and_memory_limits_hold() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let scene = bundled();
    let scene = scene.to_str().unwrap();
    let out_s = out.to_str().unwrap();
    // A transport far beyond the limit: refused up front, naming the limit.
    let o = under_ulimit(
        1_572_864,
        &[
            "estimate", scene, "--out", out_s, "--rings", "100", "--quiet",
        ],
    );
    clean_failure(&o, "address-space limit").unwrap();
    assert!(files_under(&out).is_empty());
    // Limits so tight that even loading runs out: still one line and exit 1, never an abort.
    for kib in [150_000, 250_000, 400_000] {
        let o = under_ulimit(kib, &["estimate", scene, "--out", out_s, "--quiet"]);
        if !o.status.success() {
            clean_failure(&o, "").unwrap_or_else(|e| panic!("ulimit -v {kib}: {e}"));
            let left = files_under(&out);
            assert!(
                left.iter().all(|f| !f.ends_with(".tmp")),
                "ulimit -v {kib}: left {left:?}"
            );
        }
    }
    // Within --memory-limit the estimate runs, and its peak stays under the limit.
    let o = run(&[
        "--memory-limit",
        "400M",
        "estimate",
        scene,
        "--out",
        out_s,
        "--quiet",
    ]);
    succeeded(&o);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let peak = report["memory"]["peak_bytes"].as_u64().unwrap();
    assert!(peak > 0 && peak < 400 << 20, "peak {peak} bytes");
}

#[test]
fn the_transport_memory_does_not_grow_with_the_pixels() {
    // The bundled scene at 160×120 and at 640×480 (16× the pixels). Held whole, the second
    // transport would take 614,400 pixels × 90 cells × 12 bytes = 663 MB; streamed, the fit
    // holds the same sums at both sizes, and the whole estimate stays under 300 MB.
    let tmp = tempfile::tempdir().unwrap();
    let mut bytes = Vec::new();
    for (w, h) in [(160, 120), (640, 480)] {
        let sidecar = tmp.path().join(format!("s{w}.ron"));
        std::fs::write(
            &sidecar,
            format!(
                "Scene(gltf: {:?}, views: [\"cam_front\", \"cam_side\"], image: (width: {w}, height: {h}), \
                 lights: [Sphere(center: (-1.8, 3.2, 1.5), radius: 0.25, radiance: (400, 360, 300))], \
                 envmap: (rings: 9), render: (spp: 8, max_bounces: 2, seed: 1))",
                bundled_glb()
            ),
        )
        .unwrap();
        let out = tmp.path().join(format!("out{w}"));
        let o = run(&[
            "--memory-limit",
            "300M",
            "estimate",
            sidecar.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spp",
            "8",
            "--quiet",
        ]);
        succeeded(&o);
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        let peak = report["memory"]["peak_bytes"].as_u64().unwrap();
        assert!(peak < 300 << 20, "{w}×{h}: peak {peak} bytes");
        // 8 spp: measured 0.27 at 160×120 and 0.22 at 640×480.
        assert!(
            report["rel_mae"].as_f64().unwrap() < 0.4,
            "{w}×{h}: {report}"
        );
        bytes.push(report["memory"]["transport_bytes"].as_u64().unwrap());
    }
    assert_eq!(bytes[0], bytes[1], "transport bytes {bytes:?}");
    assert!(bytes[1] < 100 << 20, "transport bytes {bytes:?}");
}

#[test]
#[cfg(target_os = "linux")]
fn every_command_runs_under_a_real_address_space_limit() {
    // 1.5 GiB of address space (threads' stacks and allocator arenas included) and the same
    // --memory-limit: each command on a small scene must finish inside them, so its memory
    // (resident memory is part of the address space) provably stayed under the limit.
    const KIB: u64 = 1_572_864;
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let ds = |p: &str| d.join(p).to_str().unwrap().to_string();
    std::fs::write(d.join("scene.ron"), small_sidecar()).unwrap();
    let steps: Vec<Vec<String>> = vec![
        vec!["info".into(), ds("scene.ron")],
        vec![
            "render-reference".into(),
            ds("scene.ron"),
            "--out".into(),
            ds("ref"),
            "--quiet".into(),
        ],
        vec![
            "estimate".into(),
            ds("scene.ron"),
            "--out".into(),
            ds("est"),
            "--reference".into(),
            ds("ref"),
            "--quiet".into(),
        ],
        vec![
            "compare".into(),
            ds("est/estimate/cam_front.exr"),
            ds("ref/cam_front.exr"),
        ],
        vec![
            "export-envmap".into(),
            ds("est/envmap.ron"),
            "--out".into(),
            ds("env.exr"),
            "--width".into(),
            "256".into(),
        ],
        vec![
            "import-envmap".into(),
            ds("env.exr"),
            "--rings".into(),
            "9".into(),
            "--out".into(),
            ds("env9.ron"),
        ],
        vec![
            "scenarios".into(),
            "--scene".into(),
            ds("scene.ron"),
            "--count".into(),
            "2".into(),
            "--out".into(),
            ds("sc"),
        ],
        vec![
            "sweep".into(),
            ds("sc/s00.ron"),
            "--out".into(),
            ds("sw"),
            "--rings".into(),
            "3".into(),
            "--spp".into(),
            "16".into(),
            "--quiet".into(),
        ],
        vec!["report".into(), ds("sw")],
        vec!["schema".into()],
    ];
    for step in &steps {
        let mut args = vec!["--memory-limit", "1536M"];
        args.extend(step.iter().map(String::as_str));
        let o = under_ulimit(KIB, &args);
        assert!(
            o.status.success(),
            "{} under ulimit -v {KIB}: exit {:?}: {}",
            step[0],
            o.status.code(),
            String::from_utf8_lossy(&o.stderr)
        );
    }
}

#[test]
#[cfg(unix)]
fn outputs_never_replace_links_and_failed_runs_leave_no_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::write(
        d.join("env.ron"),
        "Envmap(rings: 2, radiance: [(1, 1, 1), (0.5, 0.5, 0.5)])",
    )
    .unwrap();
    // An output that is a link: refused, its target untouched.
    std::fs::write(d.join("victim"), "keep").unwrap();
    std::os::unix::fs::symlink(d.join("victim"), d.join("link.exr")).unwrap();
    let o = run(&[
        "export-envmap",
        &arg(d, "env.ron"),
        "--out",
        &arg(d, "link.exr"),
        "--width",
        "8",
    ]);
    clean_failure(&o, "is not a regular file").unwrap();
    assert_eq!(std::fs::read_to_string(d.join("victim")).unwrap(), "keep");
    assert!(
        std::fs::symlink_metadata(d.join("link.exr"))
            .unwrap()
            .file_type()
            .is_symlink()
    );
    // A lock file that is a link: refused, its target untouched.
    let held = d.join("held");
    std::fs::create_dir(&held).unwrap();
    std::os::unix::fs::symlink(d.join("victim"), held.join(".lightprobe.lock")).unwrap();
    let o = run(&[
        "render-reference",
        bundled().to_str().unwrap(),
        "--out",
        held.to_str().unwrap(),
        "--spp",
        "1",
        "--quiet",
    ]);
    clean_failure(&o, "is not a regular file").unwrap();
    assert_eq!(std::fs::read_to_string(d.join("victim")).unwrap(), "keep");
    // A temporary a killed export left beside its output goes with the next export there.
    let stale = d.join(".out.exr.4194305.tmp");
    std::fs::write(&stale, "half").unwrap();
    let o = run(&[
        "export-envmap",
        &arg(d, "env.ron"),
        "--out",
        &arg(d, "out.exr"),
        "--width",
        "8",
    ]);
    succeeded(&o);
    assert!(!stale.exists());
    // A run that fails after creating its --out folder removes it again.
    std::fs::create_dir(d.join("ref")).unwrap();
    std::fs::write(d.join("scene.ron"), small_sidecar()).unwrap();
    let o = run(&[
        "estimate",
        &arg(d, "scene.ron"),
        "--out",
        &arg(d, "new"),
        "--reference",
        &arg(d, "ref"),
        "--quiet",
    ]);
    clean_failure(&o, "has no reference for view").unwrap();
    assert!(
        !d.join("new").exists(),
        "the failed run left its --out folder"
    );
}

#[test]
fn coincident_instances_load_once_and_fast() {
    // 2^16 paths through a shared hierarchy to one triangle under one transform.
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let mut nodes = vec!["{\"mesh\": 0}".to_string()];
    for level in 1..=16 {
        nodes.push(format!("{{\"children\": [{}, {}]}}", level - 1, level - 1));
    }
    let gltf = format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [16, 17]}}], "nodes": [{}, {{"camera": 0, "translation": [0, 0.5, 3]}}], "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "znear": 0.01}}}}], "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}}], "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1]}}], "bufferViews": [{{"buffer": 0, "byteLength": 36}}], "buffers": [{{"byteLength": 36, "uri": "data:application/octet-stream;base64,AACAvwAAAAAAAIC/AACAPwAAAAAAAIC/AAAAAAAAAAAAAIA/"}}]}}"#,
        nodes.join(", ")
    );
    std::fs::write(d.join("dag.gltf"), gltf).unwrap();
    std::fs::write(d.join("s.ron"), "Scene(gltf: \"dag.gltf\", image: (width: 8, height: 6), lights: [Sphere(center: (0, 3, 0), radius: 0.2, radiance: (10, 10, 10))], render: (spp: 1))").unwrap();
    let t = Instant::now();
    let o = run(&["info", &arg(d, "s.ron")]);
    succeeded(&o);
    let info: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(info["triangles"], 1, "{info}");
    let o = run(&[
        "render-reference",
        &arg(d, "s.ron"),
        "--out",
        &arg(d, "out"),
        "--quiet",
    ]);
    succeeded(&o);
    assert!(
        t.elapsed() < Duration::from_secs(30),
        "took {:?}",
        t.elapsed()
    );
}
