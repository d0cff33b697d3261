//! Any bytes → the EXR reader: an image or an error, never a panic, a hang or an allocation
//! the header declared but the budget does not allow.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(img) = lightprobe::imageio::read_exr_bytes(data, std::path::Path::new("fuzz.exr")) {
        assert_eq!(img.rgb.len(), img.width as usize * img.height as usize);
    }
});
