//! Any bytes → the sidecar parser: a `Sidecar` or an error with a position, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = lightprobe::scene::Sidecar::parse(text, std::path::Path::new("fuzz.ron"));
    }
});
