//! Any bytes → the envmap.ron parser and, when it parses, a lat-long export and lookups.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("lightprobe-fuzz-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let p = dir.join("env.ron");
    if std::fs::write(&p, data).is_ok()
        && let Ok(env) = lightprobe::envmap::Envmap::load(&p)
    {
        let img = lightprobe::envmap::latlong::export(&env, lightprobe::envmap::latlong::Target::Mitsuba, lightprobe::envmap::latlong::Filter::Smooth, 16);
        assert!(img.rgb.iter().all(|c| c.is_finite()));
    }
});
