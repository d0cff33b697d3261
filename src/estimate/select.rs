//! Choosing the model from the data: the envmap resolution (`--rings auto`) and the light
//! model (`--model auto`: envmap or K sphere lights).
//!
//! Each candidate resolution is fitted as usual (same rounds, same samples) but on three
//! quarters of the pixels; its error is measured on the held-out quarter of a re-render (the
//! transport's samples, a fresh seed). A model should be no larger
//! than the data supports, so the choice is the *smallest* resolution whose held-out error is
//! within one standard error of the best one's (the one-standard-error rule of cross
//! validation): the standard error of the paired per-pixel difference, so noise shared by
//! both models cancels.

use std::time::Instant;

use serde::Serialize;

use super::{Fit, FitSettings, Solver, Validation, fit, fit_candidates, is_held_out};
use crate::envmap::Envmap;
use crate::imageio::Image;
use crate::render::{Lights, RenderSettings, Renderer};
use crate::scene::Camera;

/// One candidate resolution's held-out figures.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct Candidate {
    pub rings: u32,
    pub cells: usize,
    /// relMAE on the held-out pixels.
    pub validation_rel_mae: f64,
    /// Its held-out relMAE minus the best candidate's (paired, ≥ 0 for all but the best).
    pub excess_over_best: f64,
    /// Standard error of that excess.
    pub standard_error: f64,
    /// Seconds of this candidate's own hold-out fit: with NNLS its solve only (the transport
    /// pass and the validation render, shared by all candidates, are in the selection's
    /// seconds).
    pub seconds: f64,
}

/// The chosen resolution and every candidate's figures.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct Selection {
    pub rings: u32,
    /// Ring count of the candidate with the lowest held-out error.
    pub best_rings: u32,
    pub held_out_pixels: usize,
    pub candidates: Vec<Candidate>,
    pub seconds: f64,
}

/// The one-standard-error rule over held-out errors (same held-out pixels, in the same order,
/// for every candidate), candidates given from the simplest: the index of the first within one
/// standard error of the best, the best's index, and per candidate its (excess over the best,
/// standard error of that excess), both relative to the best's held-out reference sum. An
/// excess below `tolerance` × the best's relMAE also counts as within.
pub fn one_standard_error(validations: &[&Validation], tolerance: f64) -> Option<OneStandardError> {
    let best = (0..validations.len()).min_by(|&a, &b| {
        validations[a]
            .rel_mae()
            .total_cmp(&validations[b].rel_mae())
    })?;
    let r = validations[best].reference_abs.max(f64::MIN_POSITIVE);
    let excess: Vec<(f64, f64)> = validations
        .iter()
        .map(|v| {
            let d: Vec<f64> = v
                .abs_error
                .iter()
                .zip(&validations[best].abs_error)
                .map(|(a, b)| a - b)
                .collect();
            let n = d.len().max(1) as f64;
            let mean = d.iter().sum::<f64>() / n;
            let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
            (d.iter().sum::<f64>() / r, (n * var).sqrt() / r)
        })
        .collect();
    let floor = tolerance * validations[best].rel_mae();
    let chosen = excess
        .iter()
        .position(|(e, se)| *e <= se.max(floor))
        .unwrap_or(best);
    Some(OneStandardError {
        chosen,
        best,
        excess,
    })
}

/// The outcome of [`one_standard_error`].
pub struct OneStandardError {
    pub chosen: usize,
    pub best: usize,
    /// Per candidate: (excess over the best, its standard error).
    pub excess: Vec<(f64, f64)>,
}

/// Applies the one-standard-error rule to the candidates' held-out errors. `None` without
/// candidates.
pub fn choose(validations: &[(u32, usize, Validation, f64)]) -> Option<Selection> {
    let mut sorted: Vec<&(u32, usize, Validation, f64)> = validations.iter().collect();
    sorted.sort_by_key(|v| v.0);
    let vals: Vec<&Validation> = sorted.iter().map(|v| &v.2).collect();
    let OneStandardError {
        chosen,
        best,
        excess,
    } = one_standard_error(&vals, 0.0)?;
    let candidates = sorted
        .iter()
        .zip(&excess)
        .map(|((rings, cells, v, secs), &(e, se))| Candidate {
            rings: *rings,
            cells: *cells,
            validation_rel_mae: v.rel_mae(),
            excess_over_best: e,
            standard_error: se,
            seconds: *secs,
        })
        .collect();
    Some(Selection {
        rings: sorted[chosen].0,
        best_rings: sorted[best].0,
        held_out_pixels: sorted[best].2.abs_error.len(),
        candidates,
        seconds: validations.iter().map(|v| v.3).sum(),
    })
}

/// One candidate light model's held-out figures (`--model auto`).
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct ModelCandidate {
    /// `envmap` or `spheres:K`.
    pub model: String,
    /// Numbers the model fits (per sphere: 4 of geometry and 3 of radiance; per cell: 3).
    pub parameters: usize,
    /// relMAE of its re-render on the held-out pixels.
    pub validation_rel_mae: f64,
    pub excess_over_best: f64,
    pub standard_error: f64,
    pub seconds: f64,
}

/// The chosen light model and every candidate's figures.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct ModelSelection {
    pub chosen: String,
    /// The candidate with the lowest held-out error.
    pub best: String,
    pub held_out_pixels: usize,
    pub candidates: Vec<ModelCandidate>,
    /// The first candidate whose re-render scored within [`MODEL_TOLERANCE`] of the noise
    /// floor, if any: no larger model could be chosen over it, so none was fitted after it
    /// (no further sphere light, no sphere model with an envmap behind it).
    #[serde(default)]
    pub at_noise_floor: Option<String>,
    /// That candidate's held-out relMAE over the noise floor's (below 1 + [`MODEL_TOLERANCE`]).
    #[serde(default)]
    pub over_noise_floor: Option<f64>,
}

/// A light model with more parameters must beat a smaller one by more than this fraction of
/// the error, besides one standard error. The standard error treats held-out pixels as
/// independent, but a misfit spans many neighbours (a shadow edge, a penumbra), so it
/// understates the uncertainty: measured on s02, s05 and s50, an extra light bought 0.7–3.5%
/// "significant" held-out improvement by patching a slightly misfit real one (3.5%: s50, a
/// third light beside two), where a true second light gains 50–80% and an envmap behind a
/// lamp under a sky 29%.
pub const MODEL_TOLERANCE: f64 = 0.10;

/// Whether light models larger than the last of `validations` (the held-out errors of the
/// candidates so far, in order of parameter count) could change the choice. Not when the last
/// one scores within [`MODEL_TOLERANCE`] of `floor` (the held-out relMAE of the true lights,
/// which no model can hope to beat) and [`choose_model`]'s rule already picks it over every
/// smaller one: a larger model scoring the floor would leave each smaller one as far outside
/// its bar as it is now, and the last one inside it.
pub fn larger_models_needed(validations: &[&Validation], floor: f64) -> bool {
    let Some(last) = validations.last() else {
        return true;
    };
    let at_floor = floor > 0.0 && last.rel_mae() < (1.0 + MODEL_TOLERANCE) * floor;
    let chosen = one_standard_error(validations, MODEL_TOLERANCE)
        .is_some_and(|o| o.chosen == validations.len() - 1);
    !(at_floor && chosen)
}

/// Chooses among light models fitted without the held-out pixels, by the error of their
/// re-renders there: the fewest parameters within one standard error (and within
/// [`MODEL_TOLERANCE`]) of the best. Each candidate: (name, parameters, held-out validation,
/// seconds).
pub fn choose_model(candidates: Vec<(String, usize, Validation, f64)>) -> Option<ModelSelection> {
    let mut sorted = candidates;
    sorted.sort_by_key(|c| c.1);
    let vals: Vec<&Validation> = sorted.iter().map(|c| &c.2).collect();
    let OneStandardError {
        chosen,
        best,
        excess,
    } = one_standard_error(&vals, MODEL_TOLERANCE)?;
    Some(ModelSelection {
        chosen: sorted[chosen].0.clone(),
        best: sorted[best].0.clone(),
        held_out_pixels: sorted[best].2.abs_error.len(),
        candidates: sorted
            .iter()
            .zip(&excess)
            .map(|((model, parameters, v, secs), &(e, se))| ModelCandidate {
                model: model.clone(),
                parameters: *parameters,
                validation_rel_mae: v.rel_mae(),
                excess_over_best: e,
                standard_error: se,
                seconds: *secs,
            })
            .collect(),
        at_noise_floor: None,
        over_noise_floor: None,
    })
}

/// Settings of a candidate's validation render: the transport's whole budget of samples, and a
/// seed neither the fit nor the final re-render uses.
pub fn validation_settings(template: &FitSettings) -> RenderSettings {
    RenderSettings {
        spp: template.transport.spp * template.rounds.max(1),
        seed: template.transport.seed.wrapping_add(15_485_863),
        ..template.transport
    }
}

/// The held-out errors of `envmaps`, re-rendered by the one path tracer
/// ([`validation_settings`]) on the held-out pixels only, every envmap lighting the same
/// camera paths (their noise is shared, so it cancels in the paired comparison).
///
/// Why a render, not the fit's own transport T̂: predicting held-out pixels as T̂·λ adds T̂'s noise
/// times λ, which grows with the contrast of λ. Measured on a small distant light at 9 rings: 10.5%
/// held-out by T̂ against 7.9% for the honest re-render, so the rule preferred 3 rings (11.0%
/// re-rendered). The re-render also scores envmaps exactly as light models are scored
/// ([`choose_model`]).
fn validate(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    envmaps: &[&Envmap],
    template: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<Validation> {
    let lights: Vec<Lights> = envmaps.iter().map(|e| Lights::env((*e).clone())).collect();
    let sets: Vec<&Lights> = lights.iter().collect();
    let mut validations = vec![Validation::default(); envmaps.len()];
    // A view at a time: all candidates' images of every view at once would be candidates ×
    // views full frames (1.3 GB for 13 candidates and 20 views of 640×480).
    for (v, view) in views.iter().enumerate() {
        let wanted = |(_, i): (usize, u32)| masks[v][i as usize] && is_held_out((v, i));
        let images = renderer.render_views_under(
            std::slice::from_ref(view),
            &validation_settings(template),
            &sets,
            Some(&wanted),
            progress,
        );
        for (validation, images) in validations.iter_mut().zip(&images) {
            add_held_out(validation, v, &images[0], &references[v], &masks[v]);
        }
    }
    validations
}

/// What [`select_rings`] reports to its progress: the candidates' fits (one pass for all with
/// NNLS, [`super::fit_candidates`]), each candidate's held-out pixels, and with NNLS the
/// chosen one's refit on all pixels unless `template.holdout`.
pub fn progress_units(template: &FitSettings, candidates: &[u32], masks: &[Vec<bool>]) -> u64 {
    let held_out = super::transport::progress_units(masks, &|p| is_held_out(p), 1);
    let fits = match template.solver {
        Solver::Nnls => template.candidates_progress_units(masks),
        Solver::Gradient => candidates
            .iter()
            .map(|&rings| {
                FitSettings {
                    rings,
                    holdout: true,
                    ..*template
                }
                .progress_units(masks)
            })
            .sum(),
    };
    let refit = match (template.solver, template.holdout) {
        (Solver::Nnls, false) => template.refit_progress_units(masks),
        _ => 0,
    };
    fits + held_out * candidates.len() as u64 + refit
}

/// The chosen resolution, and with NNLS its fit on the pixels `template` asks for (all, or
/// those [`is_held_out`] leaves in with `template.holdout`), made from the same pass.
pub struct RingsChoice {
    pub selection: Selection,
    pub fit: Option<Fit>,
}

/// Fits every candidate resolution on the kept pixels, re-renders them on the held-out ones,
/// and chooses by [`choose`]. With NNLS one transport pass serves every candidate
/// ([`super::fit_candidates`]) and the chosen one's final fit; the gradient solver fits each
/// candidate on its own. `template` gives everything but the ring count.
#[allow(clippy::too_many_arguments)]
pub fn select_rings(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    candidates: &[u32],
    template: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Option<RingsChoice> {
    if candidates.is_empty() {
        return None;
    }
    let t_all = Instant::now();
    let held_in = FitSettings {
        holdout: true,
        ..*template
    };
    let (fits, joint) = match template.solver {
        Solver::Nnls => {
            let c = fit_candidates(
                renderer, views, references, masks, &held_in, candidates, progress,
            );
            let fits = c.fits.iter().map(|f| (f.envmap.clone(), f.solve_seconds));
            (fits.collect::<Vec<_>>(), Some(c))
        }
        Solver::Gradient => {
            let fits = candidates.iter().map(|&rings| {
                let settings = FitSettings { rings, ..held_in };
                let f = fit(renderer, views, references, masks, &settings, progress);
                (f.envmap, f.transport_seconds + f.solve_seconds)
            });
            (fits.collect(), None)
        }
    };
    let envmaps: Vec<&Envmap> = fits.iter().map(|f| &f.0).collect();
    let validations = validate(
        renderer, views, references, masks, &envmaps, template, progress,
    );
    let validations: Vec<(u32, usize, Validation, f64)> = fits
        .iter()
        .zip(validations)
        .map(|((e, seconds), v)| (e.grid.rings(), e.grid.cell_count(), v, *seconds))
        .collect();
    let mut selection = choose(&validations)?;
    let fit = joint.map(|c| {
        let i = candidates
            .iter()
            .position(|&r| r == selection.rings)
            .expect("the choice is a candidate");
        let settings = FitSettings {
            rings: selection.rings,
            ..*template
        };
        if template.holdout {
            c.held_in_fit(i, &settings)
        } else {
            c.refit(i, &settings, renderer, views, references, masks, progress)
        }
    });
    selection.seconds = t_all.elapsed().as_secs_f64();
    Some(RingsChoice { selection, fit })
}

/// Error of re-rendered images on the held-out pixels ([`is_held_out`]), in one fixed
/// order, so candidates fitted without those pixels can be compared pixel by pixel.
pub fn held_out(images: &[Image], references: &[Image], masks: &[Vec<bool>]) -> Validation {
    let mut v = Validation::default();
    for (view, ((img, r), m)) in images.iter().zip(references).zip(masks).enumerate() {
        add_held_out(&mut v, view, img, r, m);
    }
    v
}

/// Adds view `view`'s held-out pixels to `v` (see [`held_out`]).
fn add_held_out(v: &mut Validation, view: usize, image: &Image, reference: &Image, mask: &[bool]) {
    for (_, ((x, y), _)) in image
        .rgb
        .iter()
        .zip(&reference.rgb)
        .zip(mask)
        .enumerate()
        .filter(|(i, (_, m))| **m && is_held_out((view, *i as u32)))
    {
        v.abs_error
            .push((x.as_dvec3() - y.as_dvec3()).abs().element_sum());
        v.reference_abs += y.as_dvec3().abs().element_sum();
    }
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
    fn larger_models_are_needed_unless_none_could_change_the_choice() {
        // Held-out relMAE (reference 100 over 8 pixels of equal error): floor 1.0%.
        let at = |e: f64| v(&[e * 100.0 / 8.0; 8]);
        let (floor, far, near, last) = (0.01, at(0.05), at(0.0115), at(0.0109));
        // A smaller model far off: a larger one scoring the floor would not change the choice.
        assert!(!larger_models_needed(&[&far, &last], floor));
        // A smaller one within the last one's bar (1.15% against 1.09% × 1.1): chosen now,
        // but a larger model at the floor would choose the last one; fit on.
        assert!(larger_models_needed(&[&near, &last], floor));
        // The last one off the floor by more than the tolerance: a larger one may win.
        assert!(larger_models_needed(&[&far, &at(0.0111)], floor));
        assert!(larger_models_needed(&[], floor));
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

    #[test]
    fn a_light_model_must_gain_more_than_the_tolerance() {
        // A bigger model consistently better by 1% or 3.5% of the error (far beyond one
        // standard error of the paired differences) loses to the smaller one; better by 20%,
        // it wins.
        let base: Vec<f64> = (0..8).map(|i| 1.0 + 0.1 * i as f64).collect();
        let by = |f: f64| -> Vec<f64> { base.iter().map(|b| b * f).collect() };
        for (gain, want) in [
            (0.99, "spheres:1"),
            (0.965, "spheres:1"),
            (0.80, "spheres:2"),
        ] {
            let s = choose_model(vec![
                ("spheres:2".into(), 14, v(&by(gain)), 0.0),
                ("spheres:1".into(), 7, v(&base), 0.0),
            ])
            .unwrap();
            assert_eq!(s.best, "spheres:2");
            assert_eq!(s.chosen, want, "gain {gain}: {s:?}");
        }
    }
}
