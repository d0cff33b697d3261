//! A bounded, deterministic fuzz run on stable Rust, in every `cargo test`: the seeds of
//! `fuzz/seeds/<target>/` and a fixed number of seeded mutations of each (bit flips, byte
//! changes, cuts, repeats, splices of another seed) go through the same parsers as the
//! cargo-fuzz targets in `fuzz/` (sidecar, glTF/GLB, envmap, EXR, reference loading). Each
//! must return a value or an error; a panic fails the test and names the seed and mutation
//! that reproduce it. Longer, coverage-guided runs use cargo-fuzz on nightly (README).

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use lightprobe::sampling::Rng;

/// Mutations per seed and target.
const MUTATIONS: usize = 2000;

fn seeds(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/seeds")
        .join(target);
    let mut v: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| {
            let p = e.unwrap().path();
            let bytes = std::fs::read(&p).unwrap();
            (p, bytes)
        })
        .collect();
    v.sort();
    assert!(!v.is_empty(), "no seeds in {}", dir.display());
    v
}

/// One random edit of `data` (`other`: another seed to splice from).
fn mutate(rng: &mut Rng, data: &mut Vec<u8>, other: &[u8]) {
    let pick = |rng: &mut Rng, n: usize| (rng.next_f32() * n as f32) as usize % n.max(1);
    match pick(rng, 7) {
        0 if !data.is_empty() => {
            let i = pick(rng, data.len());
            data[i] ^= 1 << pick(rng, 8);
        }
        1 if !data.is_empty() => {
            let i = pick(rng, data.len());
            // Bytes that matter to parsers: extremes, digits, brackets, NaN's first letter.
            const INTERESTING: &[u8] = b"\x00\xff\x7f\x80019-.e([{N,";
            data[i] = INTERESTING[pick(rng, INTERESTING.len())];
        }
        2 if !data.is_empty() => {
            let len = pick(rng, data.len());
            data.truncate(len);
        }
        3 if !data.is_empty() => {
            let (a, b) = (pick(rng, data.len()), pick(rng, data.len()));
            let (a, b) = (a.min(b), a.max(b).min(a + 64));
            let chunk = data[a..b].to_vec();
            let at = pick(rng, data.len());
            data.splice(at..at, chunk);
        }
        4 if !data.is_empty() && data.len() >= 4 => {
            // A little-endian word set to a large or boundary value (lengths, counts, sizes).
            let i = pick(rng, data.len() - 3);
            let values = [0u32, 1, 0x7fff_ffff, 0xffff_ffff, 45_000, 1 << 20];
            data[i..i + 4].copy_from_slice(&values[pick(rng, values.len())].to_le_bytes());
        }
        5 if !other.is_empty() => {
            let a = pick(rng, other.len());
            let at = pick(rng, data.len() + 1);
            data.splice(at..at, other[a..(a + 32).min(other.len())].iter().copied());
        }
        _ => {
            if !data.is_empty() {
                let i = pick(rng, data.len());
                data.remove(i);
            }
        }
    }
}

/// Runs `parse` on every seed of `target` and on MUTATIONS mutants of each (one to four edits
/// stacked); returns the panics as (seed, mutation number) descriptions. `parse` says whether
/// it accepted the input: some mutants must be accepted too, or the run tested only the
/// parser's first check.
fn smoke(target: &str, parse: &dyn Fn(&[u8]) -> bool) -> Vec<String> {
    let seeds = seeds(target);
    let mut failures = Vec::new();
    let mut accepted = 0;
    let quiet = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    for (k, (path, seed)) in seeds.iter().enumerate() {
        let other = &seeds[(k + 1) % seeds.len()].1;
        let mut rng = Rng::new(0x5eed ^ (k as u64) << 32);
        for m in 0..=MUTATIONS {
            let mut data = seed.clone();
            if m > 0 {
                for _ in 0..1 + (rng.next_f32() * 4.0) as usize {
                    mutate(&mut rng, &mut data, other);
                }
            }
            match catch_unwind(AssertUnwindSafe(|| parse(&data))) {
                Ok(ok) => accepted += (ok && m > 0) as usize,
                Err(_) => failures.push(format!("{target}: {} mutation {m}", path.display())),
            }
        }
    }
    std::panic::set_hook(quiet);
    if accepted == 0 {
        failures.push(format!("{target}: no mutant was accepted"));
    }
    failures
}

#[test]
fn parsers_survive_mutated_seeds() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let cam = lightprobe::scene::Camera::look_at("cam", glam::Vec3::Z, glam::Vec3::ZERO, 0.8, 4, 3);
    let mut failures = Vec::new();
    failures.extend(smoke("sidecar", &|d| {
        std::str::from_utf8(d).is_ok_and(|text| {
            lightprobe::scene::Sidecar::parse(text, Path::new("fuzz.ron")).is_ok()
        })
    }));
    failures.extend(smoke("gltf", &|d| {
        lightprobe::scene::load_gltf_bytes(d, Path::new("fuzz.glb"), 8, 6).is_ok()
    }));
    failures.extend(smoke("envmap", &|d| {
        let p = dir.join("env.ron");
        std::fs::write(&p, d).unwrap();
        let Ok(env) = lightprobe::envmap::Envmap::load(&p) else {
            return false;
        };
        let img = lightprobe::envmap::latlong::export(
            &env,
            lightprobe::envmap::latlong::Target::Mitsuba,
            lightprobe::envmap::latlong::Filter::Smooth,
            16,
        );
        assert!(img.rgb.iter().all(|c| c.is_finite()));
        true
    }));
    failures.extend(smoke("exr", &|d| {
        let Ok(img) = lightprobe::imageio::read_exr_bytes(d, Path::new("fuzz.exr")) else {
            return false;
        };
        assert_eq!(img.rgb.len(), img.width as usize * img.height as usize);
        true
    }));
    failures.extend(smoke("reference", &|d| {
        std::fs::write(dir.join("cam.exr"), d).unwrap();
        lightprobe::estimate::pipeline::load_references(dir, &[&cam], Default::default()).is_ok()
    }));
    assert!(
        failures.is_empty(),
        "{} inputs panicked:\n{}",
        failures.len(),
        failures.join("\n")
    );
}
