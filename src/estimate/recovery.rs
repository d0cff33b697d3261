//! Light recovery: how well an estimated envmap locates and weighs the true sphere lights.
//!
//! Bright clusters are formed first, without looking at the truth: repeatedly, the cell whose
//! neighbourhood (a cone of radius `max(2 ring spacings, 25°)`) holds the most remaining power
//! seeds a cluster of the cells in that cone (a window, not the single brightest cell, because
//! on fine grids a light's energy spreads over many cells), while clusters hold at least 5% of
//! the total power (at most 8). Then each true light, in order of decreasing power seen from
//! the scene centre, is matched to the nearest unmatched cluster: its power-weighted centroid
//! direction is compared with the light's direction from the scene centre, and its power
//! `Σ lum(λ)·Ω` with the light's `lum(L)·Ω_light`.

use glam::Vec3;
use serde::Serialize;

use crate::envmap::Envmap;
use crate::imageio::luminance;
use crate::scene::SphereLight;

/// Recovery figures of one light.
#[derive(Debug, Clone, Serialize, schemars::JsonSchema)]
pub struct LightRecovery {
    /// Which true light: its index among the scene's lights (the sidecar's order).
    pub true_light: usize,
    /// True direction from the scene centre (unit, world).
    pub true_direction: [f32; 3],
    /// Estimated direction: power-weighted centroid of the light's cluster.
    pub estimated_direction: [f32; 3],
    pub angle_error_degrees: f32,
    /// Estimated cluster power / true power (luminance × solid angle, seen from the centre).
    pub power_ratio: f32,
    pub cluster_cells: usize,
}

/// Matches clusters of bright cells to the true lights.
pub fn recover(env: &Envmap, lights: &[SphereLight], scene_center: Vec3) -> Vec<LightRecovery> {
    let mut order: Vec<(f32, usize, &SphereLight)> = lights
        .iter()
        .enumerate()
        .map(|(i, l)| {
            (
                luminance(l.radiance) * l.solid_angle_from(scene_center),
                i,
                l,
            )
        })
        .collect();
    order.sort_by(|a, b| b.0.total_cmp(&a.0));
    let clusters: Vec<(Vec3, f32, usize)> = clusters(env)
        .into_iter()
        .map(|c| (c.direction, c.power, c.cells))
        .collect();

    // ---- Match each true light to the nearest unmatched cluster ----
    let mut used = vec![false; clusters.len()];
    let mut out = Vec::new();
    for (true_power, true_light, light) in order {
        let truth = (light.center - scene_center).normalize();
        let best = (0..clusters.len()).filter(|&k| !used[k]).min_by(|&a, &b| {
            clusters[a]
                .0
                .angle_between(truth)
                .total_cmp(&clusters[b].0.angle_between(truth))
        });
        let (est, p_sum, count) = match best {
            Some(k) => {
                used[k] = true;
                clusters[k]
            }
            None => (Vec3::ZERO, 0.0, 0),
        };
        out.push(LightRecovery {
            true_light,
            true_direction: truth.to_array(),
            estimated_direction: est.to_array(),
            angle_error_degrees: if count > 0 {
                truth.angle_between(est).to_degrees()
            } else {
                f32::NAN
            },
            power_ratio: if true_power > 0.0 {
                p_sum / true_power
            } else {
                f32::NAN
            },
            cluster_cells: count,
        });
    }
    out
}

/// A bright cluster of an envmap estimate.
#[derive(Debug, Clone, Copy)]
pub struct Cluster {
    /// Power-weighted centroid direction (unit, world).
    pub direction: Vec3,
    /// Σ luminance × solid angle of its cells.
    pub power: f32,
    pub cells: usize,
}

/// The bright clusters of an estimate, brightest first, from the estimate alone (see the
/// module doc): at most 8, each with at least 5% of the total power.
pub fn clusters(env: &Envmap) -> Vec<Cluster> {
    cluster_cells(env)
        .iter()
        .map(|cells| measure(env, cells))
        .collect()
}

/// Power-weighted centroid and power of `env` over `cells`.
fn measure(env: &Envmap, cells: &[u32]) -> Cluster {
    let (mut sum, mut p_sum) = (Vec3::ZERO, 0.0f32);
    for &c in cells {
        let p = luminance(env.radiance()[c as usize]) * env.solid_angle(c);
        sum += env.grid.center(c) * p;
        p_sum += p;
    }
    let first = cells.first().map_or(Vec3::Y, |&c| env.grid.center(c));
    Cluster {
        direction: sum.normalize_or(first),
        power: p_sum,
        cells: cells.len(),
    }
}

/// The cells of each of [`clusters`], brightest cluster first.
fn cluster_cells(env: &Envmap) -> Vec<Vec<u32>> {
    let g = &env.grid;
    let n = g.cell_count() as u32;
    let power: Vec<f32> = (0..n)
        .map(|c| luminance(env.radiance()[c as usize]) * env.solid_angle(c))
        .collect();
    let spacing = if g.rings() > 1 {
        std::f32::consts::PI / (g.rings() - 1) as f32
    } else {
        std::f32::consts::PI
    };
    let radius = (2.0 * spacing).max(25f32.to_radians()) + 1e-4;
    let mut taken = vec![false; n as usize];
    let total: f32 = power.iter().sum();
    let mut clusters: Vec<Vec<u32>> = Vec::new();
    while clusters.len() < 8 {
        let free: Vec<u32> = (0..n).filter(|&c| !taken[c as usize]).collect();
        let window = |axis: Vec3| {
            free.iter()
                .filter(|&&c| g.center(c).angle_between(axis) <= radius)
                .map(|&c| power[c as usize])
                .sum::<f32>()
        };
        let Some(&seed) = free
            .iter()
            .max_by(|&&a, &&b| window(g.center(a)).total_cmp(&window(g.center(b))))
        else {
            break;
        };
        let axis = g.center(seed);
        if window(axis) < 0.05 * total || total <= 0.0 {
            break;
        }
        let cells: Vec<u32> = free
            .iter()
            .copied()
            .filter(|&c| g.center(c).angle_between(axis) <= radius)
            .collect();
        for &c in &cells {
            taken[c as usize] = true;
        }
        clusters.push(cells);
    }
    clusters
}

/// A bright cluster of the envmap estimate ([`clusters`]) with its 95% intervals: what the
/// envmap says of the lights it holds, whether or not the true ones are known.
#[derive(Debug, Clone, Serialize, schemars::JsonSchema)]
pub struct ClusterEstimate {
    /// Power-weighted centroid direction of its cells (unit, world frame, seen from the
    /// scene centre's infinity).
    pub direction: [f32; 3],
    /// Σ luminance × solid angle of its cells (W/m², linear radiance × steradians).
    pub power: f32,
    /// Its cells' indices in the envmap's ring grid (ring by ring from +Y, as envmap.ron).
    pub cells: Vec<u32>,
    /// One standard deviation of the direction per axis, degrees, from the fit's jackknife
    /// replicates over the same cells (None without replicates). It holds the scatter of the
    /// fit: the references' and the transport's noise, and under a misfit how unevenly the
    /// pixels carry it; not the bias of a coarse grid (a 9-ring cell is 22° across) or of a
    /// near light's parallax.
    pub direction_sigma_degrees: Option<f64>,
    /// One standard deviation of the power, relative, from the same replicates.
    pub power_sigma_relative: Option<f64>,
    /// Its colour: Σ radiance × solid angle of its cells per channel (R, G, B), over their
    /// sum (a white light: one third each).
    pub chromaticity: [f32; 3],
}

/// How an envmap's colour holds together ([`crate::estimate::Colour`]).
#[derive(Debug, Clone, Copy, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct ColourFigures {
    /// Share of the map's power (luminance × solid angle) in cells with a channel below a
    /// fifth of their brightest: near-primary cells, the patchwork channels fitted apart make
    /// of lights that are nearly white. None for a black map.
    pub split_power: Option<f64>,
    /// With the true sphere lights known: the mean angle, weighted by power, between each lit
    /// cell's RGB and the lights' summed RGB as seen from the scene centre (radiance × solid
    /// angle), degrees; 0 where every cell has the lights' colour.
    pub angle_to_lights_degrees: Option<f64>,
}

/// The colour figures of `env`, against `truth` seen from `center` where given.
pub fn colour_figures(env: &Envmap, truth: &[SphereLight], center: Vec3) -> ColourFigures {
    let lit: Vec<(Vec3, f64)> = (0..env.grid.cell_count() as u32)
        .map(|c| {
            let rgb = env.radiance()[c as usize];
            (rgb, (luminance(rgb) * env.solid_angle(c)) as f64)
        })
        .filter(|&(rgb, p)| p > 0.0 && rgb.max_element() > 0.0)
        .collect();
    let total: f64 = lit.iter().map(|l| l.1).sum();
    let share = |keep: &dyn Fn(Vec3) -> f64| {
        (total > 0.0).then(|| lit.iter().map(|&(rgb, p)| p * keep(rgb)).sum::<f64>() / total)
    };
    let split = share(&|rgb| (rgb.min_element() < 0.2 * rgb.max_element()) as u8 as f64);
    let lights: Vec3 = truth
        .iter()
        .map(|l| l.radiance * l.solid_angle_from(center))
        .sum();
    let angle = (lights.max_element() > 0.0)
        .then(|| share(&|rgb| rgb.angle_between(lights).to_degrees() as f64))
        .flatten();
    ColourFigures {
        split_power: split,
        angle_to_lights_degrees: angle,
    }
}

/// The bright clusters of `env`, each with the jackknife standard deviations of its
/// direction and power: the same cells measured in each replicate of `replicates` (the
/// delete-a-group fits of [`super::FitSettings::jackknife`]), `(G−1)/G Σ (θ_k − θ̄)²`.
pub fn cluster_estimates(env: &Envmap, replicates: &[Envmap]) -> Vec<ClusterEstimate> {
    let g = replicates.len() as f64;
    cluster_cells(env)
        .iter()
        .map(|cells| {
            let c = measure(env, cells);
            let jackknife = |values: &[f64]| {
                let mean = values.iter().sum::<f64>() / g;
                ((g - 1.0) / g * values.iter().map(|v| (v - mean).powi(2)).sum::<f64>()).sqrt()
            };
            let (mut direction_sigma, mut power_sigma) = (None, None);
            if replicates.len() >= 2 && c.power > 0.0 {
                // Angles of each replicate's centroid in the tangent plane at this one's.
                let d = c.direction;
                let u = d.any_orthonormal_vector();
                let v = d.cross(u);
                let reps: Vec<Cluster> = replicates.iter().map(|r| measure(r, cells)).collect();
                let along = |axis: Vec3| -> Vec<f64> {
                    reps.iter()
                        .map(|r| (r.direction.dot(axis) as f64).atan2(r.direction.dot(d) as f64))
                        .collect()
                };
                let (su, sv) = (jackknife(&along(u)), jackknife(&along(v)));
                direction_sigma = Some(((su * su + sv * sv) / 2.0).sqrt().to_degrees());
                let powers: Vec<f64> = reps.iter().map(|r| r.power as f64).collect();
                power_sigma = Some(jackknife(&powers) / c.power as f64);
            }
            let rgb: Vec3 = cells
                .iter()
                .map(|&i| env.radiance()[i as usize] * env.solid_angle(i))
                .sum();
            let sum = rgb.element_sum();
            ClusterEstimate {
                direction: c.direction.to_array(),
                power: c.power,
                chromaticity: if sum > 0.0 {
                    (rgb / sum).to_array()
                } else {
                    [1.0 / 3.0; 3]
                },
                cells: cells.clone(),
                direction_sigma_degrees: direction_sigma,
                power_sigma_relative: power_sigma,
            }
        })
        .collect()
}

/// Recovery figures of one true sphere light against a sphere-model estimate.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct SphereRecovery {
    /// Which true light: its index among the scene's lights (the sidecar's order); None in
    /// records written before it was reported.
    #[serde(default)]
    pub true_light: Option<usize>,
    /// Index of the matched estimated light among the model's lights (those kept: not
    /// merged, contributing; None: the model has fewer lights).
    pub estimated: Option<usize>,
    /// Distance of the true light from the scene centre, metres.
    pub true_distance_m: f32,
    pub centre_error_m: Option<f32>,
    pub centre_error_fraction_of_distance: Option<f32>,
    pub radius: Option<f32>,
    pub true_radius: f32,
    /// Estimated power / true power (luminance of the radiant intensity, π r² L).
    pub power_ratio: Option<f32>,
}

/// Matches each true light, brightest first, to the nearest unmatched estimated light.
pub fn recover_spheres(
    estimated: &[SphereLight],
    truth: &[SphereLight],
    scene_center: Vec3,
) -> Vec<SphereRecovery> {
    let power = |l: &SphereLight| luminance(l.intensity());
    let mut order: Vec<(usize, &SphereLight)> = truth.iter().enumerate().collect();
    order.sort_by(|a, b| power(b.1).total_cmp(&power(a.1)));
    let mut used = vec![false; estimated.len()];
    order
        .into_iter()
        .map(|(true_light, t)| {
            let d = (t.center - scene_center).length();
            let j = (0..estimated.len()).filter(|&j| !used[j]).min_by(|&a, &b| {
                estimated[a]
                    .center
                    .distance(t.center)
                    .total_cmp(&estimated[b].center.distance(t.center))
            });
            let e = j.map(|j| {
                used[j] = true;
                estimated[j]
            });
            let off = e.map(|e| e.center.distance(t.center));
            SphereRecovery {
                true_light: Some(true_light),
                estimated: j,
                true_distance_m: d,
                centre_error_m: off,
                centre_error_fraction_of_distance: off.map(|o| o / d),
                radius: e.map(|e| e.radius),
                true_radius: t.radius,
                power_ratio: e.map(|e| power(&e) / power(t)).filter(|r| r.is_finite()),
            }
        })
        .collect()
}
