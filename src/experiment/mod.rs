//! The paper's experiment and beyond: random illumination scenarios ([`scenarios`]), a
//! resumable, shardable sweep of estimates over them ([`sweep`]), and charts of the results
//! ([`report`]).

pub mod report;
pub mod scenarios;
pub mod sweep;

use glam::Vec3;

use crate::sampling::{Rng, mix64};
use crate::scene::Scene;

/// `scene` with every material's albedo but those named in `exact` scaled per channel by a
/// random factor in [1 − `fraction`, 1 + `fraction`] (clamped to [0, 1]), deterministic in
/// `seed`: the imperfect albedo an estimate may have to live with.
pub fn with_albedo_error(scene: &Scene, fraction: f32, seed: u64, exact: &[String]) -> Scene {
    let mut s = scene.clone();
    for (i, m) in s.materials.iter_mut().enumerate() {
        if exact.contains(&m.name) {
            continue;
        }
        let mut rng = Rng::new(mix64(seed ^ (i as u64).wrapping_mul(0x9E37_79B9)));
        let k = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32())
            .map(|u| 1.0 + fraction * (2.0 * u - 1.0));
        *m = m.scaled(k);
    }
    s
}
