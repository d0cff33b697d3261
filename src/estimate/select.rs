//! Choosing the envmap resolution from the data (`--rings auto`).
//!
//! Each candidate resolution is fitted as usual (same rounds, same samples) but on three
//! quarters of the pixels; its error is measured on the held-out quarter, predicted by the
//! same transport (whose held-out rows are independent samples). A model should be no larger
//! than the data supports, so the choice is the *smallest* resolution whose held-out error is
//! within one standard error of the best one's (the one-standard-error rule of cross
//! validation): the standard error of the paired per-pixel difference, so noise shared by
//! both models cancels.

use std::time::Instant;

use serde::Serialize;

use super::{FitSettings, Transport, Validation, fit_reusing};
use crate::imageio::Image;
use crate::render::Renderer;
use crate::scene::Camera;

/// One candidate resolution's held-out figures.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Candidate {
    pub rings: u32,
    pub cells: usize,
    /// relMAE on the held-out pixels.
    pub validation_rel_mae: f64,
    /// Its held-out relMAE minus the best candidate's (paired, ≥ 0 for all but the best).
    pub excess_over_best: f64,
    /// Standard error of that excess.
    pub standard_error: f64,
    /// Seconds this candidate's hold-out fit took.
    pub seconds: f64,
}

/// The chosen resolution and every candidate's figures.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Selection {
    pub rings: u32,
    /// Ring count of the candidate with the lowest held-out error.
    pub best_rings: u32,
    pub held_out_pixels: usize,
    pub candidates: Vec<Candidate>,
    pub seconds: f64,
}

/// Applies the one-standard-error rule to the candidates' held-out errors (same held-out
/// pixels, in the same order, for every candidate). `None` without candidates.
pub fn choose(validations: &[(u32, usize, Validation, f64)]) -> Option<Selection> {
    let best = validations
        .iter()
        .min_by(|a, b| a.2.rel_mae().total_cmp(&b.2.rel_mae()))?;
    let r = best.2.reference_abs.max(f64::MIN_POSITIVE);
    let mut candidates: Vec<Candidate> = validations
        .iter()
        .map(|(rings, cells, v, secs)| {
            let d: Vec<f64> = v
                .abs_error
                .iter()
                .zip(&best.2.abs_error)
                .map(|(a, b)| a - b)
                .collect();
            let n = d.len().max(1) as f64;
            let mean = d.iter().sum::<f64>() / n;
            let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
            Candidate {
                rings: *rings,
                cells: *cells,
                validation_rel_mae: v.rel_mae(),
                excess_over_best: d.iter().sum::<f64>() / r,
                standard_error: (n * var).sqrt() / r,
                seconds: *secs,
            }
        })
        .collect();
    candidates.sort_by_key(|c| c.rings);
    let chosen = candidates
        .iter()
        .find(|c| c.excess_over_best <= c.standard_error)
        .map_or(best.0, |c| c.rings);
    Some(Selection {
        rings: chosen,
        best_rings: best.0,
        held_out_pixels: best.2.abs_error.len(),
        candidates,
        seconds: validations.iter().map(|v| v.3).sum(),
    })
}

/// Fits every candidate resolution on the kept pixels and chooses by [`choose`]. `template`
/// gives everything but the ring count; `first(rings)` may supply a shared first-round
/// transport for that resolution (see [`super::first_round_transport`]).
#[allow(clippy::too_many_arguments)]
pub fn select_rings(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    candidates: &[u32],
    template: &FitSettings,
    first: &mut dyn FnMut(&FitSettings) -> Option<std::sync::Arc<Transport>>,
    progress: &(dyn Fn(u64) + Sync),
) -> Option<Selection> {
    let t_all = Instant::now();
    let mut validations = Vec::new();
    for &rings in candidates {
        let t = Instant::now();
        let settings = FitSettings {
            rings,
            holdout: true,
            ..*template
        };
        let shared = first(&settings);
        let fit = fit_reusing(
            renderer,
            views,
            references,
            masks,
            &settings,
            shared.as_deref(),
            progress,
        );
        let v = fit.validation.expect("a hold-out fit validates");
        validations.push((
            rings,
            fit.envmap.grid.cell_count(),
            v,
            t.elapsed().as_secs_f64(),
        ));
    }
    let mut s = choose(&validations)?;
    s.seconds = t_all.elapsed().as_secs_f64();
    Some(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(errors: &[f64]) -> Validation {
        Validation {
            abs_error: errors.to_vec(),
            reference_abs: 100.0,
        }
    }

    #[test]
    fn one_standard_error_rule_prefers_the_smallest_model_within_noise() {
        // Candidate 3 is clearly worse; 5 is within noise of 9 (the best); 9 wins the raw min.
        let noise = [0.3, -0.2, 0.25, -0.35, 0.1, -0.1, 0.2, -0.15];
        let base: Vec<f64> = (0..8).map(|i| 1.0 + 0.1 * i as f64).collect();
        let best: Vec<f64> = base.clone();
        let close: Vec<f64> = base.iter().zip(&noise).map(|(b, n)| b + 0.02 + n).collect();
        let far: Vec<f64> = base.iter().map(|b| b + 2.0).collect();
        let s = choose(&[
            (3, 10, v(&far), 0.0),
            (5, 30, v(&close), 0.0),
            (9, 90, v(&best), 0.0),
        ])
        .unwrap();
        assert_eq!(s.best_rings, 9);
        assert_eq!(s.rings, 5);
        assert!(s.candidates[0].excess_over_best > s.candidates[0].standard_error);
        // Without the noise, 5 is consistently worse than 9 and loses.
        let consistent: Vec<f64> = base.iter().map(|b| b + 0.02).collect();
        let s = choose(&[(5, 30, v(&consistent), 0.0), (9, 90, v(&best), 0.0)]).unwrap();
        assert_eq!(s.rings, 9);
        assert!(choose(&[]).is_none());
    }
}
