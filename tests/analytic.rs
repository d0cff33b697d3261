//! Rendering against closed-form answers. Scenes are built in code, so each answer is exact.

use std::f64::consts::PI;

use glam::Vec3;
mod common;
use common::{icosphere, plane};
use lightprobe::render::{Lights, RenderSettings, Renderer, Strategy};
use lightprobe::scene::{Albedo, Camera, Material, Mesh, Scene, SceneSettings, SphereLight};

fn scene(mesh: Mesh, albedo: Vec3, camera: Camera, lights: Vec<SphereLight>) -> Scene {
    Scene {
        mesh,
        materials: vec![Material {
            name: "m".into(),
            albedo: Albedo::Constant(albedo),
        }],
        cameras: vec![camera],
        lights,
        settings: SceneSettings {
            spp: 1,
            max_bounces: 1,
            seed: 1,
            rings: 1,
        },
        size_given: true,
        camera_names: Vec::new(),
        ignored: Vec::new(),
        source: Default::default(),
        gltf: Default::default(),
    }
}

fn settings(spp: u32, max_bounces: u32, strategy: Strategy) -> RenderSettings {
    RenderSettings {
        spp,
        max_bounces,
        seed: 7,
        strategy,
        hide_emitters: true,
        camera_sees_lights: true,
        every_light: false,
    }
}

/// Irradiance at a point with normal n from a uniform sphere wholly above its horizon:
/// E = π L sin²α cos θ, sin α = r / d.
fn sphere_irradiance(p: Vec3, n: Vec3, light: &SphereLight) -> f64 {
    let to_c = (light.center - p).as_dvec3();
    let d = to_c.length();
    let sin2 = (light.radius as f64 / d).powi(2);
    PI * light.radiance.x as f64 * sin2 * to_c.normalize().dot(n.as_dvec3())
}

/// A narrow camera looking at `target` from `eye` (pixel footprints are tiny, so irradiance is
/// nearly constant across each pixel).
fn narrow_camera(eye: Vec3, target: Vec3) -> Camera {
    Camera::look_at("cam", eye, target, 0.02, 8, 8)
}

#[test]
fn diffuse_plane_under_sphere_light_matches_closed_form() {
    let albedo = 0.6f32;
    for (light_center, radius) in [
        (Vec3::new(0.0, 2.0, 0.0), 0.3),
        (Vec3::new(1.5, 0.9, -0.4), 0.25),
    ] {
        let light = SphereLight {
            center: light_center,
            radius,
            radiance: Vec3::splat(10.0),
        };
        let target = Vec3::new(0.2, 0.0, 0.1);
        let cam = narrow_camera(Vec3::new(-0.5, 1.2, 1.0), target);
        let sc = scene(
            plane(50.0, 0.0),
            Vec3::splat(albedo),
            cam.clone(),
            vec![light],
        );
        let lights = Lights::new(sc.lights.clone());
        let r = Renderer::new(&sc, &lights);
        let img = r.render_radiance(&cam, 0, &settings(4096, 1, Strategy::Mis), &|_| {});
        let depth = r.aovs(&cam).depth;
        for i in 0..64 {
            let (x, y) = ((i % 8) as f32 + 0.5, (i / 8) as f32 + 0.5);
            let p = cam.origin_world + cam.ray_dir_world(x, y) * depth.rgb[i].x;
            let want = albedo as f64 / PI * sphere_irradiance(p, Vec3::Y, &light);
            let got = img.rgb[i].x as f64;
            assert!(
                (got / want - 1.0).abs() < 0.01,
                "light {light_center}: pixel {i}: {got} vs {want}"
            );
        }
    }
}

#[test]
fn diffuse_plane_under_point_light_matches_inverse_square_law() {
    // E = I cos θ / d²; the image is exact up to the pixel footprint (one sample direction per
    // point, no noise from the light): 64 spp only average the footprint.
    let albedo = 0.6f32;
    let light = SphereLight::point(Vec3::new(0.4, 1.7, -0.2), Vec3::new(5.0, 3.0, 1.0));
    let target = Vec3::new(0.2, 0.0, 0.1);
    let cam = narrow_camera(Vec3::new(-0.5, 1.2, 1.0), target);
    let sc = scene(
        plane(50.0, 0.0),
        Vec3::splat(albedo),
        cam.clone(),
        vec![light],
    );
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    for strategy in [Strategy::Mis, Strategy::LightOnly] {
        let img = r.render_radiance(&cam, 0, &settings(64, 1, strategy), &|_| {});
        let depth = r.aovs(&cam).depth;
        for i in 0..64 {
            let (x, y) = ((i % 8) as f32 + 0.5, (i / 8) as f32 + 0.5);
            let p = cam.origin_world + cam.ray_dir_world(x, y) * depth.rgb[i].x;
            let to = (light.center - p).as_dvec3();
            let e = to.normalize().y / to.length_squared();
            for c in 0..3 {
                let want = albedo as f64 / PI * light.radiance[c] as f64 * e;
                let got = img.rgb[i][c] as f64;
                assert!(
                    (got / want - 1.0).abs() < 2e-3,
                    "pixel {i} channel {c}: {got} vs {want}"
                );
            }
        }
    }
    // BSDF sampling alone never finds a point.
    let img = r.render_radiance(&cam, 0, &settings(16, 1, Strategy::BsdfOnly), &|_| {});
    assert!(img.rgb.iter().all(|p| *p == Vec3::ZERO));
}

#[test]
fn a_point_light_is_the_limit_of_shrinking_spheres_of_the_same_intensity() {
    // The same scene lit by a point of intensity I and by a sphere of radius r and radiance
    // I / (π r²): at r = 1 cm, 1.5 m away, they differ by O(r²/d²) ≈ 5e-5 plus the sphere's
    // soft-shadow noise; two bounces, an occluding ball, MIS.
    let intensity = Vec3::new(6.0, 5.0, 4.0);
    let center = Vec3::new(0.5, 1.5, 0.2);
    let point = SphereLight::point(center, intensity);
    let r = 0.01f32;
    let sphere = SphereLight {
        center,
        radius: r,
        radiance: intensity / (std::f32::consts::PI * r * r),
    };
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 2.5), Vec3::ZERO, 0.9, 24, 18);
    let mut mesh = plane(5.0, 0.0);
    mesh.append(&icosphere(Vec3::new(0.2, 0.3, 0.0), 0.3, 3), 0);
    let mean = |light: SphereLight| {
        let sc = scene(mesh.clone(), Vec3::splat(0.7), cam.clone(), vec![light]);
        let lights = Lights::new(sc.lights.clone());
        let img = Renderer::new(&sc, &lights).render_radiance(
            &cam,
            0,
            &settings(256, 2, Strategy::Mis),
            &|_| {},
        );
        img.rgb.iter().map(|p| p.as_dvec3()).sum::<glam::DVec3>() / img.rgb.len() as f64
    };
    let (a, b) = (mean(point), mean(sphere));
    for c in 0..3 {
        assert!((a[c] / b[c] - 1.0).abs() < 5e-3, "channel {c}: {a} vs {b}");
    }
}

/// MIS, light-only and BSDF-only sampling, with one light picked or every light sampled, give
/// the same image mean within 1%, each averaged over
/// 4 seeds (BSDF sampling alone varies by ~0.6% between seeds in these scenes, so 1% is several
/// standard errors wide).
fn assert_strategies_agree(render: impl Fn(Strategy, bool, u64) -> lightprobe::imageio::Image) {
    // Light picking, and sampling every light ([`RenderSettings::every_light`]).
    let means: Vec<Vec3> = [
        (Strategy::Mis, false),
        (Strategy::LightOnly, false),
        (Strategy::BsdfOnly, false),
        (Strategy::Mis, true),
        (Strategy::LightOnly, true),
    ]
    .iter()
    .map(|&(s, every)| {
        (0..4u64)
            .map(|seed| render(s, every, seed).mean())
            .sum::<Vec3>()
            / 4.0
    })
    .collect();
    for m in &means[1..] {
        let rel = ((*m - means[0]).abs() / means[0]).max_element();
        assert!(rel < 0.01, "means differ by {rel}: {means:?}");
    }
}

#[test]
fn mis_light_only_and_bsdf_only_agree() {
    // A large light so BSDF sampling alone finds it often enough to converge.
    let light = SphereLight {
        center: Vec3::new(0.5, 1.5, 0.0),
        radius: 0.8,
        radiance: Vec3::new(4.0, 2.0, 1.0),
    };
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 3.0), Vec3::ZERO, 0.9, 16, 12);
    let mut mesh = plane(3.0, 0.0);
    let ball = icosphere(Vec3::new(-0.4, 0.35, 0.3), 0.35, 3);
    mesh.append(&ball, 0);
    // A second, dimmer light: lights are picked by how strongly they light each point, and
    // every strategy must still agree on the mean.
    let dim = SphereLight {
        center: Vec3::new(-1.2, 1.0, 0.9),
        radius: 0.6,
        radiance: Vec3::new(0.3, 0.4, 0.6),
    };
    let sc = scene(mesh, Vec3::splat(0.7), cam.clone(), vec![light, dim]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    assert_strategies_agree(|strategy, every_light, seed| {
        r.render_radiance(
            &cam,
            0,
            &RenderSettings {
                seed,
                every_light,
                ..settings(1024, 3, strategy)
            },
            &|_| {},
        )
    });
}

#[test]
fn closed_sphere_around_a_light_follows_the_bounce_series() {
    // Inside a closed sphere of radius R (albedo ρ) around a light of radius r at its centre,
    // every wall point sees the light over a cone with cos-weighted fraction s = (r/R)², and
    // the wall elsewhere. With k scattering events the wall's radiance is
    // L ρ s Σ_{j<k} (ρ(1−s))^j; with ρ = 1 and k → ∞ it is L (energy is conserved). Sample
    // counts keep one standard error near 0.25% (measured over seeds), so 1% is ~4σ.
    let (big_r, r) = (1.0f32, 0.3f32);
    let s = (r / big_r).powi(2) as f64;
    let light = SphereLight {
        center: Vec3::ZERO,
        radius: r,
        radiance: Vec3::splat(2.0),
    };
    let cam = Camera::look_at(
        "cam",
        Vec3::new(0.0, 0.0, 0.45),
        Vec3::new(0.0, 0.2, 1.0),
        0.6,
        8,
        8,
    );
    for (rho, k, spp) in [(0.8f64, 1u32, 256u32), (0.8, 3, 1024), (1.0, 48, 4096)] {
        let sc = scene(
            icosphere(Vec3::ZERO, big_r, 5),
            Vec3::splat(rho as f32),
            cam.clone(),
            vec![light],
        );
        let lights = Lights::new(sc.lights.clone());
        let img = Renderer::new(&sc, &lights).render_radiance(
            &cam,
            0,
            &settings(spp, k, Strategy::Mis),
            &|_| {},
        );
        let want = 2.0
            * rho
            * s
            * (0..k)
                .map(|j| (rho * (1.0 - s)).powi(j as i32))
                .sum::<f64>();
        let got = img.mean().x as f64;
        assert!(
            (got / want - 1.0).abs() < 0.01,
            "ρ={rho} k={k}: {got} vs {want}"
        );
        // Every camera ray should hit the closed wall. Our Möller–Trumbore test is not
        // watertight: measured, about 1 ray in 65,536 slips through an edge here. Bound it.
        let alpha = img.alpha.as_ref().unwrap();
        let coverage = alpha.iter().map(|&a| a as f64).sum::<f64>() / alpha.len() as f64;
        assert!(
            coverage > 1.0 - 1e-4,
            "{} of camera rays escaped a closed sphere",
            1.0 - coverage
        );
    }
}

#[test]
fn same_image_at_any_thread_count() {
    let light = SphereLight {
        center: Vec3::new(0.3, 1.5, 0.2),
        radius: 0.2,
        radiance: Vec3::splat(20.0),
    };
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 2.0), Vec3::ZERO, 0.8, 37, 23);
    let mut mesh = plane(2.0, 0.0);
    let ball = icosphere(Vec3::new(0.0, 0.3, 0.0), 0.3, 2);
    mesh.append(&ball, 0);
    let sc = scene(mesh, Vec3::splat(0.5), cam.clone(), vec![light]);
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    let render = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| r.render_radiance(&cam, 3, &settings(16, 3, Strategy::Mis), &|_| {}))
    };
    let one = render(1);
    assert!(one.mean().x > 0.0);
    for t in [2, 3, 5] {
        let other = render(t);
        let same = one
            .rgb
            .iter()
            .zip(&other.rgb)
            .all(|(a, b)| a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits));
        assert!(same, "{t} threads differ from 1");
        assert_eq!(one.alpha, other.alpha);
    }
    // A different seed gives a different image (the seed is really used).
    let mut st = settings(16, 3, Strategy::Mis);
    st.seed = 8;
    assert_ne!(r.render_radiance(&cam, 3, &st, &|_| {}).rgb, one.rgb);
}

#[test]
fn depth_aov_is_exact_on_a_plane() {
    let cam = Camera::look_at(
        "cam",
        Vec3::new(0.0, 2.0, 0.0) + Vec3::new(0.0, 0.0, 0.001),
        Vec3::ZERO,
        0.5,
        8,
        8,
    );
    let sc = scene(plane(10.0, 0.0), Vec3::splat(0.5), cam.clone(), vec![]);
    let lights = Lights::default();
    let aov = Renderer::new(&sc, &lights).aovs(&cam);
    for i in 0..64 {
        let d = cam.ray_dir_world((i % 8) as f32 + 0.5, (i / 8) as f32 + 0.5);
        let want = cam.origin_world.y / -d.y;
        assert!((aov.depth.rgb[i].x - want).abs() < 1e-5 * want);
        assert!((aov.normal.rgb[i] - Vec3::Y).length() < 1e-6);
    }
}

// ---- Environment map lighting ----

use lightprobe::envmap::Envmap;

fn render_env(
    sc: &Scene,
    env: Envmap,
    cam: &Camera,
    st: RenderSettings,
) -> lightprobe::imageio::Image {
    let lights = Lights::env(env);
    Renderer::new(sc, &lights).render_radiance(cam, 0, &st, &|_| {})
}

#[test]
fn constant_envmap_over_a_plane_gives_albedo_times_radiance() {
    let cam = Camera::look_at("cam", Vec3::new(0.3, 1.5, 1.0), Vec3::ZERO, 0.6, 8, 8);
    let sc = scene(
        plane(100.0, 0.0),
        Vec3::new(0.2, 0.5, 0.8),
        cam.clone(),
        vec![],
    );
    let img = render_env(
        &sc,
        Envmap::constant(9, Vec3::splat(1.5)),
        &cam,
        settings(1024, 1, Strategy::Mis),
    );
    let want = Vec3::new(0.2, 0.5, 0.8) * 1.5;
    assert!(
        ((img.mean() - want).abs() / want).max_element() < 0.005,
        "mean {} vs {want}",
        img.mean()
    );
    for c in &img.rgb {
        assert!(
            ((*c - want).abs() / want).max_element() < 0.03,
            "pixel {c} vs {want}"
        );
    }
}

#[test]
fn white_furnace_is_invisible() {
    // Albedo 1 everywhere under a constant envmap: with enough bounces every surface has the
    // envmap's radiance, whatever the geometry.
    let cam = Camera::look_at(
        "cam",
        Vec3::new(0.0, 1.0, 2.5),
        Vec3::new(0.0, 0.3, 0.0),
        0.8,
        12,
        9,
    );
    let mut mesh = plane(20.0, 0.0);
    let ball = icosphere(Vec3::new(0.0, 0.5, 0.0), 0.5, 3);
    mesh.append(&ball, 0);
    let sc = scene(mesh, Vec3::ONE, cam.clone(), vec![]);
    let img = render_env(
        &sc,
        Envmap::constant(5, Vec3::splat(0.7)),
        &cam,
        settings(1024, 64, Strategy::Mis),
    );
    // Only pixels wholly on geometry (the background is black: emitters are hidden).
    let covered: Vec<f32> = img
        .rgb
        .iter()
        .zip(img.alpha.as_ref().unwrap())
        .filter(|(_, a)| **a == 1.0)
        .map(|(c, _)| c.x)
        .collect();
    assert!(covered.len() > 60, "{} covered pixels", covered.len());
    let mean = covered.iter().map(|&v| v as f64).sum::<f64>() / covered.len() as f64;
    assert!((mean / 0.7 - 1.0).abs() < 0.005, "{mean}");
    for v in covered {
        assert!((v / 0.7 - 1.0).abs() < 0.03, "pixel {v}");
    }
}

#[test]
fn single_bright_cell_gives_the_patch_irradiance() {
    // One cell of radiance L above an upward plane: E = L ∫cos θ dω = L Δφ (sin²θ1 − sin²θ0) / 2.
    let rings = 7;
    let grid = lightprobe::envmap::RingGrid::new(rings);
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 0.01), Vec3::ZERO, 0.05, 4, 4);
    let sc = scene(plane(100.0, 0.0), Vec3::splat(0.5), cam.clone(), vec![]);
    for cell in [0u32, 3, grid.ring_start(2) + 5] {
        let mut radiance = vec![Vec3::ZERO; grid.cell_count()];
        radiance[cell as usize] = Vec3::splat(10.0);
        let env = Envmap::new(rings, radiance).unwrap();
        let b = grid.bounds(cell);
        let e = 10.0
            * (b.phi_max - b.phi_min)
            * (b.theta_max.sin().powi(2) - b.theta_min.sin().powi(2))
            / 2.0;
        let want = 0.5 / PI * e;
        for strategy in [Strategy::Mis, Strategy::LightOnly] {
            let got = render_env(&sc, env.clone(), &cam, settings(4096, 1, strategy))
                .mean()
                .x as f64;
            assert!(
                (got / want - 1.0).abs() < 0.01,
                "cell {cell} {strategy:?}: {got} vs {want}"
            );
        }
    }
}

#[test]
fn envmap_strategies_agree() {
    let rings = 9;
    let grid = lightprobe::envmap::RingGrid::new(rings);
    let radiance = (0..grid.cell_count() as u32)
        .map(|c| {
            let d = grid.center(c);
            Vec3::new(0.2, 0.3, 0.5)
                + if d.y > 0.6 && d.x > 0.0 {
                    Vec3::new(20.0, 15.0, 8.0)
                } else {
                    Vec3::ZERO
                }
        })
        .collect();
    let env = Envmap::new(rings, radiance).unwrap();
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 3.0), Vec3::ZERO, 0.9, 16, 12);
    let mut mesh = plane(3.0, 0.0);
    let ball = icosphere(Vec3::new(-0.4, 0.35, 0.3), 0.35, 3);
    mesh.append(&ball, 0);
    let sc = scene(mesh, Vec3::splat(0.6), cam.clone(), vec![]);
    assert_strategies_agree(|strategy, every_light, seed| {
        render_env(
            &sc,
            env.clone(),
            &cam,
            RenderSettings {
                seed,
                every_light,
                ..settings(512, 3, strategy)
            },
        )
    });
}

#[test]
fn pixels_that_see_no_geometry_show_what_lies_behind() {
    // The camera sees a sphere light against the void; the only geometry is a plane far
    // below, out of view, so no pixel's camera rays can meet a triangle. Such pixels are
    // skipped wholesale only when nothing can show in them: checked for a fresh render and
    // for walked paths lit afterwards.
    let renders = |r: &Renderer, cam: &Camera, st: &RenderSettings| {
        let fresh = r.render_radiance(cam, 0, st, &|_| {});
        let walked = r.render_radiance_under(cam, 0, st, &[r.lights], &|_| {});
        [fresh, walked.into_iter().next().unwrap()]
    };
    let light = SphereLight {
        center: Vec3::ZERO,
        radius: 0.5,
        radiance: Vec3::new(3.0, 2.0, 1.0),
    };
    let cam = Camera::look_at("cam", Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, 0.2, 8, 8);
    let sc = scene(
        plane(1.0, -10.0),
        Vec3::splat(0.5),
        cam.clone(),
        vec![light],
    );
    let lights = Lights::new(sc.lights.clone());
    let r = Renderer::new(&sc, &lights);
    // Behind the void, an envmap: every pixel sees its radiance, unless emitters are hidden.
    let void = Camera::look_at(
        "void",
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::new(0.0, 0.0, 6.0),
        0.2,
        8,
        8,
    );
    let env = Lights::env(Envmap::constant(9, Vec3::splat(1.5)));
    let r_env = r.with_lights(&env);
    for hide in [true, false] {
        let st = RenderSettings {
            hide_emitters: hide,
            ..settings(16, 2, Strategy::Mis)
        };
        for img in renders(&r, &cam, &st) {
            let want = if hide { Vec3::ZERO } else { light.radiance };
            assert!(
                img.rgb.iter().all(|c| *c == want),
                "light, hide_emitters {hide}"
            );
            assert!(img.alpha.as_ref().unwrap().iter().all(|&a| a == 0.0));
        }
        for img in renders(&r_env, &void, &st) {
            let want = if hide { Vec3::ZERO } else { Vec3::splat(1.5) };
            assert!(
                img.rgb.iter().all(|c| *c == want),
                "envmap, hide_emitters {hide}"
            );
        }
    }
}

#[test]
fn camera_rays_can_pass_through_lights() {
    // A dark light just in front of the camera hides the middle of the view (black, with
    // hidden emitters). With `camera_sees_lights` off, camera rays pass through it and the
    // plane behind shows as it does without that light: the sphere fit's trial lights never
    // black out what a view sees.
    let key = SphereLight {
        center: Vec3::new(0.0, 3.0, 0.0),
        radius: 0.3,
        radiance: Vec3::splat(100.0),
    };
    let dark = SphereLight {
        center: Vec3::new(0.0, 0.9, 2.1),
        radius: 0.08,
        radiance: Vec3::ZERO,
    };
    let cam = Camera::look_at("cam", Vec3::new(0.0, 1.0, 2.5), Vec3::ZERO, 0.8, 16, 16);
    // Traced fresh, or walked first and lit after (as the sphere fit's kept paths are).
    let render = |lights: Vec<SphereLight>, sees: bool, hide: bool, walked: bool| {
        let sc = scene(plane(50.0, 0.0), Vec3::splat(0.5), cam.clone(), lights);
        let lights = Lights::new(sc.lights.clone());
        let st = RenderSettings {
            camera_sees_lights: sees,
            hide_emitters: hide,
            every_light: true,
            ..settings(256, 1, Strategy::Mis)
        };
        let r = Renderer::new(&sc, &lights);
        if walked {
            let mut all = r.render_radiance_under(&cam, 0, &st, &[&lights], &|_| {});
            all.remove(0)
        } else {
            r.render_radiance(&cam, 0, &st, &|_| {})
        }
    };
    let seen = render(vec![key, dark], true, true, false);
    let without = render(vec![key], true, true, false);
    let hidden: Vec<usize> = (0..seen.rgb.len())
        .filter(|&i| seen.rgb[i] == Vec3::ZERO)
        .collect();
    assert!(
        hidden.len() >= 16,
        "the dark light hides {} pixels",
        hidden.len()
    );
    let mean = |img: &lightprobe::imageio::Image| {
        hidden.iter().map(|&i| img.rgb[i].x as f64).sum::<f64>() / hidden.len() as f64
    };
    assert!(mean(&without) > 0.05, "the plane behind is lit");
    // Elsewhere too (the dark light casts no shadow on what the view sees).
    let rest = |img: &lightprobe::imageio::Image| -> f64 {
        (0..img.rgb.len())
            .filter(|i| !hidden.contains(i))
            .map(|i| img.rgb[i].x as f64)
            .sum()
    };
    for (hide, walked) in [(true, false), (true, true), (false, false), (false, true)] {
        let through = render(vec![key, dark], false, hide, walked);
        assert!(
            (mean(&through) / mean(&without) - 1.0).abs() < 0.02,
            "hide {hide}, walked {walked}: {} through the light against {} without it",
            mean(&through),
            mean(&without)
        );
        assert!((rest(&through) / rest(&without) - 1.0).abs() < 0.02);
    }
}
