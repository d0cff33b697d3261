//! Any bytes as a view's reference EXR → reference loading (size, radiance and alpha checks):
//! references or an error naming the file, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("lightprobe-fuzz-ref-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let cam = lightprobe::scene::Camera::look_at("cam", glam::Vec3::Z, glam::Vec3::ZERO, 0.8, 4, 3);
    if std::fs::write(dir.join("cam.exr"), data).is_ok() {
        let _ = lightprobe::estimate::pipeline::load_references(&dir, &[&cam], Default::default());
    }
});
