//! References as cameras and renderers write them: OpenEXR, Radiance HDR, 8- and 16-bit PNG
//! and JPEG (sRGB or linear), with saturated pixels and `<view>.mask.png` left out.

use std::path::Path;

use glam::Vec3;
use lightprobe::estimate::pipeline::load_references;
use lightprobe::imageio::{self, Decoding, Image};
use lightprobe::scene::Camera;

/// A 6×4 image of known radiance: a ramp over [0.02, 0.9] in each channel, out of phase.
fn ramp() -> Image {
    let mut img = Image::new(6, 4);
    for (i, p) in img.rgb.iter_mut().enumerate() {
        let t = i as f32 / 23.0;
        *p = Vec3::new(
            0.02 + 0.88 * t,
            0.9 - 0.88 * t,
            0.02 + 0.88 * (1.0 - (2.0 * t - 1.0).abs()),
        );
    }
    img
}

fn cam() -> Camera {
    Camera::look_at("v", Vec3::Z, Vec3::ZERO, 0.8, 6, 4)
}

fn encode(c: f32, linear: bool) -> f32 {
    if linear {
        c
    } else {
        imageio::linear_to_srgb(c)
    }
}

fn write_png16(path: &Path, img: &Image, linear: bool) {
    let mut buf = image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::new(img.width, img.height);
    for (p, c) in buf.pixels_mut().zip(&img.rgb) {
        *p = image::Rgb(
            c.to_array()
                .map(|v| (encode(v, linear) * 65535.0).round() as u16),
        );
    }
    buf.save(path).unwrap();
}

fn write_png8(path: &Path, img: &Image) {
    let mut buf = image::RgbImage::new(img.width, img.height);
    for (p, c) in buf.pixels_mut().zip(&img.rgb) {
        *p = image::Rgb(
            c.to_array()
                .map(|v| (encode(v, false) * 255.0).round() as u8),
        );
    }
    buf.save(path).unwrap();
}

fn read(dir: &Path, decoding: Decoding) -> (Image, Vec<bool>) {
    let (mut images, mut usable) = load_references(dir, &[&cam()], decoding).unwrap();
    (images.remove(0), usable.remove(0))
}

fn max_rel_err(a: &Image, b: &Image) -> f32 {
    a.rgb
        .iter()
        .zip(&b.rgb)
        .map(|(x, y)| ((*x - *y).abs() / y.max(Vec3::splat(1e-3))).max_element())
        .fold(0.0, f32::max)
}

#[test]
fn photographs_decode_to_the_radiance_they_encode() {
    let want = ramp();
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    // 16-bit sRGB PNG: sRGB-decoded, to the 16-bit step.
    write_png16(&d.join("v.png"), &want, false);
    let (got, usable) = read(d, Decoding::default());
    assert!(max_rel_err(&got, &want) < 2e-3, "{:?}", got.rgb);
    assert!(usable.iter().all(|&u| u));
    assert!(got.alpha.is_none());
    // Linear 16-bit with --linear; read as sRGB it would be far off.
    write_png16(&d.join("v.png"), &want, true);
    let (got, _) = read(
        d,
        Decoding {
            linear: true,
            ..Default::default()
        },
    );
    assert!(max_rel_err(&got, &want) < 2e-3);
    let (wrong, _) = read(d, Decoding::default());
    assert!(max_rel_err(&wrong, &want) > 0.3);
    // 8-bit sRGB: to the 8-bit step (relative error largest in the darks).
    std::fs::remove_file(d.join("v.png")).unwrap();
    write_png8(&d.join("v.png"), &want);
    let (got, _) = read(d, Decoding::default());
    assert!(max_rel_err(&got, &want) < 0.03, "{:?}", got.rgb);
    // Radiance HDR (RGBE): to its 8-bit mantissa.
    std::fs::remove_file(d.join("v.png")).unwrap();
    let mut hdr = image::Rgb32FImage::new(6, 4);
    for (p, c) in hdr.pixels_mut().zip(&want.rgb) {
        *p = image::Rgb((*c * 40.0).to_array());
    }
    image::DynamicImage::ImageRgb32F(hdr)
        .save(d.join("v.hdr"))
        .unwrap();
    // RGBE shares one exponent per pixel: each channel is exact to 1/128 of the pixel's
    // largest.
    let (got, _) = read(d, Decoding::default());
    for (g, w) in got.rgb.iter().zip(&want.rgb) {
        let w = *w * 40.0;
        assert!(
            (*g - w).abs().max_element() < w.max_element() / 128.0,
            "{g} vs {w}"
        );
    }
}

#[test]
fn saturated_and_masked_pixels_are_left_out() {
    let mut img = ramp();
    img.rgb[5] = Vec3::new(1.0, 0.2, 0.2); // one channel at the format's maximum
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    write_png8(&d.join("v.png"), &img);
    let (_, usable) = read(d, Decoding::default());
    let out: Vec<usize> = (0..24).filter(|&i| !usable[i]).collect();
    assert_eq!(out, vec![5]);
    // A mask: black leaves out, anything else keeps.
    let mut mask = image::GrayImage::from_pixel(6, 4, image::Luma([255]));
    mask.put_pixel(0, 0, image::Luma([0]));
    mask.put_pixel(2, 3, image::Luma([0]));
    mask.save(d.join("v.mask.png")).unwrap();
    let (_, usable) = read(d, Decoding::default());
    let out: Vec<usize> = (0..24).filter(|&i| !usable[i]).collect();
    assert_eq!(out, vec![0, 5, 20]);
    // A threshold on an EXR.
    std::fs::remove_file(d.join("v.png")).unwrap();
    std::fs::remove_file(d.join("v.mask.png")).unwrap();
    imageio::write_exr(&d.join("v.exr"), &ramp()).unwrap();
    let (_, usable) = read(
        d,
        Decoding {
            saturation: Some(0.85),
            ..Default::default()
        },
    );
    let want: Vec<bool> = ramp().rgb.iter().map(|c| c.max_element() < 0.85).collect();
    assert_eq!(usable, want);
    assert!(want.contains(&false) && want.contains(&true));
    // A mask of the wrong size is refused by name; of two references for one view, the EXR
    // is read (render-reference writes a PNG preview beside it).
    image::GrayImage::new(3, 2)
        .save(d.join("v.mask.png"))
        .unwrap();
    let e = load_references(d, &[&cam()], Decoding::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("v.mask.png") && e.contains("3×2"), "{e}");
    std::fs::remove_file(d.join("v.mask.png")).unwrap();
    let mut other = ramp();
    other.rgb.iter_mut().for_each(|c| *c *= 0.5);
    write_png8(&d.join("v.png"), &other);
    let (got, _) = read(d, Decoding::default());
    assert_eq!(got.rgb, ramp().rgb);
}

#[test]
fn estimate_fits_png_references_as_it_fits_their_exrs() {
    // The bundled scene's references, once as the EXRs render-reference writes and once as
    // 16-bit sRGB PNGs of them (scaled into range): both fits land at the same error.
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("s.ron");
    std::fs::write(
        &scene,
        format!(
            "Scene(gltf: {:?}, image: (width: 32, height: 24), \
             lights: [Sphere(center: (-1.8, 3.2, 1.5), radius: 0.25, radiance: (400.0, 360.0, 300.0))], \
             render: (spp: 64))",
            concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb")
        ),
    )
    .unwrap();
    let bin = env!("CARGO_BIN_EXE_lightprobe");
    let run = |args: &[&str]| {
        let o = std::process::Command::new(bin).args(args).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    let exr = tmp.path().join("exr");
    run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--quiet",
    ]);
    let png = tmp.path().join("png");
    std::fs::create_dir(&png).unwrap();
    for v in ["cam_front", "cam_side"] {
        let mut img = imageio::read_exr(&exr.join(format!("{v}.exr"))).unwrap();
        let peak = img.rgb.iter().map(|c| c.max_element()).fold(0.0, f32::max);
        img.rgb.iter_mut().for_each(|c| *c /= peak * 1.01);
        write_png16(&png.join(format!("{v}.png")), &img, false);
    }
    let rel_mae = |refs: &Path, out: &str| {
        let o = run(&[
            "estimate",
            scene.to_str().unwrap(),
            "--reference",
            refs.to_str().unwrap(),
            "--rings",
            "5",
            "--spp",
            "64",
            "--out",
            tmp.path().join(out).to_str().unwrap(),
            "--json",
            "--quiet",
        ]);
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        r["rel_mae"].as_f64().unwrap()
    };
    let (a, b) = (rel_mae(&exr, "a"), rel_mae(&png, "b"));
    // The PNGs lose the geometry's coverage alpha (silhouette pixels are then taken whole)
    // and are quantised; the fit's error barely moves.
    assert!((a - b).abs() < 0.1 * a, "EXR {a}, PNG {b}");
}

#[test]
fn per_view_exposures_of_photographs_are_fitted_and_bad_uses_refused() {
    // The bundled scene's two views under a 3-ring sky (which the 3-ring model fits exactly)
    // as 8-bit sRGB PNGs, one at half the exposure of the other: `--exposure per-view` gives
    // back their ratio; a black view, whose exposure nothing can tell, and `--fit-only`,
    // which has no re-render to compare, are refused. (Exposures are fitted through the
    // model: under the scene's near sphere light a 5-ring envmap, which misfits the two views
    // differently, gave the ratio 14% off.)
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("s.ron");
    std::fs::write(
        &scene,
        format!(
            "Scene(gltf: {:?}, image: (width: 48, height: 36), \
             lights: [Sphere(center: (-1.8, 3.2, 1.5), radius: 0.25, radiance: (400.0, 360.0, 300.0))], \
             render: (spp: 128))",
            concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb")
        ),
    )
    .unwrap();
    let bin = env!("CARGO_BIN_EXE_lightprobe");
    let run = |args: &[&str]| std::process::Command::new(bin).args(args).output().unwrap();
    let sky = tmp.path().join("sky.ron");
    std::fs::write(
        &sky,
        "Envmap(rings: 3, radiance: [(0.6, 0.7, 1.0), (3.0, 2.0, 1.0), (0.2, 0.3, 0.5), \
         (1.5, 1.5, 1.5), (0.4, 0.8, 2.0), (0.3, 0.3, 0.3)])",
    )
    .unwrap();
    let exr = tmp.path().join("exr");
    let o = run(&[
        "render-reference",
        scene.to_str().unwrap(),
        "--envmap",
        sky.to_str().unwrap(),
        "--no-sphere-lights",
        "--out",
        exr.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let png = tmp.path().join("png");
    std::fs::create_dir(&png).unwrap();
    let mut peak = 0.0f32;
    let images: Vec<Image> = ["cam_front", "cam_side"]
        .map(|v| imageio::read_exr(&exr.join(format!("{v}.exr"))).unwrap())
        .into_iter()
        .inspect(|img| peak = img.rgb.iter().map(|c| c.max_element()).fold(peak, f32::max))
        .collect();
    for (v, (mut img, e)) in ["cam_front", "cam_side"]
        .iter()
        .zip(images.into_iter().zip([0.9, 0.45]))
    {
        img.rgb.iter_mut().for_each(|c| *c *= e / peak);
        write_png8(&png.join(format!("{v}.png")), &img);
    }
    let estimate = |refs: &Path, out: &str, extra: &[&str]| {
        let out = tmp.path().join(out);
        let mut args = vec![
            "estimate",
            scene.to_str().unwrap(),
            "--reference",
            refs.to_str().unwrap(),
            "--exposure",
            "per-view",
            "--rings",
            "3",
            "--spp",
            "64",
            "--out",
            out.to_str().unwrap(),
            "--quiet",
        ];
        args.extend_from_slice(extra);
        (run(&args), out)
    };
    let (o, out) = estimate(&png, "fit", &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let e = &r["exposure"]["relative"];
    let (front, side) = (
        e[0]["exposure"].as_f64().unwrap(),
        e[1]["exposure"].as_f64().unwrap(),
    );
    assert_eq!(e[0]["view"], "cam_front");
    assert!(
        ((front / side) / 2.0 - 1.0).abs() < 0.02,
        "{front} / {side}"
    );
    assert!(((front * side).sqrt() - 1.0).abs() < 1e-9);
    // The noise floor comes from the photographs themselves, not from the sidecar's sphere
    // light (which did not light them): that light's render is its own, far worse figure.
    // The 3-ring model explains the photographs within their noise.
    assert_eq!(r["noise_floor_source"], "neighbouring-pixels");
    let floor = r["noise_floor_rel_mae"].as_f64().unwrap();
    let lights = r["true_lights_rel_mae"].as_f64().unwrap();
    assert!(floor > 0.0 && lights > 10.0 * floor, "{floor} {lights}");
    assert_eq!(r["fit_test"]["misfit"], false, "{}", r["fit_test"]);

    let (o, out) = estimate(&png, "fit_only", &["--fit-only"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--exposure per-view"),
        "{err}"
    );
    assert!(!out.join("report.json").exists());

    let black = tmp.path().join("black");
    std::fs::create_dir(&black).unwrap();
    std::fs::copy(png.join("cam_front.png"), black.join("cam_front.png")).unwrap();
    write_png8(&black.join("cam_side.png"), &Image::new(48, 36));
    let (o, out) = estimate(&black, "black", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("\"cam_side\"") && err.contains("exposure"),
        "{err}"
    );
    assert!(!out.join("report.json").exists());
}

#[test]
fn environment_maps_are_read_from_exr_and_hdr() {
    // A lat-long map as EXR and as Radiance .hdr: import-envmap gives the same cells (to the
    // .hdr's 8-bit mantissa), and render-reference --envmap with the image renders exactly
    // what it renders with the ring envmap import-envmap makes of it. Other formats are
    // refused naming the file.
    let tmp = tempfile::tempdir().unwrap();
    let (w, h) = (64u32, 32u32);
    let mut img = Image::new(w, h);
    for (i, p) in img.rgb.iter_mut().enumerate() {
        let (x, y) = (
            (i as u32 % w) as f32 / w as f32,
            (i as u32 / w) as f32 / h as f32,
        );
        *p = Vec3::new(0.2 + 3.0 * x, 0.5 + 0.5 * y, 1.0 + (6.0 * x).sin().abs());
    }
    let exr = tmp.path().join("sky.exr");
    imageio::write_exr(&exr, &img).unwrap();
    let hdr = tmp.path().join("sky.hdr");
    let pixels: Vec<image::Rgb<f32>> = img.rgb.iter().map(|c| image::Rgb(c.to_array())).collect();
    image::codecs::hdr::HdrEncoder::new(std::fs::File::create(&hdr).unwrap())
        .encode(&pixels, w as usize, h as usize)
        .unwrap();
    let bin = env!("CARGO_BIN_EXE_lightprobe");
    let run = |args: &[&str]| std::process::Command::new(bin).args(args).output().unwrap();
    let ok = |o: std::process::Output| {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let cells = |from: &Path, name: &str| {
        let out = tmp.path().join(name);
        ok(run(&[
            "import-envmap",
            from.to_str().unwrap(),
            "--rings",
            "9",
            "--target",
            "blender",
            "--out",
            out.to_str().unwrap(),
        ]));
        lightprobe::envmap::Envmap::load(&out).unwrap()
    };
    let (a, b) = (cells(&exr, "a.ron"), cells(&hdr, "b.ron"));
    for (x, y) in a.radiance().iter().zip(b.radiance()) {
        assert!(
            (*x - *y).abs().max_element() < 0.01 * x.max_element(),
            "{x} vs {y}"
        );
    }
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.ron");
    let render = |envmap: &Path, out: &str| {
        let out = tmp.path().join(out);
        ok(run(&[
            "render-reference",
            scene,
            "--envmap",
            envmap.to_str().unwrap(),
            "--envmap-target",
            "blender",
            "--envmap-rings",
            "9",
            "--no-sphere-lights",
            "--height",
            "12",
            "--spp",
            "4",
            "--out",
            out.to_str().unwrap(),
            "--quiet",
        ]));
        std::fs::read(out.join("cam_side.exr")).unwrap()
    };
    assert!(render(&exr, "from_exr") == render(&tmp.path().join("a.ron"), "from_ron"));
    let png = tmp.path().join("sky.png");
    write_png8(&png, &img);
    for args in [
        vec![
            "import-envmap",
            png.to_str().unwrap(),
            "--rings",
            "3",
            "--out",
            "x.ron",
        ],
        vec![
            "render-reference",
            scene,
            "--envmap",
            png.to_str().unwrap(),
            "--out",
            "x",
        ],
    ] {
        let o = run(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains("sky.png") && err.contains(".hdr"),
            "{err}"
        );
    }
}

#[test]
fn twins_of_the_references_measure_their_noise_and_test_the_fit() {
    // The bundled scene under a 3-ring sky, rendered with `--twin`: the 3-ring model explains
    // the images, so against the twins its fit test reads 1 within noise, and the floor agrees
    // with the neighbouring pixels' (which are calibrated under a right model); a 1-ring model
    // cannot hold the sky and fails the test. A missing or misshapen twin is refused.
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("s.ron");
    std::fs::write(
        &scene,
        format!(
            "Scene(gltf: {:?}, image: (width: 64, height: 48), render: (spp: 64))",
            concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb")
        ),
    )
    .unwrap();
    let sky = tmp.path().join("sky.ron");
    std::fs::write(
        &sky,
        "Envmap(rings: 3, radiance: [(0.6, 0.7, 1.0), (3.0, 2.0, 1.0), (0.2, 0.3, 0.5), \
         (1.5, 1.5, 1.5), (0.4, 0.8, 2.0), (0.3, 0.3, 0.3)])",
    )
    .unwrap();
    let bin = env!("CARGO_BIN_EXE_lightprobe");
    let run = |args: &[&str]| std::process::Command::new(bin).args(args).output().unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let refs = tmp.path().join("refs");
    let o = run(&[
        "render-reference",
        &s(&scene),
        "--envmap",
        &s(&sky),
        "--twin",
        "--out",
        &s(&refs),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(refs.join("cam_front_b.exr").is_file() && refs.join("cam_side_b.exr").is_file());
    let estimate = |refs: &Path, rings: &str, out: &str| {
        let o = run(&[
            "estimate",
            &s(&scene),
            "--reference",
            &s(refs),
            "--rings",
            rings,
            "--spp",
            "64",
            "--out",
            &s(&tmp.path().join(out)),
            "--json",
            "--quiet",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap()
    };
    let right = estimate(&refs, "3", "right");
    assert_eq!(right["noise_floor_source"], "given-twins");
    let t = &right["fit_test"];
    let ratio = t["residual_over_noise"].as_f64().unwrap();
    assert!(
        !t["misfit"].as_bool().unwrap() && (0.85..1.15).contains(&ratio),
        "{t}"
    );

    // The same references without their twins: the neighbouring pixels' floor.
    let alone = tmp.path().join("alone");
    std::fs::create_dir(&alone).unwrap();
    for v in ["cam_front", "cam_side"] {
        std::fs::copy(
            refs.join(format!("{v}.exr")),
            alone.join(format!("{v}.exr")),
        )
        .unwrap();
    }
    let neighbours = estimate(&alone, "3", "neighbours");
    assert_eq!(neighbours["noise_floor_source"], "neighbouring-pixels");
    let (a, b) = (
        right["noise_floor_rel_mae"].as_f64().unwrap(),
        neighbours["noise_floor_rel_mae"].as_f64().unwrap(),
    );
    assert!((a - b).abs() < 0.1 * a, "twins {a}, neighbours {b}");

    let wrong = estimate(&refs, "1", "wrong");
    assert!(
        wrong["fit_test"]["misfit"].as_bool().unwrap(),
        "{}",
        wrong["fit_test"]
    );

    // A twin for one view only, then one of the wrong size: refused, naming what is wrong.
    std::fs::remove_file(refs.join("cam_side_b.exr")).unwrap();
    let refuse = |want: &[&str]| {
        let o = run(&["estimate", &s(&scene), "--reference", &s(&refs), "--out"]
            .into_iter()
            .chain([s(&tmp.path().join("refused")).as_str(), "--quiet"])
            .collect::<Vec<_>>());
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!o.status.success(), "{err}");
        for w in want {
            assert!(err.contains(w), "{err:?} lacks {w:?}");
        }
        assert!(!tmp.path().join("refused").join("report.json").exists());
    };
    refuse(&["cam_side", "twin", "every view"]);
    let small = Image {
        width: 32,
        height: 24,
        rgb: vec![Vec3::ONE; 32 * 24],
        alpha: None,
    };
    imageio::write_exr(&refs.join("cam_side_b.exr"), &small).unwrap();
    refuse(&["cam_side_b.exr", "32×24", "twin"]);
    // A twin that is its reference again (the same seed) measures no noise.
    std::fs::copy(refs.join("cam_side.exr"), refs.join("cam_side_b.exr")).unwrap();
    refuse(&["cam_side_b.exr", "equals", "another seed"]);

    // A camera named as a view's twin: its reference is no twin, and --twin will not
    // overwrite it.
    let named = tmp.path().join("named.ron");
    std::fs::write(
        &named,
        format!(
            "Scene(gltf: {:?}, image: (width: 64, height: 48), render: (spp: 16), \
             views: [\"cam_front\", \"cam_side\"], \
             cameras: [(name: \"cam_side_b\", yfov: 0.7, pose: LookAt(eye: (0, 1, 3), target: (0, 0, 0)))])",
            concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb")
        ),
    )
    .unwrap();
    let o = run(&[
        "render-reference",
        &s(&named),
        "--twin",
        "--envmap",
        &s(&sky),
        "--out",
        &s(&tmp.path().join("r2")),
        "--quiet",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("\"cam_side_b\" is a camera"),
        "{err}"
    );
    assert!(!tmp.path().join("r2").join("cam_front_b.exr").exists());
    std::fs::copy(refs.join("cam_front.exr"), refs.join("cam_side_b.exr")).unwrap();
    let o = run(&[
        "estimate",
        &s(&named),
        "--reference",
        &s(&refs),
        "--out",
        &s(&tmp.path().join("refused")),
        "--quiet",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("is a camera of the scene"),
        "{err}"
    );
    // Rendering again without --twin removes the twins an earlier --twin left.
    let o = run(&[
        "render-reference",
        &s(&scene),
        "--envmap",
        &s(&sky),
        "--out",
        &s(&refs),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!refs.join("cam_front_b.exr").exists() && refs.join("cam_front.exr").exists());
}
