//! The estimator against known answers: a known envmap recovered, a distant sphere light
//! located, and the solvers at the optimum.

use std::path::Path;
use std::time::Duration;

use glam::Vec3;
mod common;
use common::{icosphere, plane};
use lightprobe::envmap::{Envmap, RingGrid};
use lightprobe::estimate::select::MODEL_TOLERANCE;
use lightprobe::estimate::{self, FitSettings, Solver, recovery};
use lightprobe::imageio::Image;
use lightprobe::metrics;
use lightprobe::render::{Lights, RenderSettings, Renderer, Strategy};
use lightprobe::scene::{Albedo, Camera, Material, Scene, SceneSettings, SphereLight};

/// A table-like plane with a ball and a box on it, seen from two sides.
fn scene(lights: Vec<SphereLight>) -> Scene {
    let mut mesh = plane(1.0, 0.0);
    let ball = icosphere(Vec3::new(-0.3, 0.25, 0.1), 0.25, 3);
    mesh.append(&ball, 1);
    let (lo, hi) = (Vec3::new(0.2, 0.0, -0.3), Vec3::new(0.45, 0.4, -0.05));
    let c = |x: bool, y: bool, z: bool| {
        Vec3::new(
            if x { hi.x } else { lo.x },
            if y { hi.y } else { lo.y },
            if z { hi.z } else { lo.z },
        )
    };
    let corners = [
        c(false, false, false),
        c(true, false, false),
        c(true, true, false),
        c(false, true, false),
        c(false, false, true),
        c(true, false, true),
        c(true, true, true),
        c(false, true, true),
    ];
    let faces = [
        0, 1, 2, 0, 2, 3, 4, 6, 5, 4, 7, 6, 0, 4, 5, 0, 5, 1, 3, 2, 6, 3, 6, 7, 0, 3, 7, 0, 7, 4,
        1, 5, 6, 1, 6, 2,
    ];
    mesh.push(&corners, None, None, &faces, 2);
    let (w, h) = (128, 96);
    Scene {
        mesh,
        materials: vec![
            Material {
                name: "table".into(),
                albedo: Albedo::Constant(Vec3::new(0.6, 0.55, 0.5)),
            },
            Material {
                name: "ball".into(),
                albedo: Albedo::Constant(Vec3::new(0.8, 0.8, 0.8)),
            },
            Material {
                name: "box".into(),
                albedo: Albedo::Constant(Vec3::new(0.7, 0.3, 0.2)),
            },
        ],
        cameras: vec![
            Camera::look_at(
                "a",
                Vec3::new(0.0, 1.2, 1.8),
                Vec3::new(0.0, 0.1, 0.0),
                0.9,
                w,
                h,
            ),
            Camera::look_at(
                "b",
                Vec3::new(1.7, 1.0, -0.8),
                Vec3::new(0.0, 0.1, 0.0),
                0.9,
                w,
                h,
            ),
        ],
        lights,
        settings: SceneSettings {
            spp: 256,
            max_bounces: 2,
            seed: 1,
            rings: 5,
        },
        size_given: true,
        camera_names: Vec::new(),
        ignored: Vec::new(),
        source: Default::default(),
        gltf: Default::default(),
    }
}

fn settings(spp: u32, seed: u64) -> RenderSettings {
    RenderSettings {
        spp,
        max_bounces: 2,
        seed,
        strategy: Strategy::Mis,
        hide_emitters: true,
        camera_sees_lights: true,
        every_light: false,
    }
}

fn fit_settings(rings: u32, spp: u32, solver: Solver, ridge: f64) -> FitSettings {
    FitSettings {
        rings,
        transport: settings(spp, 99),
        solver,
        smooth: 0.0,
        ridge,
        rounds: 1,
        time_limit: Duration::from_secs(60),
        holdout: false,
        jackknife: 0,
        colour: estimate::Colour::PerChannel,
    }
}

/// Renders every view of `sc` under `lights`; returns images and their geometry masks.
fn render_all(r: &Renderer, sc: &Scene, spp: u32, seed: u64) -> (Vec<Image>, Vec<Vec<bool>>) {
    let imgs: Vec<Image> = sc
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| r.render_radiance(c, i as u64, &settings(spp, seed), &|_| {}))
        .collect();
    let masks = imgs.iter().map(metrics::mask_of).collect();
    (imgs, masks)
}

/// The sphere model's observations: every pixel, summed over 4×4 bins.
fn binned<'a>(
    cameras: &'a [&'a Camera],
    masks: &'a [Vec<bool>],
    references: &'a [Image],
) -> estimate::spheres::Observations<'a> {
    estimate::spheres::Observations {
        cameras,
        masks,
        evaluated: masks,
        references,
        bin: 4,
        holdout: false,
        background: None,
        paths: None,
        progress: None,
    }
}

/// A 3-ring sky (zenith, four horizon sectors, nadir) with distinct colours.
fn three_ring_sky() -> Envmap {
    Envmap::new(
        3,
        vec![
            Vec3::new(0.6, 0.7, 1.0),
            Vec3::new(3.0, 2.0, 1.0),
            Vec3::new(0.2, 0.3, 0.5),
            Vec3::new(1.5, 1.5, 1.5),
            Vec3::new(0.4, 0.8, 2.0),
            Vec3::new(0.3, 0.3, 0.3),
        ],
    )
    .unwrap()
}

/// A sphere light 1.9 m from the 2 m table: too near for any envmap.
const NEAR_LIGHT: SphereLight = SphereLight {
    center: Vec3::new(0.8, 1.6, 0.6),
    radius: 0.15,
    radiance: Vec3::new(60.0, 50.0, 40.0),
};

/// A sky with a warm and a blue bright cell.
fn known_envmap(rings: u32) -> Envmap {
    let g = RingGrid::new(rings);
    let radiance = (0..g.cell_count() as u32)
        .map(|c| {
            let d = g.center(c);
            let sky = Vec3::new(0.2, 0.3, 0.5) * (0.5 + 0.5 * d.y.max(0.0));
            if c == g.ring_start(1) + 1 {
                Vec3::new(8.0, 6.0, 3.0)
            } else if c == g.ring_start(2) + 5 {
                Vec3::new(1.0, 2.0, 4.0)
            } else {
                sky
            }
        })
        .collect();
    Envmap::new(rings, radiance).unwrap()
}

#[test]
fn a_known_envmap_is_recovered_at_the_noise_floor() {
    // Exact recovery needs cells the images can tell apart. A diffuse scene low-pass filters
    // its lighting: with 5 rings here the fit renders at the noise floor yet shuffles energy
    // between neighbouring 45° cells (measured: a pole cell fitted 1.28 for a true 0.2). With
    // 3 rings (the zenith, four horizon sectors and the nadir) the ball and box shadows
    // separate every cell above the table; the nadir, hidden by the table, is not checked.
    let rings = 3;
    let truth = three_ring_sky();
    let sc = scene(vec![]);
    let lights = Lights::env(truth.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 1024, 1);
    let (again, _) = render_all(&r, &sc, 1024, 2);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let fit = estimate::fit(
        &r,
        &cams,
        &refs,
        &masks,
        &fit_settings(rings, 2048, Solver::Nnls, 1e-4),
        &|_| {},
    );
    assert!(
        fit.channels
            .iter()
            .all(|c| c.converged && c.kkt_violation < 1e-6),
        "{:?}",
        fit.channels
    );

    // Photometric error of a fresh render of the estimate, against the noise floor.
    let est_lights = Lights::env(fit.envmap.clone());
    let (est, _) = render_all(&r.with_lights(&est_lights), &sc, 1024, 3);
    for v in 0..2 {
        let e = metrics::compare(&est[v], &refs[v], &masks[v])
            .unwrap()
            .rel_mae;
        let floor = metrics::compare(&again[v], &refs[v], &masks[v])
            .unwrap()
            .rel_mae;
        assert!(
            e < 1.3 * floor,
            "view {v}: relMAE {e} vs noise floor {floor}"
        );
    }
    // Every cell above the table comes back within 10% (in luminance).
    for cell in 0..5 {
        let (want, got) = (truth.radiance()[cell], fit.envmap.radiance()[cell]);
        let (lw, lg) = (
            lightprobe::imageio::luminance(want),
            lightprobe::imageio::luminance(got),
        );
        assert!((lg / lw - 1.0).abs() < 0.10, "cell {cell}: {got} vs {want}");
    }
}

#[test]
fn one_pass_recovers_a_sky_in_a_grid_it_did_not_sample_by() {
    // `--rings auto` fits every candidate from one pass whose cells are sampled on the finest
    // candidate's grid (9 rings here): the 3-ring rows are binned from path directions. They
    // must still be an unbiased transport of the 3-ring grid, so the 3-ring sky comes back
    // as exactly as from its own pass (the exact-recovery test above: every cell above the
    // table within 10%), on the held-in pixels and refitted on all of them.
    let truth = three_ring_sky();
    let sc = scene(vec![]);
    let lights = Lights::env(truth.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 1024, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let template = FitSettings {
        rounds: 4,
        holdout: true,
        ..fit_settings(3, 2048, Solver::Nnls, 1e-4)
    };
    let c = estimate::fit_candidates(&r, &cams, &refs, &masks, &template, &[3, 5, 9], &|_| {});
    assert_eq!(
        c.grids.iter().map(|g| g.rings()).collect::<Vec<_>>(),
        [3, 5, 9]
    );
    let all = FitSettings {
        holdout: false,
        ..template
    };
    let refit = c.refit(0, &all, &r, &cams, &refs, &masks, &|_| {});
    for (what, fit) in [("held-in", &c.fits[0]), ("refit", &refit)] {
        assert_eq!(fit.envmap.grid.rings(), 3);
        for cell in 0..5 {
            let (want, got) = (truth.radiance()[cell], fit.envmap.radiance()[cell]);
            let (lw, lg) = (
                lightprobe::imageio::luminance(want),
                lightprobe::imageio::luminance(got),
            );
            assert!(
                (lg / lw - 1.0).abs() < 0.10,
                "{what}, cell {cell}: {got} vs {want}"
            );
        }
    }
    // The finer candidates explain the same images: their renders match the references'
    // total light to within a few percent.
    for fit in &c.fits[1..] {
        let est = Lights::env(fit.envmap.clone());
        let (img, _) = render_all(&r.with_lights(&est), &sc, 256, 3);
        for v in 0..2 {
            let e = metrics::compare(&img[v], &refs[v], &masks[v]).unwrap();
            assert!(
                e.rel_mae < 0.05,
                "{} rings, view {v}: {e:?}",
                fit.envmap.grid.rings()
            );
        }
    }
}

#[test]
fn a_small_distant_sphere_light_is_located_within_its_own_disc() {
    // 100 m away, 1.4° across. (At 10 m, 6× the table's size, the same light came out
    // 3.7–4.1° off at 17–41 rings, whatever the samples: parallax, not the estimator. From
    // the table's edges it lies up to 3° either side of its direction from the centre, and
    // an envmap can only hold one direction.)
    let center = Vec3::new(0.0, 0.1, 0.0);
    let dir = Vec3::new(0.45, 0.8, 0.3).normalize();
    let light = SphereLight {
        center: center + dir * 100.0,
        radius: 2.5,
        radiance: Vec3::splat(3000.0),
    };
    let sc = scene(vec![light]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let fit = estimate::fit(
        &r,
        &cams,
        &refs,
        &masks,
        &FitSettings {
            rounds: 4,
            ..fit_settings(21, 512, Solver::Nnls, 1e-3)
        },
        &|_| {},
    );
    let rec = recovery::recover(&fit.envmap, &sc.lights, center);
    assert_eq!(rec.len(), 1);
    // Measured (21 rings, 4 rounds of 512 spp): 0.53°, power ×1.013; 17 and 31 rings: 0.43°,
    // 0.40°; 4 rounds of 128 spp: 0.65°. Inside the light's own disc (0.7° in radius) with
    // room for that spread.
    assert!(rec[0].angle_error_degrees < 1.0, "{:?}", rec[0]);
    assert!((0.9..1.1).contains(&rec[0].power_ratio), "{:?}", rec[0]);
}

#[test]
fn gradient_and_nnls_reach_the_same_optimum() {
    let rings = 3;
    let sc = scene(vec![]);
    let lights = Lights::env(known_envmap(rings));
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    // One round each, same transport (same seed and sampling): the same quadratic problem.
    let a = estimate::fit(
        &r,
        &cams,
        &refs,
        &masks,
        // The gradient solver fits each channel on its own: the same objective.
        &FitSettings {
            colour: estimate::Colour::PerChannel,
            ..fit_settings(rings, 256, Solver::Nnls, 1e-4)
        },
        &|_| {},
    );
    let b = estimate::fit(
        &r,
        &cams,
        &refs,
        &masks,
        &fit_settings(rings, 256, Solver::Gradient, 1e-4),
        &|_| {},
    );
    for ch in 0..3 {
        let (fa, fb) = (
            *a.channels[ch].objective.last().unwrap(),
            *b.channels[ch].objective.last().unwrap(),
        );
        assert!(
            b.channels[ch].converged,
            "gradient did not converge in channel {ch}"
        );
        assert!(
            (fb - fa).abs() <= 1e-3 * fa.abs().max(1e-12),
            "channel {ch}: gradient {fb} vs nnls {fa}"
        );
    }
    for (x, y) in a.envmap.radiance().iter().zip(b.envmap.radiance()) {
        assert!(
            (*x - *y).abs().max_element() < 0.02 * x.max_element().max(0.1),
            "{x} vs {y}"
        );
    }
}

#[test]
fn rings_auto_rejects_grids_too_coarse_for_the_data() {
    // A sky that a 3-ring grid represents exactly. Measured (256 transport spp in 2 rounds,
    // ridge 0.001, candidates re-rendered at 512 spp): held-out relMAE 1.38% at 3 rings,
    // 1.33% at 9, 2.19% at 15, all near the noise floor; the rule takes 9. Nine rings fit
    // the sky about as well, and their finer cells importance-sample it better in the
    // re-render: at this level rendering noise is much of the error. (It is part of what a
    // user gets, so it is a fair part of the choice.) With ridge 0.01 the 3-ring fit was
    // 1% too dark, which the noise used to hide: 1.81% against 1.27%. What must hold: the
    // true resolution is close to the best, and the rule's choice is within one standard
    // error of it.
    let truth = three_ring_sky();
    let sc = scene(vec![]);
    let sky = Lights::env(truth);
    let r = Renderer::new(&sc, &sky);
    let (refs, masks) = render_all(&r, &sc, 512, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let template = FitSettings {
        rounds: 2,
        ..fit_settings(1, 256, Solver::Nnls, 1e-3)
    };
    let s =
        estimate::select::select_rings(&r, &cams, &refs, &masks, &[3, 9, 15], &template, &|_| {})
            .unwrap()
            .selection;
    let best = s
        .candidates
        .iter()
        .find(|c| c.rings == s.best_rings)
        .unwrap();
    assert!(
        s.candidates[0].validation_rel_mae < 1.25 * best.validation_rel_mae,
        "{s:#?}"
    );
    let chosen = s.candidates.iter().find(|c| c.rings == s.rings).unwrap();
    assert!(chosen.excess_over_best <= chosen.standard_error, "{s:#?}");
    assert!(
        s.candidates
            .iter()
            .filter(|c| c.rings < s.rings)
            .all(|c| c.excess_over_best > c.standard_error),
        "{s:#?}"
    );
    // About a quarter of the masked pixels were held out.
    let masked: usize = masks.iter().map(|m| m.iter().filter(|&&b| b).count()).sum();
    let f = s.held_out_pixels as f64 / masked as f64;
    assert!((0.22..0.28).contains(&f), "held out {f}");

    // A small distant sphere light is far from a 3-ring sky: held-out pixels say so clearly.
    let center = Vec3::new(0.0, 0.1, 0.0);
    let light = SphereLight {
        center: center + Vec3::new(0.45, 0.8, 0.3).normalize() * 10.0,
        radius: 0.25,
        radiance: Vec3::splat(3000.0),
    };
    let sc = scene(vec![light]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 512, 1);
    let s =
        estimate::select::select_rings(&r, &cams, &refs, &masks, &[3, 9, 15], &template, &|_| {})
            .unwrap()
            .selection;
    assert!(s.rings >= 9, "{s:#?}");
    let c3 = &s.candidates[0];
    assert!(c3.excess_over_best > 3.0 * c3.standard_error, "{c3:?}");
    // Measured: 11.0% at 3 rings against 7.6% at 9 and 7.3% at 15.
    assert!(
        c3.validation_rel_mae > 1.1 * s.candidates[1].validation_rel_mae,
        "{s:#?}"
    );
}

#[test]
fn sphere_light_radiance_is_recovered_given_its_geometry_and_wrong_geometry_shows() {
    // A light 1.9 m from a 2 m table: no envmap fits it, but with its centre and radius known
    // the images are linear in its radiance (the sphere model's inner solve).
    let truth = NEAR_LIGHT;
    let sc = scene(vec![truth]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let (again, _) = render_all(&r, &sc, 256, 2);
    let floor = (0..2)
        .map(|v| {
            metrics::compare(&again[v], &refs[v], &masks[v])
                .unwrap()
                .rel_mae
        })
        .sum::<f64>()
        / 2.0;
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let st = settings(256, 77);
    // Single pixels (bin 1): this checks the per-pixel error against the noise floor.
    let obs = estimate::spheres::Observations {
        cameras: &cams,
        masks: &masks,
        evaluated: &masks,
        references: &refs,
        bin: 1,
        holdout: false,
        background: None,
        paths: None,
        progress: None,
    };
    let solve = |geometry: SphereLight| {
        let p = estimate::spheres::sphere_problem(&r, &obs, &[geometry], &st);
        estimate::spheres::solve_radiance(&p)
    };
    let (radiance, err) = solve(truth);
    // Measured: radiance within 0.02%, relMAE 0.685% against a noise floor of 0.686%; moved
    // 10 cm: 3.65%; 30% farther: 6.54%.
    for ch in 0..3 {
        let ratio = radiance[0][ch] / truth.radiance[ch];
        assert!((ratio - 1.0).abs() < 0.005, "channel {ch}: {radiance:?}");
    }
    // Its error is that of a second render: the noise floor.
    assert!(err < 1.1 * floor, "relMAE {err} vs noise floor {floor}");
    // With the same random numbers, a light 10 cm off or 30% farther along the same direction
    // (brightness refitted) explains the images clearly worse: the geometry is identifiable.
    let center = Vec3::new(0.0, 0.1, 0.0);
    let farther = center + (truth.center - center) * 1.3;
    for moved in [truth.center + Vec3::new(0.1, 0.0, 0.0), farther] {
        let (_, e) = solve(SphereLight {
            center: moved,
            ..truth
        });
        assert!(e > 3.0 * err, "moved to {moved}: {e} vs {err}");
    }
}

#[test]
fn per_light_transports_sample_every_light() {
    // Two lights of similar weight at unit radiance: picking one per vertex makes each
    // light's transport a coin toss with variance of the order of the signal, which on a
    // tabletop scenario let a wrong single light score below the true pair. Sampling every
    // light removes that variance; stratifying the pick removes most of it too.
    let fill = SphereLight {
        center: Vec3::new(-1.0, 1.4, 0.4),
        radius: 0.12,
        radiance: Vec3::new(20.0, 22.0, 25.0),
    };
    let sc = scene(vec![NEAR_LIGHT, fill]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let obs = binned(&cams, &masks, &refs);
    let error = |geometry: &[SphereLight], every_light: bool| {
        let st = RenderSettings {
            every_light,
            ..settings(64, 5)
        };
        let p = estimate::spheres::sphere_problem(&r, &obs, geometry, &st);
        estimate::spheres::solve_radiance(&p).1
    };
    let (picked, every) = (error(&sc.lights, false), error(&sc.lights, true));
    let key_only = error(&[NEAR_LIGHT], true);
    eprintln!(
        "binned relMAE at the truth: picked {picked:.5}, every light {every:.5}; key only {key_only:.5}"
    );
    // Measured: picked 0.37%, every light 0.27%, key only 13.2%. (Picked was 1.27% against
    // 0.42% before the first vertex's light sample was stratified over each pixel's samples:
    // the coin toss now evens out within a pixel, so sampling every light gains less.)
    assert!(every < 0.8 * picked, "{every} vs {picked}");
    assert!(every < 0.5 * key_only, "{every} vs {key_only}");
}

/// Levenberg–Marquardt from `start` (4×4 bins, 64-spp residuals, 16-spp Jacobians) on
/// 256-spp references of [`NEAR_LIGHT`] alone, about the table's centre.
fn refine_near_light(
    start: SphereLight,
    max_iterations: usize,
    polish_radii: bool,
) -> estimate::spheres::Refined {
    let sc = scene(vec![NEAR_LIGHT]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let obs = binned(&cams, &masks, &refs);
    estimate::spheres::refine(
        &r,
        &obs,
        &[start],
        Vec3::new(0.0, 0.1, 0.0),
        &estimate::spheres::RefineSettings {
            residual: settings(64, 5),
            jacobian: settings(16, 6),
            max_iterations,
            fixed: 0,
            polish_radii,
            radiance_spp: 0,
        },
    )
}

#[test]
fn levenberg_marquardt_moves_a_misplaced_sphere_light_back() {
    let truth = NEAR_LIGHT;
    let center = Vec3::new(0.0, 0.1, 0.0);
    // Start 25% too far along the true direction, 15 cm sideways, radius ×1.6.
    let start = SphereLight {
        center: center + (truth.center - center) * 1.25 + Vec3::new(0.0, 0.0, -0.15),
        radius: 0.24,
        radiance: Vec3::ONE,
    };
    let out = refine_near_light(start, 10, false);
    let got = out.lights[0];
    let dist = (truth.center - center).length();
    let off = got.center.distance(truth.center);
    let power = |l: &SphereLight| lightprobe::imageio::luminance(l.radiance) * l.radius * l.radius;
    eprintln!(
        "centre {off:.4} m off ({:.2}% of {dist:.2} m), radius {:.3}, power ×{:.3}, {} renders",
        100.0 * off / dist,
        got.radius,
        power(&got) / power(&truth),
        out.evaluations
    );
    // Measured (4×4 bins, 64-spp residuals, 16-spp Jacobians): centre 1.1 mm off (0.06% of
    // 1.80 m), radius 0.151 (true 0.15), power ×1.001, 61 renders. (Single pixels and one
    // 64-spp render for both: 11 mm, ×1.011, 101 renders.) The goal is 2% and 5%.
    assert!(off < 0.005 * dist, "{out:?}");
    assert!((power(&got) / power(&truth) - 1.0).abs() < 0.02, "{out:?}");
}

#[test]
fn a_light_started_far_too_small_grows_to_its_size() {
    // Scenario s50's failure: a 0.42 m lamp fitted from a start at a sixth of its radius
    // stalled at 0.07 m (its penumbrae hardly move under the Jacobian's 3% step), and a third
    // light grew beside it to widen them. The direct search on the apparent size must get
    // there from the true centre.
    let truth = NEAR_LIGHT;
    let start = SphereLight {
        radius: truth.radius / 6.0,
        radiance: Vec3::ONE,
        ..truth
    };
    let (without, with) = (
        refine_near_light(start, 2, false),
        refine_near_light(start, 2, true),
    );
    let ratio = |o: &estimate::spheres::Refined| o.lights[0].radius / truth.radius;
    eprintln!(
        "radius ×{:.3} without the search ({} renders), ×{:.3} with it ({} renders)",
        ratio(&without),
        without.evaluations,
        ratio(&with),
        with.evaluations
    );
    // Measured: ×0.167 without the search (20 renders), ×0.931 with it (46 renders).
    assert!((ratio(&with) - 1.0).abs() < 0.1, "{with:?}");
}

/// Envmap fit (5 rings), sphere fits with up to `max_k` lights and the chosen one's lights
/// with a 5-ring envmap behind them, all without the held-out pixels, then `--model auto`'s
/// choice.
fn select_model(
    sc: &Scene,
    r: &Renderer,
    refs: &[Image],
    masks: &[Vec<bool>],
    max_k: usize,
) -> (
    estimate::select::ModelSelection,
    Vec<estimate::pipeline::SphereOutcome>,
) {
    use estimate::pipeline;
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let center = Vec3::new(0.0, 0.1, 0.0);
    let render = settings(256, 1);
    let options = pipeline::EstimateOptions {
        fit: FitSettings {
            holdout: true,
            ..fit_settings(5, 256, Solver::Nnls, 0.01)
        },
        fitted: false,
        evaluate: true,
        noise_floor: false,
        oracle: false,
    };
    let env = pipeline::run(
        r,
        r,
        &cams,
        refs,
        masks,
        &[],
        center,
        &options,
        None,
        &render,
        &|_| {},
    )
    .unwrap();
    let paths = estimate::spheres::PathCache::default();
    let obs = estimate::spheres::Observations {
        cameras: &cams,
        masks,
        evaluated: masks,
        references: refs,
        bin: 4,
        holdout: true,
        background: None,
        paths: Some(&paths),
        progress: None,
    };
    let spheres = pipeline::run_sphere_models(
        r,
        r,
        &obs,
        &env.fit.envmap,
        &[],
        (center, 2.0),
        max_k,
        true,
        &render,
        true,
        &|_| false,
        &|_| {},
    )
    .unwrap();
    // Sphere models again with a 5-ring envmap behind their lights.
    let combined: Vec<_> = pipeline::background_bases(&spheres, refs, masks)
        .into_iter()
        .map(|base| {
            pipeline::run_with_background(
                r,
                r,
                &obs,
                &base.fit,
                5,
                &[],
                (center, 2.0),
                &render,
                true,
                &|_| {},
            )
            .unwrap()
        })
        .collect();
    let mut all = spheres;
    all.extend(combined);
    let sel = pipeline::select_model(Some(&env), &all, refs, masks).unwrap();
    (sel, all)
}

#[test]
fn model_selection_picks_a_sphere_for_a_near_light_and_the_envmap_for_a_smooth_sky() {
    // Near light: one sphere explains the images; the envmap cannot (parallax).
    let sc = scene(vec![NEAR_LIGHT]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let (sel, _) = select_model(&sc, &r, &refs, &masks, 2);
    eprintln!("near light: {sel:#?}");
    // Measured: held-out relMAE spheres:1 0.67%, envmap (5 rings) 33.2%, envmap+spheres:1 0.80%.
    assert_eq!(sel.chosen, "spheres:1", "{sel:#?}");
    let env = sel.candidates.iter().find(|c| c.model == "envmap").unwrap();
    let one = sel
        .candidates
        .iter()
        .find(|c| c.model == "spheres:1")
        .unwrap();
    assert!(env.excess_over_best > 3.0 * env.standard_error, "{sel:#?}");
    assert!(
        env.validation_rel_mae > 2.0 * one.validation_rel_mae,
        "{sel:#?}"
    );

    // A smooth sky at infinity: no few spheres fit it; the envmap does.
    let sc = scene(vec![]);
    let sky = Lights::env(three_ring_sky());
    let r = Renderer::new(&sc, &sky);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let (sel, _) = select_model(&sc, &r, &refs, &masks, 2);
    eprintln!("smooth sky: {sel:#?}");
    // Measured: envmap 3.82%, spheres:1 11.5%, spheres:2 5.21% (± 0.34%, 0.07%),
    // envmap+spheres:1 3.83%, envmap+spheres:2 3.92%.
    assert_eq!(sel.chosen, "envmap", "{sel:#?}");
    let env = sel.candidates.iter().find(|c| c.model == "envmap").unwrap();
    for c in sel.candidates.iter().filter(|c| c.model != "envmap") {
        if c.model.starts_with("envmap+") {
            // It holds the envmap as a special case (lights at zero), so it cannot be much
            // worse; its lights must not buy the gain a bigger model needs.
            assert!(
                c.validation_rel_mae > env.validation_rel_mae * (1.0 - MODEL_TOLERANCE),
                "{sel:#?}"
            );
        } else {
            assert!(c.excess_over_best > 3.0 * c.standard_error, "{sel:#?}");
        }
    }
}

#[test]
fn paths_walked_once_and_lit_again_render_what_a_fresh_render_does() {
    // The sphere model's renders re-light kept camera paths: under any lights, with any
    // accumulator and strategy, that must give the render's own image.
    let sc = scene(vec![NEAR_LIGHT]);
    let none = Lights::default();
    let base = Renderer::new(&sc, &none);
    let cam = &sc.cameras[1];
    let walked = settings(16, 7);
    let paths = base.trace_paths(cam, 3, &walked, None);
    let moved = SphereLight {
        center: Vec3::new(-0.5, 1.2, 0.9),
        ..NEAR_LIGHT
    };
    let lit = [
        Lights::new(vec![NEAR_LIGHT]),
        Lights::new(vec![moved, NEAR_LIGHT]),
        Lights {
            spheres: vec![moved],
            env: Some(three_ring_sky()),
            alone: None,
        },
    ];
    for (i, lights) in lit.iter().enumerate() {
        for (strategy, every_light) in [
            (Strategy::Mis, false),
            (Strategy::Mis, true),
            (Strategy::LightOnly, false),
            (Strategy::BsdfOnly, false),
        ] {
            let st = RenderSettings {
                strategy,
                every_light,
                ..walked
            };
            let r = base.with_lights(lights);
            let acc = lightprobe::render::RadianceAccumulator(lights);
            let fresh = r.render(cam, 3, &st, &acc, &|_| {});
            let again = r.render_paths(&paths, cam, &st, &acc);
            let (mut worst, mut total) = (0.0f32, 0.0f32);
            for (a, b) in fresh.pixels.iter().zip(&again.pixels) {
                worst = worst.max((*a - *b).abs().max_element());
                total += a.element_sum();
            }
            let mean = total / (3 * fresh.pixels.len()) as f32;
            // Bit-identical but where the last segment grazes an edge (closest hit against
            // an occlusion test): measured 0.
            assert!(
                worst <= 1e-4 * mean,
                "lights {i} {strategy:?} every_light {every_light}: {worst} (mean {mean})"
            );
            assert_eq!(fresh.coverage, again.coverage);
        }
    }
    // Several light sets lit from one walk (the evaluation's re-render and noise floor):
    // each image is that light set's own render.
    let sets: Vec<&Lights> = lit.iter().collect();
    let under = base.render_radiance_under(cam, 3, &walked, &sets, &|_| {});
    assert_eq!(under.len(), lit.len());
    assert!(
        base.render_radiance_under(cam, 3, &walked, &[], &|_| {})
            .is_empty()
    );
    for (i, (lights, img)) in lit.iter().zip(&under).enumerate() {
        let fresh = base
            .with_lights(lights)
            .render_radiance(cam, 3, &walked, &|_| {});
        let (mut worst, mut total) = (0.0f32, 0.0f32);
        for (a, b) in fresh.rgb.iter().zip(&img.rgb) {
            worst = worst.max((*a - *b).abs().max_element());
            total += a.element_sum();
        }
        let mean = total / (3 * fresh.rgb.len()) as f32;
        assert!(worst <= 1e-4 * mean, "lights {i}: {worst} (mean {mean})");
        assert_eq!(fresh.alpha, img.alpha);
    }
}

#[test]
fn one_light_alone_renders_its_share_of_every_lights_render() {
    // The sphere model's trial geometries move one light and render it alone (without the
    // background envmap, as the fit does): its column must be the one it has among all the
    // lights, bit for bit (same random numbers, the others still blocking it), at any depth,
    // with emitters seen by the camera, with or without an envmap beside them.
    use lightprobe::estimate::transport::{EmitterKind, PerEmitterAccumulator};
    let sc = scene(vec![NEAR_LIGHT]);
    let none = Lights::default();
    let base = Renderer::new(&sc, &none);
    let cam = &sc.cameras[0];
    // The second light sits in front of the first as seen from part of the table.
    let blocker = SphereLight {
        center: NEAR_LIGHT.center * 0.6,
        radius: 0.15,
        radiance: Vec3::ONE,
    };
    let spheres = vec![NEAR_LIGHT, blocker];
    for env in [None, Some(three_ring_sky())] {
        for max_bounces in [1, 4] {
            let st = RenderSettings {
                every_light: true,
                max_bounces,
                hide_emitters: false,
                ..settings(8, 3)
            };
            let all = Lights {
                spheres: spheres.clone(),
                env: env.clone(),
                alone: None,
            };
            let acc = PerEmitterAccumulator {
                kind: EmitterKind::Spheres,
                count: 2,
            };
            let full = base.with_lights(&all).render(cam, 9, &st, &acc, &|_| {});
            let mut lit = [0.0f32; 2];
            for j in 0..2 {
                let alone = Lights {
                    spheres: spheres.clone(),
                    env: None,
                    alone: Some(j as u32),
                };
                let one = PerEmitterAccumulator {
                    kind: EmitterKind::Sphere(j as u32),
                    count: 1,
                };
                let column = base.with_lights(&alone).render(cam, 9, &st, &one, &|_| {});
                for (a, b) in full.pixels.iter().zip(&column.pixels) {
                    assert_eq!(a[j], b[0], "light {j}, {max_bounces} bounces");
                    lit[j] += b[0].element_sum();
                }
            }
            assert!(lit[0] > 0.0 && lit[1] > 0.0, "{lit:?}");
        }
    }
    // The blocker does block: the first light alone, without it, lights the table more.
    let st = RenderSettings {
        every_light: true,
        ..settings(8, 3)
    };
    let one = PerEmitterAccumulator {
        kind: EmitterKind::Sphere(0),
        count: 1,
    };
    let lit = |spheres: Vec<SphereLight>| -> f32 {
        let l = Lights {
            spheres,
            env: None,
            alone: Some(0),
        };
        let frame = base.with_lights(&l).render(cam, 9, &st, &one, &|_| {});
        frame.pixels.iter().map(|p| p[0].element_sum()).sum()
    };
    let (blocked, free) = (lit(spheres.clone()), lit(vec![NEAR_LIGHT]));
    assert!(blocked < 0.99 * free, "{blocked} vs {free}");
}

#[test]
fn model_selection_puts_an_envmap_behind_a_near_light_under_a_sky() {
    // A near lamp under a dim sky (about a third of the light on the table): no few spheres
    // fit the sky and no envmap fits the lamp (parallax); the lamp with an envmap behind it
    // fits both.
    let sc = scene(vec![NEAR_LIGHT]);
    // Smooth, brighter toward the zenith and warm low in the south-east, on the background's
    // own 5-ring grid.
    let g = RingGrid::new(5);
    let sky = (0..g.cell_count() as u32)
        .map(|c| {
            let d = g.center(c);
            let warm = (d.dot(Vec3::new(0.6, 0.3, 0.74).normalize()).max(0.0)).powi(2);
            Vec3::new(0.25, 0.3, 0.45) * (0.3 + 0.7 * d.y.max(0.0))
                + Vec3::new(0.5, 0.35, 0.15) * warm
        })
        .collect();
    let lights = Lights {
        spheres: sc.lights.clone(),
        env: Some(Envmap::new(5, sky).unwrap()),
        alone: None,
    };
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let (sel, all) = select_model(&sc, &r, &refs, &masks, 2);
    eprintln!("lamp under a sky: {sel:#?}");
    // Measured: envmap+spheres:1 4.71%, envmap+spheres:2 4.72%, spheres:2 5.97%, spheres:1
    // 6.65%, envmap 14.9%; the lamp 0.35% of its distance off, power ×0.998.
    assert_eq!(sel.chosen, "envmap+spheres:1", "{sel:#?}");
    let best = sel
        .candidates
        .iter()
        .find(|c| c.model == sel.chosen)
        .unwrap();
    for c in sel.candidates.iter().filter(|c| c.model != sel.chosen) {
        if c.model.starts_with("envmap+") {
            // A bigger model of the same kind holds this one (a light at zero): not much
            // worse, but its extra light must not buy a bigger model's gain.
            assert!(
                c.validation_rel_mae > best.validation_rel_mae * (1.0 - MODEL_TOLERANCE),
                "{sel:#?}"
            );
        } else {
            assert!(c.excess_over_best > 3.0 * c.standard_error, "{sel:#?}");
        }
    }
    let combined = all
        .iter()
        .find(|s| s.fit.model_name() == sel.chosen)
        .unwrap();
    let got = combined.fit.lights();
    assert_eq!(got.len(), 1, "{:#?}", combined.fit);
    let dist = (NEAR_LIGHT.center - Vec3::new(0.0, 0.1, 0.0)).length();
    let off = got[0].center.distance(NEAR_LIGHT.center);
    let ratio = estimate::spheres::power(&got[0]) / estimate::spheres::power(&NEAR_LIGHT);
    eprintln!(
        "lamp: {off} m off ({:.2}% of {dist} m), power x{ratio}",
        100.0 * off / dist
    );
    assert!(off < 0.02 * dist, "{:#?}", combined.fit);
    assert!((ratio - 1.0).abs() < 0.05, "{:#?}", combined.fit);
}

#[test]
fn degenerate_sphere_fits_are_reported_not_hidden() {
    use estimate::spheres::{
        LightStatus, Observations, SphereSettings, fit_sphere_models, judge, refine,
    };
    let center = Vec3::new(0.0, 0.1, 0.0);
    let render = settings(256, 1);
    let grid = RingGrid::new(9);
    let envmap_towards = |dirs: &[Vec3]| {
        let mut radiance = vec![Vec3::ZERO; grid.cell_count()];
        for d in dirs {
            radiance[grid.lookup(*d) as usize] = Vec3::splat(10.0);
        }
        Envmap::new(9, radiance).unwrap()
    };

    // A second light straight down, below the table, changes no pixel: it is reported and
    // left out of the model, never a NaN. A second light beside the true one, in nearly the
    // same direction, is merged into it (or left without radiance).
    let sc = scene(vec![NEAR_LIGHT]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let obs = binned(&cams, &masks, &refs);
    // Started there by hand (the joint search would not put a light below the table).
    let st = SphereSettings::new(2, &render);
    let below = SphereLight {
        center: center - Vec3::Y * 3.0,
        radius: 0.15,
        radiance: Vec3::ONE,
    };
    let beside = SphereLight {
        center: NEAR_LIGHT.center + Vec3::new(0.03, 0.0, -0.03),
        ..NEAR_LIGHT
    };
    for (extra, want) in [(below, "no_contribution"), (beside, "merged")] {
        let refined = refine(&r, &obs, &[NEAR_LIGHT, extra], center, &st.refine);
        let (fitted, _) = judge(&r, &obs, &refined, center, &st.refine.residual);
        eprintln!("{want}: {fitted:#?}");
        assert_eq!(fitted.len(), 2, "{fitted:#?}");
        let kept: Vec<_> = fitted
            .iter()
            .filter(|f| {
                matches!(
                    f.status,
                    LightStatus::Identified | LightStatus::DistanceUnidentified
                )
            })
            .collect();
        assert_eq!(kept.len(), 1, "{want}: {fitted:#?}");
        assert!(
            kept[0].light.center.distance(NEAR_LIGHT.center) < 0.05,
            "{want}: {fitted:#?}"
        );
        if want == "no_contribution" {
            let below = fitted.iter().find(|f| f.light.center.y < 0.0);
            assert_eq!(
                below.map(|f| f.status),
                Some(LightStatus::NoContribution),
                "{fitted:#?}"
            );
        }
        assert!(refined.rel_mae.is_finite());
        assert!(fitted.iter().all(|f| f.light.radiance.is_finite()));
    }

    // Far lights. At 60 m the table still sees 1.9° of parallax and a 1.9° penumbra: the
    // distance is measured (not assumed infinite). At 30 km only direction and power show:
    // reported as such, with its uncertainty, and no NaN however far the search wanders.
    // (This scene's references are quiet, relMAE 0.08% per binned pixel: the parallax of
    // irradiance across the table still shows at a few km. A fit at 2.2 km of a light at 3 km
    // measured a 25% move at 2.8σ, and a far light that shows at 2σ or more is "identified";
    // the signal falls as 1/distance², so the test's far light, 3 km until then, is at 30 km.)
    // Measured: 60 m found at 59.2 m, 0.05° off, a 25% change costs 57.9σ; 30 km: found at
    // 5.7 km (still moving outward), 0.06° off, 0.0σ.
    for (distance, identified) in [(60.0f32, true), (30000.0, false)] {
        let far = SphereLight {
            center: center + Vec3::new(0.5, 1.0, 0.3).normalize() * distance,
            radius: distance * 0.033,
            radiance: Vec3::splat(20.0),
        };
        let sc = scene(vec![far]);
        let lights = Lights::new(sc.lights.clone());
        let r = Renderer::new(&sc, &lights);
        let (refs, masks) = render_all(&r, &sc, 256, 1);
        let obs = Observations {
            references: &refs,
            masks: &masks,
            evaluated: &masks,
            ..obs
        };
        let env = envmap_towards(&[(far.center - center).normalize()]);
        let fit = fit_sphere_models(
            &r,
            &obs,
            &env,
            center,
            2.0,
            &SphereSettings::new(1, &render),
            &mut |_| true,
        )
        .pop()
        .unwrap();
        let f = &fit.fitted[0];
        let (got, truth) = (f.light.center - center, far.center - center);
        eprintln!(
            "light at {distance} m: {:?} ({:?} σ), found at {:.1} m, {:.2}° off, fit relMAE {:.3}%",
            f.status,
            f.distance_profile_sigmas,
            got.length(),
            got.angle_between(truth).to_degrees(),
            100.0 * fit.fit_rel_mae
        );
        assert!(got.angle_between(truth).to_degrees() < 1.0, "{fit:#?}");
        assert!(f.light.radiance.is_finite() && got.is_finite(), "{fit:#?}");
        if identified {
            assert_eq!(f.status, LightStatus::Identified, "{fit:#?}");
            assert!((got.length() / distance - 1.0).abs() < 0.05, "{fit:#?}");
        } else {
            assert!(
                matches!(f.status, LightStatus::DistanceUnidentified),
                "{fit:#?}"
            );
        }
    }
}

/// Records each phase's declared units and the units reported done.
#[derive(Default)]
struct Recorder(std::sync::Mutex<Vec<(String, u64, u64)>>);

impl lightprobe::estimate::job::Progress for Recorder {
    fn phase(&self, name: &str, units: u64) {
        self.0.lock().unwrap().push((name.to_string(), units, 0));
    }
    fn advance(&self, units: u64) {
        self.0.lock().unwrap().last_mut().unwrap().2 += units;
    }
}

fn bundled_scene() -> Scene {
    Scene::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/tabletop/tabletop.ron"
    )))
    .unwrap()
}

/// Runs an estimate with `settings` on the bundled scene, its references rendered at 4 spp.
fn on_bundled_scene(
    settings: &lightprobe::estimate::job::EstimateSettings,
    progress: &dyn lightprobe::estimate::job::Progress,
) {
    use lightprobe::estimate::job::{self, Job, References};
    let scene = bundled_scene();
    let lights = Lights::new(scene.lights.clone());
    let renderer = Renderer::new(&scene, &lights);
    let render = RenderSettings {
        spp: 4,
        ..RenderSettings::from_scene(&scene.settings)
    };
    let seen = job::observe(&renderer, &render, References::Render, &()).unwrap();
    job::run(&Job::new(&renderer, &seen, &render, settings), progress).unwrap();
}

#[test]
fn progress_declares_exactly_the_work_it_reports() {
    // Every unit a phase reports done was declared when it started, and all of them are
    // reported by its end: a bar neither stops short (it stopped at 28% with the oracle)
    // nor sits at 100% while work remains. The envmap's phases with a held-out choice of
    // rings, the oracle, masks that leave tiles out, NNLS (pilot and parts) and gradient.
    use lightprobe::estimate::job::{EstimateSettings, Rings};
    for solver in [Solver::Nnls, Solver::Gradient] {
        let settings = EstimateSettings {
            rings: Rings::Auto(vec![3, 5]),
            spp: 8,
            solver,
            rounds: solver.default_rounds(),
            oracle: true,
            ..EstimateSettings::new(&bundled_scene().settings)
        };
        let rec = Recorder::default();
        on_bundled_scene(&settings, &rec);
        let phases = rec.0.into_inner().unwrap();
        assert_eq!(phases.len(), 2, "{phases:?}");
        for (name, declared, done) in phases {
            assert_eq!(done, declared, "{solver:?}, phase {name}");
        }
    }
}

#[test]
fn sphere_fits_report_their_progress_as_they_go() {
    // A sphere model's phase counts its fit's renders, not only its re-render: with no
    // re-render at all (--fit-only) the bar moves in small steps while the fit runs (no
    // step, the last included, over a quarter of the phase), and reports exactly what it
    // declared. So does the phase of its intervals' renders after it.
    use lightprobe::estimate::job::{EstimateSettings, LightModel};
    for k in [1, 2] {
        let settings = EstimateSettings {
            model: LightModel::Spheres(Some(k)),
            evaluate: false,
            spp: 8,
            ..EstimateSettings::new(&bundled_scene().settings)
        };
        let rec = Recorder::default();
        let largest = Largest(&rec, Default::default());
        on_bundled_scene(&settings, &largest);
        let steps = largest.1.into_inner().unwrap();
        let phases = rec.0.into_inner().unwrap();
        for name in ["sphere lights", "sphere intervals"] {
            let (_, declared, done) = phases
                .iter()
                .find(|p| p.0 == name)
                .unwrap_or_else(|| panic!("spheres:{k}, {name}: {phases:?}"));
            assert_eq!(done, declared, "spheres:{k}, {name}");
            let largest = steps[name];
            assert!(
                largest * 4 <= *declared,
                "spheres:{k}, {name}: a step of {largest} of {declared}"
            );
        }
    }
}

/// Keeps the largest advance of each phase (and passes all on to a `Recorder`).
struct Largest<'a>(
    &'a Recorder,
    std::sync::Mutex<std::collections::HashMap<String, u64>>,
);

impl lightprobe::estimate::job::Progress for Largest<'_> {
    fn phase(&self, name: &str, units: u64) {
        self.0.phase(name, units);
    }
    fn advance(&self, units: u64) {
        let name = self.0.0.lock().unwrap().last().unwrap().0.clone();
        let mut steps = self.1.lock().unwrap();
        let largest = steps.entry(name).or_default();
        *largest = (*largest).max(units);
        drop(steps);
        self.0.advance(units);
    }
}

/// `sc` with two of its three materials' albedo off by up to 20% per channel.
fn albedo_off(sc: &Scene) -> Scene {
    let off = [
        Vec3::ONE,
        Vec3::new(0.85, 1.15, 0.9),
        Vec3::new(1.2, 0.8, 1.1),
    ];
    let mut wrong = sc.clone();
    for (m, k) in wrong.materials.iter_mut().zip(off) {
        *m = m.scaled(k);
    }
    wrong
}

/// Each image times its exposure, as photographs at those exposures.
fn at_exposures(images: &mut [Image], exposures: &[f32]) {
    for (img, s) in images.iter_mut().zip(exposures) {
        img.rgb.iter_mut().for_each(|p| *p *= s);
    }
}

#[test]
fn per_material_albedo_is_recovered_beside_the_lighting() {
    // The fit's scene has two of three materials' albedo off by up to 20% per channel; the
    // references are rendered with the true albedo under a 3-ring sky (a model the fit can
    // match exactly). Trusting the table, the fitted albedo must come back to the truth and
    // the lighting to the exact-albedo fit's error; without a trusted material, the ratios
    // between materials must.
    use lightprobe::estimate::albedo::{FitAlbedo, MaterialStatus};
    use lightprobe::estimate::job::{self, EstimateSettings, Job, References, Rings};
    let sc = scene(vec![]);
    let lights = Lights::env(three_ring_sky());
    let truth = Renderer::new(&sc, &lights);
    let render = settings(256, 1);
    let (refs, _) = render_all(&truth, &sc, 256, 1);
    let seen = job::observe(&truth, &render, References::Images(refs), &()).unwrap();
    let wrong = albedo_off(&sc);
    let fit = truth.with_scene(&wrong, &lights);
    let run = |fit_albedo, trust: &[&str], fit: &Renderer| {
        let settings = EstimateSettings {
            rings: Rings::Fixed(3),
            spp: 256,
            noise_floor: false,
            fit_albedo,
            trust_albedo: trust.iter().map(|s| s.to_string()).collect(),
            ..EstimateSettings::new(&sc.settings)
        };
        let job = Job {
            fit,
            ..Job::new(&truth, &seen, &render, &settings)
        };
        job::run(&job, &()).unwrap()
    };
    let exact = run(None, &[], &truth).report.rel_mae.unwrap();
    let wrong_albedo = run(None, &[], &fit).report.rel_mae.unwrap();
    let trusted = run(Some(FitAlbedo::Materials), &["table"], &fit);
    let report = trusted.report.albedo.as_ref().unwrap();
    let statuses: Vec<MaterialStatus> = report.materials.iter().map(|m| m.status).collect();
    assert_eq!(
        statuses,
        [
            MaterialStatus::Trusted,
            MaterialStatus::Fitted,
            MaterialStatus::Fitted
        ]
    );
    assert!(report.converged, "{report:?}");
    for (m, truth_m) in report.materials.iter().zip(&sc.materials) {
        let want = truth_m.mean_albedo();
        for c in 0..3 {
            let err = m.fitted[c] / want[c] - 1.0;
            assert!(
                err.abs() < 0.02,
                "{}: fitted {:?}, true {want}",
                m.name,
                m.fitted
            );
        }
        assert!(m.observability.is_none_or(|o| o > 0.1), "{m:?}");
    }
    // Judged in the true scene, the lighting is as good as with the albedo known.
    let fitted = trusted.report.rel_mae.unwrap();
    assert!(
        fitted < 1.1 * exact && wrong_albedo > 1.25 * exact,
        "relMAE exact albedo {exact}, fitted {fitted}, wrong {wrong_albedo}"
    );
    // The materials the fit returns are those of the report.
    let materials = trusted.materials.as_ref().unwrap();
    assert!((materials[1].mean_albedo() - sc.materials[1].mean_albedo()).length() < 0.03);
    // Nothing trusted: the scale is the fitted materials' mean, their ratios the truth's.
    let free = run(Some(FitAlbedo::Materials), &[], &fit);
    let report = free.report.albedo.as_ref().unwrap();
    assert!(report.converged, "{report:?}");
    let f = |m: usize| Vec3::from_array(report.materials[m].fitted);
    let ratio = (f(1) / f(2)) / (sc.materials[1].mean_albedo() / sc.materials[2].mean_albedo());
    assert!((ratio - Vec3::ONE).abs().max_element() < 0.02, "{ratio}");
    assert!(
        report
            .materials
            .iter()
            .all(|m| m.status == MaterialStatus::Fitted)
    );
    // The gauge: the pixel-weighted geometric mean of the multipliers stays 1 per channel.
    let (mut log_sum, mut weight) = (glam::DVec3::ZERO, 0.0);
    for m in &report.materials {
        let k = Vec3::from_array(m.multiplier).as_dvec3();
        log_sum += glam::DVec3::new(k.x.ln(), k.y.ln(), k.z.ln()) * m.pixels as f64;
        weight += m.pixels as f64;
    }
    assert!((log_sum / weight).abs().max_element() < 1e-3, "{report:?}");
}

#[test]
fn per_view_exposures_are_recovered_and_the_lighting_is_in_their_geometric_mean() {
    // Photographs of one lighting at exposures 2 and 0.6: the fitted exposures must come back
    // in that ratio, and the lighting must be the truth times their geometric mean (the unit
    // the fit reports it in), while a shared-exposure fit of the same references misfits.
    use lightprobe::estimate::job::{self, EstimateSettings, Exposure, Job, References, Rings};
    let truth = three_ring_sky();
    let sc = scene(vec![]);
    let lights = Lights::env(truth.clone());
    let r = Renderer::new(&sc, &lights);
    let render = settings(256, 1);
    let (mut refs, _) = render_all(&r, &sc, 256, 1);
    let applied = [2.0f32, 0.6];
    at_exposures(&mut refs, &applied);
    let seen = job::observe(&r, &render, References::Images(refs), &()).unwrap();
    let run = |exposure| {
        let settings = EstimateSettings {
            rings: Rings::Fixed(3),
            spp: 256,
            noise_floor: false,
            exposure,
            ..EstimateSettings::new(&sc.settings)
        };
        job::run(&Job::new(&r, &seen, &render, &settings), &()).unwrap()
    };
    let per_view = run(Exposure::PerView);
    let report = per_view.report.exposure.as_ref().unwrap();
    let e: Vec<f64> = report.relative.iter().map(|v| v.exposure).collect();
    let want = (applied[0] / applied[1]) as f64;
    assert!(
        ((e[0] / e[1]) / want - 1.0).abs() < 0.01,
        "exposures {e:?}, want ratio {want}"
    );
    assert!(((e[0] * e[1]).sqrt() - 1.0).abs() < 1e-9, "{e:?}");
    // Converged: the fit with every sample asks for less than the tolerance's change.
    assert!(
        report.fits < job::MAX_ALTERNATION_FITS && report.last_change < job::EXPOSURE_TOLERANCE,
        "{report:?}"
    );
    let mean = (applied[0] * applied[1]).sqrt();
    let power = |env: &Envmap| lightprobe::imageio::luminance(env.radiance()[0..5].iter().sum());
    let ratio = power(&per_view.envmap.fit.envmap) / (mean * power(&truth));
    assert!(
        (ratio - 1.0).abs() < 0.02,
        "lighting / (truth × mean exposure) = {ratio}"
    );
    // Judged against the references over their exposures, the fit is as good as a fit of
    // references at one exposure; the shared fit cannot explain both views.
    let shared = run(Exposure::Shared);
    let (pv, sh) = (
        per_view.report.rel_mae.unwrap(),
        shared.report.rel_mae.unwrap(),
    );
    assert!(
        pv < 0.02 && sh > 5.0 * pv,
        "relMAE per-view {pv}, shared {sh}"
    );
}

#[test]
fn albedo_and_per_view_exposures_are_fitted_together_with_the_envmap() {
    // Photographs at exposures 2 and 0.6 of a scene whose fit has two of three materials'
    // albedo off by up to 20%, under a 3-ring sky: with the envmap, each exposure fit is a
    // joint fit of the albedo and the lighting. The exposures' ratio, the albedo (the table
    // trusted) and the lighting in the exposures' geometric mean must all come back.
    use lightprobe::estimate::albedo::{AlbedoMethod, FitAlbedo};
    use lightprobe::estimate::job::{self, EstimateSettings, Exposure, Job, References, Rings};
    let sky = three_ring_sky();
    let sc = scene(vec![]);
    let lights = Lights::env(sky.clone());
    let truth = Renderer::new(&sc, &lights);
    let render = settings(256, 1);
    let (mut refs, _) = render_all(&truth, &sc, 256, 1);
    let applied = [2.0f32, 0.6];
    at_exposures(&mut refs, &applied);
    let seen = job::observe(&truth, &render, References::Images(refs), &()).unwrap();
    let wrong = albedo_off(&sc);
    let fit = truth.with_scene(&wrong, &lights);
    let settings = EstimateSettings {
        rings: Rings::Fixed(3),
        spp: 256,
        noise_floor: false,
        exposure: Exposure::PerView,
        fit_albedo: Some(FitAlbedo::Materials),
        trust_albedo: vec!["table".to_string()],
        ..EstimateSettings::new(&sc.settings)
    };
    let job = Job {
        fit: &fit,
        ..Job::new(&truth, &seen, &render, &settings)
    };
    let estimate = job::run(&job, &()).unwrap();
    let exposure = estimate.report.exposure.as_ref().unwrap();
    let e: Vec<f64> = exposure.relative.iter().map(|v| v.exposure).collect();
    let want = (applied[0] / applied[1]) as f64;
    assert!(
        ((e[0] / e[1]) / want - 1.0).abs() < 0.01 && exposure.converged,
        "exposures {exposure:?}, want ratio {want}"
    );
    let albedo = estimate.report.albedo.as_ref().unwrap();
    assert_eq!(albedo.method, AlbedoMethod::Joint);
    assert!(albedo.converged, "{albedo:?}");
    for (m, truth_m) in albedo.materials.iter().zip(&sc.materials) {
        let want = truth_m.mean_albedo();
        for c in 0..3 {
            assert!(
                (m.fitted[c] / want[c] - 1.0).abs() < 0.02,
                "{}: fitted {:?}, true {want}",
                m.name,
                m.fitted
            );
        }
    }
    let mean = (applied[0] * applied[1]).sqrt();
    let power = |env: &Envmap| lightprobe::imageio::luminance(env.radiance()[0..5].iter().sum());
    let ratio = power(&estimate.envmap.fit.envmap) / (mean * power(&sky));
    assert!(
        (ratio - 1.0).abs() < 0.02,
        "lighting / (truth × mean exposure) = {ratio}"
    );
}

#[test]
fn a_model_short_of_the_references_bounces_fails_the_fit_test_and_the_right_one_passes() {
    // References of a sky-lit scene with 4 bounces. Fitted with 4 bounces the 3-ring envmap
    // explains them within noise; fitted with 1 bounce it cannot (interreflections between
    // the ball, the box and the table are missing), and the test must say so and name the
    // bounce count. Given references are judged by neighbouring pixels; rendered ones by
    // their rendered twin, and the two noise floors must agree.
    use lightprobe::estimate::job::{self, EstimateSettings, Job, NoiseSource, References, Rings};
    let sc = scene(vec![]);
    let lights = Lights::env(three_ring_sky());
    let r = Renderer::new(&sc, &lights);
    let at = |bounces| RenderSettings {
        max_bounces: bounces,
        ..settings(256, 1)
    };
    let refs: Vec<Image> = sc
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| r.render_radiance(c, i as u64, &at(4), &|_| {}))
        .collect();
    let given = job::observe(&r, &at(4), References::Images(refs.clone()), &()).unwrap();
    let rendered = job::observe(&r, &at(4), References::Render, &()).unwrap();
    let run = |seen: &lightprobe::estimate::pipeline::SeenViews, bounces| {
        let settings = EstimateSettings {
            rings: Rings::Fixed(3),
            spp: 256,
            ..EstimateSettings::new(&sc.settings)
        };
        job::run(&Job::new(&r, seen, &at(bounces), &settings), &())
            .unwrap()
            .report
    };
    let right = run(&given, 4);
    let short = run(&given, 1);
    let twin = run(&rendered, 4);
    let test = |rep: &job::EstimateReport| rep.fit_test.clone().unwrap();
    assert_eq!(
        right.noise_floor_source,
        Some(NoiseSource::NeighbouringPixels)
    );
    assert_eq!(twin.noise_floor_source, Some(NoiseSource::RenderedTwin));
    assert!(!test(&right).misfit, "{:?}", test(&right));
    assert!(!test(&twin).misfit, "{:?}", test(&twin));
    let bad = test(&short);
    assert!(bad.misfit && bad.test.residual_over_noise > 2.0, "{bad:?}");
    // A quick re-fit with 2 bounces removes most of the misfit: the bounce count comes first.
    assert!(
        bad.causes[0].starts_with("the bounce count") && bad.causes[0].contains("re-fit with 2"),
        "{bad:?}"
    );
    // The same noise measured two ways: within 15%.
    let (n, t) = (
        right.noise_floor_rel_mae.unwrap(),
        twin.noise_floor_rel_mae.unwrap(),
    );
    assert!((n / t - 1.0).abs() < 0.15, "neighbours {n}, twin {t}");
    // Scene lights against given references are their own figure, not the noise floor.
    assert!(right.true_lights_rel_mae.is_some() && twin.true_lights_rel_mae.is_none());
}

#[test]
fn a_radius_the_images_cannot_see_is_not_identified_and_the_intervals_hold_the_truth() {
    // Two lights refined from their true places: a small one 2.5 m away (1.5 cm, 0.3°
    // across: its penumbrae are far below a pixel) and the near one (15 cm at 1.8 m, whose
    // penumbrae span pixels). The small one's radius must be reported as not identified —
    // never a number with a 1% interval, as the LM loop's own covariance gave — while its
    // power, and both lights' direction and distance, come with 95% intervals that hold the
    // truth (here at 3 σ: one deterministic trial; docs/results.md has the multi-seed study).
    use estimate::spheres::{self, FittedLight};
    let center = Vec3::new(0.0, 0.1, 0.0);
    let small = SphereLight {
        center: center + Vec3::new(-0.6, 0.9, 0.4).normalize() * 2.5,
        radius: 0.015,
        radiance: Vec3::splat(12000.0),
    };
    let sc = scene(vec![NEAR_LIGHT, small]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let obs = binned(&cams, &masks, &refs);
    let residual = settings(64, 5);
    let refined = spheres::refine(
        &r,
        &obs,
        &sc.lights,
        center,
        &spheres::RefineSettings {
            residual,
            jacobian: settings(16, 6),
            max_iterations: 8,
            fixed: 0,
            polish_radii: false,
            radiance_spp: 0,
        },
    );
    let (mut fitted, _) = spheres::judge(&r, &obs, &refined, center, &residual);
    spheres::measure_intervals(&r, &obs, &mut fitted, center, &residual);
    let power = |l: &SphereLight| lightprobe::imageio::luminance(l.radiance) * l.radius * l.radius;
    let within = |f: &FittedLight, truth: &SphereLight| {
        let (d, dt) = (f.light.center - center, truth.center - center);
        let angle = d.angle_between(dt) as f64;
        let sigma = f.direction_sigma_degrees.unwrap().to_radians();
        let distance = (d.length() - dt.length()) as f64;
        let power = (power(&f.light) / power(truth)).ln() as f64;
        eprintln!(
            "angle {angle:.5} rad (σ {sigma:.5}), distance {distance:.4} m (σ {:.4}), ln power {power:.4} (σ {:?}), radius {} ({:?})",
            f.distance_sigma_m.unwrap(),
            f.power_sigma_relative,
            f.light.radius,
            f.radius_sigma_relative
        );
        // 2 degrees of freedom for the direction: 3.44 σ holds 99.7%.
        assert!(angle < 3.44 * sigma, "{f:?}");
        assert!(distance.abs() < 3.0 * f.distance_sigma_m.unwrap(), "{f:?}");
        assert!(power.abs() < 3.0 * f.power_sigma_relative.unwrap(), "{f:?}");
    };
    let (near, far) = (&fitted[0], &fitted[1]);
    within(near, &NEAR_LIGHT);
    within(far, &small);
    assert_eq!(far.radius_identified, Some(false), "{far:?}");
    assert_eq!(far.power_identified, Some(true), "{far:?}");
    assert_eq!(near.power_identified, Some(true), "{near:?}");
    // The lights file says so beside the light.
    let fit = spheres::SphereFit {
        requested: 2,
        fitted: fitted.clone(),
        start: Vec::new(),
        fit_rel_mae: 0.0,
        iterations: 0,
        renders: 0,
        history: Vec::new(),
        seconds: 0.0,
        background: None,
    };
    assert!(fit.fragment().contains("Radius not identified"));
    // Colour (radiance over its luminance) within 3 σ per channel.
    let colour = |l: &SphereLight| l.radiance / lightprobe::imageio::luminance(l.radiance);
    for (f, truth) in [(near, &NEAR_LIGHT), (far, &small)] {
        let (c, t, sigma) = (colour(&f.light), colour(truth), f.colour_sigma.unwrap());
        for ch in 0..3 {
            assert!((c[ch] - t[ch]).abs() as f64 <= 3.0 * sigma[ch], "{f:?}");
        }
    }
    // And so do the exports: the glTF's extras, USD's attributes and the Mitsuba scene.
    use lightprobe::scene::export;
    // (The near light's radius, from 256-spp references, is not identified either: ×/÷ 2.4.)
    let doubts = fit.radius_doubts();
    let unidentified = fitted.iter().filter(|f| f.radius_identified == Some(false));
    assert_eq!(doubts.iter().flatten().count(), unidentified.count());
    assert!(doubts[1].is_some_and(|f| f > 1.5), "{doubts:?}");
    let (doubted, measured) = (
        doubts.iter().flatten().count(),
        doubts
            .iter()
            .flatten()
            .filter(|&&f| f <= export::WIDEST_STATED_DOUBT)
            .count(),
    );
    let usda = export::usda(&fit.lights(), &doubts, None);
    let n = usda.matches("lightprobe:radiusIdentified = 0").count();
    assert_eq!(n, doubted, "{usda}");
    assert_eq!(usda.matches("lightprobe:radius95").count(), measured);
    assert!(
        usda.contains("# radius not identified by the images"),
        "{usda}"
    );
    let dir = tempfile::tempdir().unwrap();
    let glb = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/tabletop/tabletop.glb");
    let written = export::write_with_lights(
        Path::new(glb),
        dir.path(),
        &fit.lights(),
        &doubts,
        None,
        None,
    )
    .unwrap()
    .0;
    let bytes = std::fs::read(&written).unwrap();
    let text = String::from_utf8_lossy(&bytes);
    assert_eq!(text.matches("\"radius_identified\":false").count(), doubted);
    assert_eq!(text.matches("\"radius_95_interval\"").count(), measured);
    // Still a scene lightprobe loads, with the fitted radius.
    let back = Scene::load(&written).unwrap();
    assert!(
        back.lights
            .iter()
            .any(|l| (l.radius - far.light.radius).abs() < 1e-6)
    );
    let xml_dir = dir.path().join("mitsuba");
    let render = export::mitsuba::Render {
        spp: 16,
        max_bounces: 2,
    };
    export::mitsuba::write(&xml_dir, &sc, &fit.lights(), &doubts, None, render).unwrap();
    let xml = std::fs::read_to_string(xml_dir.join("scene.xml")).unwrap();
    assert_eq!(xml.matches("<!-- radius not identified").count(), doubted);
}

#[test]
fn the_jackknife_intervals_of_envmap_clusters_match_their_spread_over_seeds() {
    // A known 5-ring envmap fitted from 8 independent seeds (new references and transport
    // each time): the brightest cluster's power and direction scatter over the seeds as
    // much as each fit's own jackknife says, within a factor of 2 either way (an estimate of
    // a spread from 8 samples is itself ±27%). Measured: power 0.26% against a stated 0.42%,
    // direction 0.25° against 0.30° (the jackknife errs wide, as it is known to).
    let rings = 5;
    let truth = known_envmap(rings);
    let sc = scene(vec![]);
    let lights = Lights::env(truth);
    let r = Renderer::new(&sc, &lights);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let mut fits = Vec::new();
    for seed in 0..8u64 {
        let (refs, masks) = render_all(&r, &sc, 64, 100 + seed);
        let settings = FitSettings {
            rounds: 4,
            jackknife: 16,
            transport: settings(64, 200 + seed),
            ..fit_settings(rings, 256, Solver::Nnls, 1e-3)
        };
        let fit = estimate::fit(&r, &cams, &refs, &masks, &settings, &|_| {});
        assert_eq!(fit.replicates.len(), 16);
        let c = recovery::cluster_estimates(&fit.envmap, &fit.replicates);
        fits.push(c[0].clone());
    }
    let n = fits.len() as f64;
    let mean_power = fits.iter().map(|c| c.power as f64).sum::<f64>() / n;
    let spread_power = (fits
        .iter()
        .map(|c| (c.power as f64 / mean_power - 1.0).powi(2))
        .sum::<f64>()
        / (n - 1.0))
        .sqrt();
    let stated_power = (fits
        .iter()
        .map(|c| c.power_sigma_relative.unwrap().powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    let mean_dir = fits
        .iter()
        .map(|c| Vec3::from(c.direction))
        .sum::<Vec3>()
        .normalize();
    // Two axes: the mean squared angle is twice the per-axis variance.
    let spread_dir = (fits
        .iter()
        .map(|c| {
            (Vec3::from(c.direction).angle_between(mean_dir) as f64)
                .to_degrees()
                .powi(2)
        })
        .sum::<f64>()
        / (2.0 * (n - 1.0)))
        .sqrt();
    let stated_dir = (fits
        .iter()
        .map(|c| c.direction_sigma_degrees.unwrap().powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    eprintln!(
        "power: spread {spread_power:.4}, stated {stated_power:.4}; direction: spread {spread_dir:.3}°, stated {stated_dir:.3}°"
    );
    for (spread, stated) in [(spread_power, stated_power), (spread_dir, stated_dir)] {
        assert!(
            (0.5..2.0).contains(&(spread / stated)),
            "spread {spread}, stated {stated}"
        );
    }
}

#[test]
fn choosing_the_rings_keeps_the_chosen_fits_jackknife() {
    // `--rings auto`: the candidates' pass keeps its sums per jackknife group, so the chosen
    // resolution comes with replicates, whether refitted on every pixel or kept as the
    // hold-out fit (`--model auto`). Grouping only reorders the sums: the envmap is the one
    // chosen without groups. The intervals describe the chosen fit's own scatter: within a
    // factor of 2 of a fixed fit of the same resolution on the same references.
    use lightprobe::estimate::select;
    let rings = 5;
    let sc = scene(vec![]);
    let lights = Lights::env(known_envmap(rings));
    let r = Renderer::new(&sc, &lights);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let (refs, masks) = render_all(&r, &sc, 64, 7);
    let template = |jackknife, holdout| FitSettings {
        rounds: 4,
        jackknife,
        holdout,
        transport: settings(64, 8),
        ..fit_settings(rings, 256, Solver::Nnls, 1e-3)
    };
    let choose = |settings: &FitSettings| {
        select::select_rings(&r, &cams, &refs, &masks, &[3, 5], settings, &|_| {}).unwrap()
    };
    let fixed = estimate::fit(&r, &cams, &refs, &masks, &template(16, false), &|_| {});
    let fixed = recovery::cluster_estimates(&fixed.envmap, &fixed.replicates);
    for holdout in [false, true] {
        let grouped = choose(&template(16, holdout));
        let plain = choose(&template(0, holdout));
        assert_eq!(grouped.selection.rings, rings, "holdout {holdout}");
        assert_eq!(plain.selection.rings, rings, "holdout {holdout}");
        let (grouped, plain) = (grouped.fit.unwrap(), plain.fit.unwrap());
        assert!(plain.replicates.is_empty());
        assert_eq!(grouped.replicates.len(), 16, "holdout {holdout}");
        for (a, b) in grouped
            .envmap
            .radiance()
            .iter()
            .zip(plain.envmap.radiance())
        {
            assert!(
                (*a - *b).abs().max_element() <= 1e-4 * b.max_element().max(1e-3),
                "{a} against {b}"
            );
        }
        let clusters = recovery::cluster_estimates(&grouped.envmap, &grouped.replicates);
        let (c, f) = (&clusters[0], &fixed[0]);
        for (stated, fixed) in [
            (c.power_sigma_relative, f.power_sigma_relative),
            (c.direction_sigma_degrees, f.direction_sigma_degrees),
        ] {
            let ratio = stated.unwrap() / fixed.unwrap();
            // Three quarters of the pixels: sqrt(4/3) wider, ideally.
            let expected = if holdout { 1.15 } else { 1.0 };
            assert!(
                (0.5..2.0).contains(&(ratio / expected)),
                "holdout {holdout}: {stated:?} against a fixed fit's {fixed:?}"
            );
        }
    }
    // A grid too large to keep its sums per group (19 rings, over 330 cells) beside one that
    // does: it takes every group's pixels in the same order as with no groups, so its fit is
    // the same to the bit.
    let candidates = |jackknife| {
        estimate::fit_candidates(
            &r,
            &cams,
            &refs,
            &masks,
            &template(jackknife, true),
            &[5, 19],
            &|_| {},
        )
    };
    let (grouped, plain) = (candidates(16), candidates(0));
    assert!(RingGrid::new(19).cell_count() > estimate::MAX_JACKKNIFE_CELLS);
    assert_eq!(
        grouped.fits[1].envmap.radiance(),
        plain.fits[1].envmap.radiance()
    );
}

#[test]
fn choosing_stops_at_a_model_at_the_noise_floor_and_goes_on_where_none_is() {
    // A near lamp alone: one sphere re-renders at the noise floor, so no larger model could
    // be chosen over it and none is fitted (no second light, no envmap behind it). A lamp
    // under a sky: neither one sphere nor the envmap reaches the floor, so the sequence goes
    // on to the lamp with an envmap behind it. Both through the estimate job, whose progress
    // must still end each phase at what it declared.
    use lightprobe::estimate::job::{self, EstimateSettings, Job, LightModel, References, Rings};
    let g = RingGrid::new(5);
    let sky = (0..g.cell_count() as u32)
        .map(|c| Vec3::new(0.25, 0.3, 0.45) * (0.3 + 0.7 * g.center(c).y.max(0.0)))
        .collect();
    let sc = scene(vec![NEAR_LIGHT]);
    let lamp = Lights::new(sc.lights.clone());
    let lamp_and_sky = Lights {
        env: Some(Envmap::new(5, sky).unwrap()),
        ..lamp.clone()
    };
    let render = settings(256, 1);
    for (lights, stop) in [(&lamp, Some("spheres:1")), (&lamp_and_sky, None)] {
        let r = Renderer::new(&sc, lights);
        let seen = job::observe(&r, &render, References::Render, &()).unwrap();
        let settings = EstimateSettings {
            rings: Rings::Fixed(5),
            model: LightModel::Auto,
            spp: 256,
            ..EstimateSettings::new(&sc.settings)
        };
        let rec = Recorder::default();
        let est = job::run(&Job::new(&r, &seen, &render, &settings), &rec).unwrap();
        let sel = est.report.model_selection.unwrap();
        eprintln!("{sel:#?}");
        let names: Vec<&str> = sel.candidates.iter().map(|c| c.model.as_str()).collect();
        assert_eq!(sel.at_noise_floor.as_deref(), stop, "{sel:#?}");
        match stop {
            Some(_) => {
                assert_eq!(names, ["spheres:1", "envmap"], "{sel:#?}");
                assert_eq!(sel.chosen, "spheres:1");
            }
            None => assert!(names.contains(&"envmap+spheres:1"), "{sel:#?}"),
        }
        for (name, declared, done) in rec.0.into_inner().unwrap() {
            assert_eq!(done, declared, "phase {name}");
        }
    }
}

#[test]
fn pixels_left_out_of_a_walk_or_render_change_no_other_pixel() {
    // The sphere fit walks and lights only the pixels it compares (the mask less the held-out
    // quarter): every other pixel must come out exactly as a full render makes it, and the
    // left-out ones empty with coverage 0.
    let sc = scene(vec![NEAR_LIGHT]);
    let lights = Lights::new(vec![NEAR_LIGHT]);
    let r = Renderer::new(&sc, &lights);
    let cam = &sc.cameras[1];
    let st = settings(16, 7);
    let keep = |i: u32| !i.is_multiple_of(3) && i % 7 != 2;
    let wanted: Vec<bool> = (0..cam.width * cam.height).map(keep).collect();
    let acc = lightprobe::render::RadianceAccumulator(&lights);
    let full = r.render(cam, 3, &st, &acc, &|_| {});
    let walked = r.trace_paths(cam, 3, &st, Some(wanted.clone()));
    let lit = r.render_paths(&walked, cam, &st, &acc);
    let some = r.render_some(cam, 3, &st, &acc, Some(&keep), &|_| {});
    let all_paths = r.trace_paths(cam, 3, &st, None);
    assert!(
        walked.bytes() < all_paths.bytes() * 3 / 4,
        "the left-out pixels were walked"
    );
    let lit_all = r.render_paths(&all_paths, cam, &st, &acc);
    for (part, full) in [(&lit, &lit_all), (&some, &full)] {
        for (i, w) in wanted.iter().enumerate() {
            if *w {
                assert_eq!(part.pixels[i], full.pixels[i], "pixel {i}");
                assert_eq!(part.coverage[i], full.coverage[i], "pixel {i}");
            } else {
                assert_eq!(part.pixels[i], Vec3::ZERO, "pixel {i}");
                assert_eq!(part.coverage[i], 0.0, "pixel {i}");
            }
        }
    }
}

#[test]
fn a_white_light_comes_back_white_when_the_channels_are_fitted_together() {
    // A white near lamp, which no envmap represents exactly: fitted channel by channel the
    // misfit is shared out between primaries (cells of one or two channels side by side);
    // fitted together every lit cell keeps the lamp's colour, and the map explains the images
    // as well.
    use estimate::Colour;
    use lightprobe::estimate::recovery::colour_figures;
    let white = SphereLight {
        radiance: Vec3::splat(50.0),
        ..NEAR_LIGHT
    };
    let sc = scene(vec![white]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let (refs, masks) = render_all(&r, &sc, 256, 1);
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let center = Vec3::new(0.0, 0.2, 0.0);
    let fit_with = |colour| {
        let settings = FitSettings {
            colour,
            rounds: 4,
            ..fit_settings(9, 256, Solver::Nnls, 1e-3)
        };
        let fit = estimate::fit(&r, &cams, &refs, &masks, &settings, &|_| {});
        let (img, _) = render_all(
            &r.with_lights(&Lights::env(fit.envmap.clone())),
            &sc,
            256,
            5,
        );
        let err: f64 = (0..refs.len())
            .map(|v| {
                metrics::compare(&img[v], &refs[v], &masks[v])
                    .unwrap()
                    .rel_mae
            })
            .sum::<f64>()
            / refs.len() as f64;
        (colour_figures(&fit.envmap, &sc.lights, center), err)
    };
    let (apart, apart_err) = fit_with(Colour::PerChannel);
    let (together, together_err) = fit_with(Colour::Together);
    eprintln!(
        "per channel {apart:?} relMAE {apart_err}; together {together:?} relMAE {together_err}"
    );
    let angle =
        |c: &lightprobe::estimate::recovery::ColourFigures| c.angle_to_lights_degrees.unwrap();
    // Measured: per channel 21.7% of the power in split cells, 13.6° from the lamp's colour;
    // together none, 12.2° (the misfit the map absorbs is coloured by the scene's albedo).
    assert!(together.split_power.unwrap() < 0.01, "{together:?}");
    // The comparison shows the fault the mode removes, so this test can tell them apart.
    assert!(apart.split_power.unwrap() > 0.05, "{apart:?}");
    assert!(angle(&together) < angle(&apart), "{together:?} {apart:?}");
    assert!(
        together_err < 1.02 * apart_err,
        "{together_err} vs {apart_err}"
    );
}

/// The test scene with a striped texture on its table, `true_scene`, and `baked`, the same with
/// a soft shadow baked into that texture (down to 45% in a blob the views see).
struct BakedTable {
    true_scene: Scene,
    baked: Scene,
    /// The true texture's texels, `N`×`N`.
    stripes: Vec<Vec3>,
}

impl BakedTable {
    const N: u32 = 64;

    fn new(lights: Vec<SphereLight>) -> Self {
        use lightprobe::scene::Texture;
        let n = Self::N;
        let stripes: Vec<Vec3> = (0..n * n)
            .map(|i| {
                if (i % n / 8).is_multiple_of(2) {
                    Vec3::new(0.7, 0.6, 0.45)
                } else {
                    Vec3::new(0.5, 0.42, 0.3)
                }
            })
            .collect();
        let texture = |texels: Vec<Vec3>| Albedo::Texture {
            texture: std::sync::Arc::new(Texture {
                width: n,
                height: n,
                texels,
            }),
            factor: Vec3::ONE,
        };
        let mut sc = scene(lights);
        // The table with texture coordinates over its 2 m × 2 m, texels 3 cm wide.
        let mut mesh = lightprobe::scene::Mesh::default();
        let p = [
            Vec3::new(-1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(-1.0, 0.0, 1.0),
        ];
        let uv = [
            glam::Vec2::new(0.0, 0.0),
            glam::Vec2::new(1.0, 0.0),
            glam::Vec2::new(1.0, 1.0),
            glam::Vec2::new(0.0, 1.0),
        ];
        mesh.push(&p, None, Some(&uv), &[0, 2, 1, 0, 3, 2], 0);
        let rest = {
            let mut m = sc.mesh.clone();
            let first = 2; // the plane's two triangles come first
            m.triangles.drain(..first);
            m.triangle_material.drain(..first);
            m
        };
        // Rebuild: the textured plane, then the ball and the box as `scene` made them.
        let mut whole = mesh;
        let offset = whole.positions.len() as u32;
        whole.positions.extend(&rest.positions);
        whole.normals.extend(&rest.normals);
        whole.uvs.extend(&rest.uvs);
        whole.colors.extend(&rest.colors);
        whole
            .triangles
            .extend(rest.triangles.iter().map(|t| t.map(|i| i + offset)));
        whole.triangle_material.extend(&rest.triangle_material);
        sc.mesh = whole;
        sc.materials[0].albedo = texture(stripes.clone());
        let mut baked = sc.clone();
        baked.materials[0].albedo = texture(
            stripes
                .iter()
                .enumerate()
                .map(|(i, t)| *t * Self::shadow(i as u32))
                .collect(),
        );
        BakedTable {
            true_scene: sc,
            baked,
            stripes,
        }
    }

    /// The factor baked into texel `i`.
    fn shadow(i: u32) -> f32 {
        let n = Self::N;
        let (u, v) = (
            (i % n) as f32 / n as f32 - 0.62,
            (i / n) as f32 / n as f32 - 0.72,
        );
        1.0 - 0.55 * (-(u * u + v * v) / (2.0 * 0.12f32.powi(2))).exp()
    }

    /// Mean relative error (worst channel) of the table's fitted texture × factor against the
    /// true texture, over the texels the views see (texture coordinates at their pixel
    /// centres, rendered by `truth`) and over those inside the shadow (darkened by more than
    /// 20%).
    fn texture_error(
        &self,
        truth: &Renderer,
        e: &lightprobe::estimate::job::Estimate,
    ) -> (f64, f64) {
        let n = Self::N;
        let mut seen_texel = vec![false; (n * n) as usize];
        for cam in &self.true_scene.cameras {
            let aovs = truth.aovs(cam);
            let ids = truth.material_ids(cam);
            for (uv, id) in aovs.uv.iter().zip(ids) {
                if id == 0 && uv.is_finite() {
                    let (x, y) = ((uv.x * n as f32) as u32, (uv.y * n as f32) as u32);
                    seen_texel[(y.min(n - 1) * n + x.min(n - 1)) as usize] = true;
                }
            }
        }
        let Albedo::Texture { texture, factor } = &e.materials.as_ref().unwrap()[0].albedo else {
            panic!("the table stays textured");
        };
        let (mut all, mut inside) = ((0.0f64, 0usize), (0.0f64, 0usize));
        for (i, t) in texture.texels.iter().enumerate() {
            if seen_texel[i] {
                let rel = (*t * *factor / self.stripes[i] - Vec3::ONE)
                    .abs()
                    .max_element() as f64;
                all = (all.0 + rel, all.1 + 1);
                if Self::shadow(i as u32) < 0.8 {
                    inside = (inside.0 + rel, inside.1 + 1);
                }
            }
        }
        assert!(inside.1 > 100, "the views see the shadow");
        (all.0 / all.1 as f64, inside.0 / inside.1 as f64)
    }
}

#[test]
fn shading_baked_into_a_texture_is_taken_out_by_texels() {
    // The references show the true texture under a 3-ring sky. `--fit-albedo materials` can
    // only rescale the whole texture; `texels` must take most of the shadow out (texture
    // error over the seen texels well under half the materials fit's), keep the stripes, and
    // fit the lighting as well as with the true texture.
    use lightprobe::estimate::albedo::FitAlbedo;
    use lightprobe::estimate::job::{self, EstimateSettings, Job, References, Rings};
    let table = BakedTable::new(vec![]);
    let sc = &table.true_scene;
    let lights = Lights::env(three_ring_sky());
    let truth = Renderer::new(sc, &lights);
    let render = settings(256, 1);
    let (refs, _) = render_all(&truth, sc, 256, 1);
    let seen = job::observe(&truth, &render, References::Images(refs), &()).unwrap();
    let fit = truth.with_scene(&table.baked, &lights);
    let progress = Recorder::default();
    let run = |fit_albedo, fit: &Renderer| {
        let settings = EstimateSettings {
            rings: Rings::Fixed(3),
            spp: 256,
            noise_floor: false,
            fit_albedo,
            trust_albedo: match fit_albedo {
                Some(_) => vec!["ball".into()],
                None => Vec::new(),
            },
            texel_grid: 16,
            ..EstimateSettings::new(&sc.settings)
        };
        let job = Job {
            fit,
            ..Job::new(&truth, &seen, &render, &settings)
        };
        job::run(&job, &progress).unwrap()
    };
    let exact = run(None, &truth).report.rel_mae.unwrap();
    let materials = run(Some(FitAlbedo::Materials), &fit);
    let texels = run(Some(FitAlbedo::Texels), &fit);
    let (e_materials, e_texels) = (
        table.texture_error(&truth, &materials),
        table.texture_error(&truth, &texels),
    );
    let report = texels.report.albedo.as_ref().unwrap();
    let (rel_materials, rel_texels) = (
        materials.report.rel_mae.unwrap(),
        texels.report.rel_mae.unwrap(),
    );
    eprintln!(
        "texture error (all, in the shadow): materials {e_materials:?}, texels {e_texels:?}; \
         relMAE exact {exact:.4}, materials {rel_materials:.4}, texels {rel_texels:.4}; {} \
         rounds, {:?}",
        report.texel_rounds, report.texels
    );
    assert!(
        e_texels.0 < 0.4 * e_materials.0 && e_texels.1 < 0.2 * e_materials.1,
        "texture error (all, in the shadow): materials {e_materials:?}, texels {e_texels:?}"
    );
    assert!(
        rel_texels < 1.1 * exact && rel_materials > 1.5 * exact,
        "relMAE exact {exact}, materials {rel_materials}, texels {rel_texels}"
    );
    assert_eq!(report.texels.len(), 1);
    let fit = &report.texels[0];
    // The shadow took the texture to 45%: the correction reaches about 1/0.45 inside it,
    // and keeps the level (about 1) outside.
    assert!(fit.range[1] > 1.7 && fit.range[0] > 0.85, "{fit:?}");
    assert!(fit.cells_seen > 100 && fit.clamped_texels == 0, "{fit:?}");
    // A deviation is stated for the correction, and it is a fraction of it.
    let [median, largest] = fit.sigma.expect("measured on a 16×16 grid");
    assert!(
        0.0 < median && median <= largest && largest < 0.2,
        "{fit:?}"
    );
    // Every phase, the deviations' columns (three channels per cell) among them, reports
    // exactly the work it declared.
    let phases = progress.0.into_inner().unwrap();
    let columns = 3 * (fit.grid[0] * fit.grid[1]) as u64;
    assert!(
        phases.contains(&("texel deviations".to_string(), columns, columns)),
        "{phases:?}"
    );
    assert!(phases.iter().all(|p| p.1 == p.2), "{phases:?}");
}

#[test]
fn texels_are_corrected_beside_per_view_exposures() {
    // Photographs at two exposures (2 and 0.6) of the table with its true texture under a near
    // light; the fit's texture has the shadow baked in. `--fit-albedo texels --exposure
    // per-view` with one sphere light must give back the exposures' ratio, take the shadow out
    // of the texture as a fit at one exposure does, and fit the light as well.
    use lightprobe::estimate::albedo::FitAlbedo;
    use lightprobe::estimate::job::{
        self, EstimateSettings, Exposure, Job, LightModel, References,
    };
    let table = BakedTable::new(vec![NEAR_LIGHT]);
    let sc = &table.true_scene;
    let lights = Lights::new(sc.lights.clone());
    let truth = Renderer::new(sc, &lights);
    let render = settings(128, 1);
    let (refs, masks) = render_all(&truth, sc, 256, 1);
    let applied = [2.0f32, 0.6];
    let mut photos = refs.clone();
    at_exposures(&mut photos, &applied);
    let fit = truth.with_scene(&table.baked, &lights);
    let run = |refs: &[Image], exposure| {
        let seen = job::observe(&truth, &render, References::Images(refs.to_vec()), &()).unwrap();
        let settings = EstimateSettings {
            model: LightModel::Spheres(Some(1)),
            spp: 256,
            noise_floor: false,
            fit_albedo: Some(FitAlbedo::Texels),
            trust_albedo: vec!["ball".into()],
            texel_grid: 16,
            exposure,
            ..EstimateSettings::new(&sc.settings)
        };
        let job = Job {
            fit: &fit,
            ..Job::new(&truth, &seen, &render, &settings)
        };
        job::run(&job, &()).unwrap()
    };
    let shared = run(&refs, Exposure::Shared);
    let per_view = run(&photos, Exposure::PerView);
    let report = per_view.report.exposure.as_ref().unwrap();
    let e: Vec<f64> = report.relative.iter().map(|v| v.exposure).collect();
    let want = (applied[0] / applied[1]) as f64;
    assert!(
        ((e[0] / e[1]) / want - 1.0).abs() < 0.01 && report.converged,
        "exposures {e:?}, want ratio {want}; {report:?}"
    );
    // They are the exposures of the lighting the estimate ends with, in the scene at the
    // albedo it ends with: each photograph's sum over that render's, relative to their
    // geometric mean.
    let mut fitted_scene = table.baked.clone();
    fitted_scene.materials = per_view.materials.clone().unwrap();
    let final_lights = Lights::new(per_view.spheres.as_ref().unwrap().fit.lights());
    let cams: Vec<&Camera> = sc.cameras.iter().collect();
    let renders = truth.with_scene(&fitted_scene, &final_lights).render_views(
        &cams,
        &settings(256, 7),
        &|_| {},
    );
    let sum = |img: &Image, mask: &[bool]| -> f64 {
        img.rgb
            .iter()
            .zip(mask)
            .filter(|(_, m)| **m)
            .map(|(p, _)| p.as_dvec3().element_sum())
            .sum()
    };
    let ratios: Vec<f64> = (0..2)
        .map(|v| sum(&photos[v], &masks[v]) / sum(&renders[v], &masks[v]))
        .collect();
    let mean = (ratios[0] * ratios[1]).sqrt();
    for (r, e) in ratios.iter().zip(&e) {
        assert!(
            (r / mean / e - 1.0).abs() < 0.003,
            "the final lighting's exposures {ratios:?} / {mean}, reported {e:?}"
        );
    }
    let (e_shared, e_per_view) = (
        table.texture_error(&truth, &shared),
        table.texture_error(&truth, &per_view),
    );
    let rel = |e: &job::Estimate| e.spheres.as_ref().unwrap().rel_mae().unwrap();
    let (rel_shared, rel_per_view) = (rel(&shared), rel(&per_view));
    eprintln!(
        "exposures {e:?} ({} fits); texture error (all, in the shadow): one exposure \
         {e_shared:?}, per view {e_per_view:?}; relMAE {rel_shared:.4}, {rel_per_view:.4}",
        report.fits
    );
    // The shadow (down to 45%, an error of up to 55% as given) is taken out as well, and the
    // texels one view sees alone are as good (a view's exposure left in them would not be).
    assert!(
        e_per_view.1 < 0.1
            && e_per_view.1 < 1.5 * e_shared.1 + 0.01
            && e_per_view.0 < 1.5 * e_shared.0 + 0.01,
        "texture error (all, in the shadow): one exposure {e_shared:?}, per view {e_per_view:?}"
    );
    assert!(
        rel_per_view < 1.1 * rel_shared,
        "relMAE one exposure {rel_shared}, per view {rel_per_view}"
    );
    // The light in the unit of the exposures' geometric mean: the one-exposure fit's light
    // times it.
    let power =
        |e: &job::Estimate| estimate::spheres::power(&e.spheres.as_ref().unwrap().fit.lights()[0]);
    let mean = (applied[0] * applied[1]).sqrt();
    let ratio = power(&per_view) / (mean * power(&shared));
    assert!(
        (ratio - 1.0).abs() < 0.03,
        "power / (one exposure's × mean exposure) = {ratio}; one exposure's / true {}",
        power(&shared) / estimate::spheres::power(&NEAR_LIGHT)
    );
}
