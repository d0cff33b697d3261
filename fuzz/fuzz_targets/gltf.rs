//! Any bytes → the glTF/GLB loader (geometry, materials, cameras): a scene or an error, never
//! a panic, a hang or an allocation beyond the fuzzer's limit.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = lightprobe::scene::load_gltf_bytes(data, std::path::Path::new("fuzz.glb"), 8, 6);
});
