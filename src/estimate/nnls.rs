//! Non-negative least squares on the normal equations: minimise `½xᵀGx − bᵀx` subject to
//! `x ≥ 0`, which is `min ‖Tx − y‖²` with `G = TᵀT`, `b = Tᵀy`. Solved exactly by the active-set
//! method of Lawson & Hanson in Bro & de Jong's Gram form (FNNLS); the answer satisfies the KKT
//! conditions to a stated tolerance. Also the paper's baseline: projected gradient descent
//! with a backtracking (Armijo) line search.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::ldlt::update;
use faer::linalg::triangular_solve::{
    solve_unit_lower_triangular_in_place, solve_unit_upper_triangular_in_place,
};
use faer::{Mat, Par};
use std::time::{Duration, Instant};

/// The outcome of a solve.
#[derive(Debug, Clone)]
pub struct Solution {
    pub x: Vec<f64>,
    pub iterations: usize,
    /// Largest KKT violation relative to `max|b|`: `max(−x_i, w_i for x_i = 0, |w_i| for
    /// x_i > 0)` with `w = b − Gx`.
    pub kkt_violation: f64,
    pub converged: bool,
    /// Objective `½xᵀGx − bᵀx` after each iteration.
    pub objective: Vec<f64>,
}

/// `½xᵀGx − bᵀx` for a dense row-major `n × n` G.
pub fn objective(g: &[f64], b: &[f64], x: &[f64]) -> f64 {
    let gx = matvec(g, x);
    0.5 * dot(x, &gx) - dot(b, x)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn matvec(g: &[f64], x: &[f64]) -> Vec<f64> {
    let n = x.len();
    g.chunks_exact(n).map(|row| dot(row, x)).collect()
}

/// The relative KKT violation of `x` (see [`Solution::kkt_violation`]).
pub fn kkt_violation(g: &[f64], b: &[f64], x: &[f64]) -> f64 {
    let scale = b
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(f64::MIN_POSITIVE);
    let gx = matvec(g, x);
    let mut worst = 0.0f64;
    for i in 0..x.len() {
        let w = b[i] - gx[i];
        let v = if x[i] < 0.0 {
            -x[i] * scale
        } else if x[i] == 0.0 {
            w.max(0.0)
        } else {
            w.abs()
        };
        worst = worst.max(v);
    }
    worst / scale
}

/// The passive set's Gram `G_PP`, plus a tiny ridge for numerical safety, as a factor
/// `L D Lᵀ` kept in the order its variables were freed. Freeing a variable appends a row (one
/// triangular solve); fixing variables at zero deletes their rows and columns (faer's
/// rank-update deletion). Each is O(k²) for k passive variables, where factoring the set
/// again at every step of the active-set method costs O(k³).
struct PassiveFactor {
    /// `n × n`; the top-left `k × k` block is the factor: unit L strictly below the
    /// diagonal, D on it.
    ld: Mat<f64>,
    /// The passive variables, in the factor's order.
    order: Vec<usize>,
    ridge: f64,
}

impl PassiveFactor {
    fn new(n: usize, ridge: f64) -> Self {
        PassiveFactor {
            ld: Mat::zeros(n, n),
            order: Vec::new(),
            ridge,
        }
    }

    /// Frees variable `j`. False (the factor unchanged) when `G_PP` with it is not
    /// numerically positive definite: its column depends on the others.
    fn push(&mut self, g: &[f64], j: usize) -> bool {
        let (n, k) = (self.ld.nrows(), self.order.len());
        let mut z = Mat::from_fn(k, 1, |r, _| g[self.order[r] * n + j]);
        solve_unit_lower_triangular_in_place(
            self.ld.as_ref().submatrix(0, 0, k, k),
            z.as_mut(),
            Par::Seq,
        );
        let mut d = g[j * n + j] + self.ridge;
        for r in 0..k {
            let l = z[(r, 0)] / self.ld[(r, r)];
            d -= z[(r, 0)] * l;
            self.ld[(k, r)] = l;
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        self.ld[(k, k)] = d;
        self.order.push(j);
        true
    }

    /// Fixes the variables `gone` (all passive) at zero.
    fn remove(&mut self, gone: &[usize]) {
        let k = self.order.len();
        let mut at: Vec<usize> = gone
            .iter()
            .map(|j| self.order.iter().position(|v| v == j).expect("passive"))
            .collect();
        let mut buf = MemBuffer::new(update::delete_rows_and_cols_clobber_scratch::<f64>(
            k,
            at.len(),
        ));
        update::delete_rows_and_cols_clobber(
            self.ld.as_mut().submatrix_mut(0, 0, k, k),
            &mut at,
            Par::Seq,
            MemStack::new(&mut buf),
        );
        self.order.retain(|v| !gone.contains(v));
    }

    /// The least-squares solution on the passive set, `G_PP s = b_P`, in the factor's order;
    /// `None` if not finite.
    fn solve(&self, b: &[f64]) -> Option<Vec<f64>> {
        let k = self.order.len();
        let l = self.ld.as_ref().submatrix(0, 0, k, k);
        let mut s = Mat::from_fn(k, 1, |r, _| b[self.order[r]]);
        solve_unit_lower_triangular_in_place(l, s.as_mut(), Par::Seq);
        for r in 0..k {
            s[(r, 0)] /= l[(r, r)];
        }
        solve_unit_upper_triangular_in_place(l.transpose(), s.as_mut(), Par::Seq);
        let s: Vec<f64> = (0..k).map(|r| s[(r, 0)]).collect();
        s.iter().all(|v| v.is_finite()).then_some(s)
    }
}

/// FNNLS: exact NNLS by active sets. `tol` is relative to `max|b|`; stops after `max_iter`
/// outer iterations or `time_limit`, reporting `converged = false`.
pub fn nnls(g: &[f64], b: &[f64], tol: f64, max_iter: usize, time_limit: Duration) -> Solution {
    let n = b.len();
    assert_eq!(g.len(), n * n, "G must be n × n");
    let start = Instant::now();
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut x = vec![0.0; n];
    let mut objective_trace = Vec::new();
    let mut iterations = 0;
    let mut converged = false;
    if scale == 0.0 {
        return Solution {
            x,
            iterations,
            kkt_violation: 0.0,
            converged: true,
            objective: vec![0.0],
        };
    }
    let tol_abs = tol * scale;
    // The ridge scales with G's largest diagonal (it scaled with the passive set's when that
    // set was factored afresh at each step).
    let max_diag = (0..n).map(|i| g[i * n + i]).fold(0.0, f64::max);
    let mut factor = PassiveFactor::new(n, 1e-13 * max_diag);
    let mut passive = vec![false; n];
    // Variables whose column proved numerically dependent on the passive set's: not tried
    // again until a variable of that set is fixed at zero.
    let mut dependent = vec![false; n];
    // G x, kept with x (zero off the passive set, so a sum over its rows).
    let mut gx = vec![0.0; n];
    loop {
        // The most promising variable not yet free.
        let candidate = (0..n)
            .filter(|&i| !passive[i] && !dependent[i])
            .max_by(|&i, &j| (b[i] - gx[i]).total_cmp(&(b[j] - gx[j])));
        let Some(j) = candidate.filter(|&j| b[j] - gx[j] > tol_abs) else {
            // Optimal unless a dependent variable would still lower the objective.
            converged = (0..n).all(|i| !dependent[i] || b[i] - gx[i] <= tol_abs);
            break;
        };
        if iterations >= max_iter || start.elapsed() > time_limit {
            break;
        }
        iterations += 1;
        if !factor.push(g, j) {
            dependent[j] = true;
            continue;
        }
        passive[j] = true;
        // Inner loop: keep the passive solution feasible.
        let mut broken = false;
        loop {
            let Some(s) = factor.solve(b) else {
                if passive[j] {
                    factor.remove(&[j]);
                    passive[j] = false;
                    x[j] = 0.0;
                    dependent[j] = true;
                } else {
                    // Not finite without the newest variable either: stop, not converged.
                    broken = true;
                }
                break;
            };
            if s.iter().all(|&v| v > 0.0) {
                for (k, &i) in factor.order.iter().enumerate() {
                    x[i] = s[k];
                }
                break;
            }
            // Step from x toward s as far as feasibility allows, then fix the variables
            // that hit zero.
            let mut alpha = 1.0f64;
            for (k, &i) in factor.order.iter().enumerate() {
                if s[k] <= 0.0 {
                    let a = x[i] / (x[i] - s[k]);
                    if a < alpha {
                        alpha = a;
                    }
                }
            }
            let mut gone = Vec::new();
            for (k, &i) in factor.order.iter().enumerate() {
                x[i] += alpha * (s[k] - x[i]);
                if x[i] <= 1e-15 * scale.max(1.0)
                    || (s[k] <= 0.0 && (x[i] - 0.0).abs() <= f64::EPSILON * x[i].abs().max(1.0))
                {
                    x[i] = 0.0;
                    passive[i] = false;
                    gone.push(i);
                }
            }
            factor.remove(&gone);
            if !gone.is_empty() {
                // A column dependent on the variables just fixed may not be on the rest.
                dependent.fill(false);
            }
            if factor.order.is_empty() {
                break;
            }
        }
        if broken {
            break;
        }
        gx.fill(0.0);
        for &i in &factor.order {
            let row = &g[i * n..(i + 1) * n];
            gx.iter_mut().zip(row).for_each(|(a, &v)| *a += x[i] * v);
        }
        objective_trace.push(0.5 * dot(&x, &gx) - dot(b, &x));
    }
    let kkt = kkt_violation(g, b, &x);
    Solution {
        x,
        iterations,
        kkt_violation: kkt,
        converged,
        objective: objective_trace,
    }
}

/// The paper's solver: projected gradient descent with a backtracking (Armijo) line search
/// from `x0`, stopped when the projected gradient's norm falls below `tol` × its initial value
/// (the first-order optimality of the Wolfe conditions), or after `max_iter` / `time_limit`.
pub fn projected_gradient(
    g: &[f64],
    b: &[f64],
    x0: &[f64],
    tol: f64,
    max_iter: usize,
    time_limit: Duration,
) -> Solution {
    let n = b.len();
    let start = Instant::now();
    let mut x: Vec<f64> = x0.iter().map(|v| v.max(0.0)).collect();
    let proj_grad_norm = |x: &[f64], grad: &[f64]| -> f64 {
        x.iter()
            .zip(grad)
            .map(|(&xi, &gi)| if xi > 0.0 || gi < 0.0 { gi * gi } else { 0.0 })
            .sum::<f64>()
            .sqrt()
    };
    let mut grad: Vec<f64> = matvec(g, &x)
        .iter()
        .zip(b)
        .map(|(gx, bi)| gx - bi)
        .collect();
    let mut f = objective(g, b, &x);
    let g0 = proj_grad_norm(&x, &grad).max(f64::MIN_POSITIVE);
    // Initial step: 1 / (an upper bound of G's largest eigenvalue: the max row sum).
    let lipschitz = g
        .chunks_exact(n)
        .map(|r| r.iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let mut step = 1.0 / lipschitz;
    let mut trace = vec![f];
    let mut iterations = 0;
    let mut converged = false;
    while iterations < max_iter && start.elapsed() < time_limit {
        if proj_grad_norm(&x, &grad) <= tol * g0 {
            converged = true;
            break;
        }
        iterations += 1;
        step *= 2.0; // let the step grow again after easy iterations
        loop {
            let xn: Vec<f64> = x
                .iter()
                .zip(&grad)
                .map(|(xi, gi)| (xi - step * gi).max(0.0))
                .collect();
            let fn_ = objective(g, b, &xn);
            let d: Vec<f64> = xn.iter().zip(&x).map(|(a, b)| a - b).collect();
            // Armijo sufficient decrease for projected steps.
            if fn_ <= f + dot(&grad, &d) + dot(&d, &d) / (2.0 * step) || step < 1e-300 {
                x = xn;
                f = fn_;
                break;
            }
            step *= 0.5;
        }
        grad = matvec(g, &x)
            .iter()
            .zip(b)
            .map(|(gx, bi)| gx - bi)
            .collect();
        trace.push(f);
    }
    let kkt = kkt_violation(g, b, &x);
    Solution {
        x,
        iterations,
        kkt_violation: kkt,
        converged,
        objective: trace,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Rng;

    /// A random least-squares problem: T is m × n, y = T x_true + noise, with some x_true = 0.
    fn problem(m: usize, n: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut r = Rng::new(seed);
        let t: Vec<f64> = (0..m * n).map(|_| r.next_f32() as f64).collect();
        let x_true: Vec<f64> = (0..n)
            .map(|i| {
                if i % 3 == 0 {
                    0.0
                } else {
                    r.next_f32() as f64 * 2.0
                }
            })
            .collect();
        let y: Vec<f64> = (0..m)
            .map(|i| dot(&t[i * n..(i + 1) * n], &x_true) + (r.next_f32() as f64 - 0.5) * 0.3)
            .collect();
        let mut g = vec![0.0; n * n];
        let mut b = vec![0.0; n];
        for i in 0..m {
            let row = &t[i * n..(i + 1) * n];
            for a in 0..n {
                b[a] += row[a] * y[i];
                for c in 0..n {
                    g[a * n + c] += row[a] * row[c];
                }
            }
        }
        (g, b, x_true)
    }

    #[test]
    fn nnls_satisfies_kkt_and_recovers_noise_free_solutions() {
        for seed in 0..5 {
            let (g, b, _) = problem(60, 20, seed);
            let s = nnls(&g, &b, 1e-10, 1000, Duration::from_secs(10));
            assert!(
                s.converged && s.kkt_violation < 1e-8,
                "seed {seed}: {}",
                s.kkt_violation
            );
            assert!(s.x.iter().all(|&v| v >= 0.0));
            // Some constraints are active (the noisy data pull some variables below zero).
            assert!(
                s.objective
                    .windows(2)
                    .all(|w| w[1] <= w[0] + 1e-9 * w[0].abs().max(1.0))
            );
        }
        // Without noise and with a full-rank T the truth is recovered.
        let n = 8;
        let mut r = Rng::new(9);
        let t: Vec<f64> = (0..40 * n).map(|_| r.next_f32() as f64).collect();
        let x_true: Vec<f64> = (0..n)
            .map(|i| if i % 2 == 0 { 0.0 } else { 1.0 + i as f64 })
            .collect();
        let mut g = vec![0.0; n * n];
        let mut b = vec![0.0; n];
        for i in 0..40 {
            let row = &t[i * n..(i + 1) * n];
            let y = dot(row, &x_true);
            for a in 0..n {
                b[a] += row[a] * y;
                for c in 0..n {
                    g[a * n + c] += row[a] * row[c];
                }
            }
        }
        let s = nnls(&g, &b, 1e-12, 100, Duration::from_secs(10));
        for (a, e) in s.x.iter().zip(&x_true) {
            assert!((a - e).abs() < 1e-8, "{a} vs {e}");
        }
    }

    #[test]
    fn nnls_stays_exact_through_many_freed_and_fixed_variables() {
        // Wide problems with noise: the active set gains and loses many variables, each a
        // row appended to or deleted from the passive factor.
        for seed in 10..14 {
            let (g, b, _) = problem(120, 60, seed);
            let s = nnls(&g, &b, 1e-10, 10_000, Duration::from_secs(10));
            assert!(s.converged && s.kkt_violation < 1e-8, "seed {seed}");
            let free = s.x.iter().filter(|&&v| v > 0.0).count();
            assert!(free > 5 && free < 60, "seed {seed}: {free} free");
        }
        // Two identical columns: the second is dependent on the first once that is free,
        // and the optimum is still found.
        let (g0, b0, _) = problem(40, 6, 5);
        let n = 7;
        let at = |i: usize| if i == 6 { 2 } else { i };
        let g: Vec<f64> = (0..n * n).map(|k| g0[at(k / n) * 6 + at(k % n)]).collect();
        let b: Vec<f64> = (0..n).map(|i| b0[at(i)]).collect();
        let s = nnls(&g, &b, 1e-10, 1000, Duration::from_secs(10));
        let exact = nnls(&g0, &b0, 1e-10, 1000, Duration::from_secs(10));
        let (f, fe) = (objective(&g, &b, &s.x), objective(&g0, &b0, &exact.x));
        assert!((f - fe).abs() <= 1e-9 * fe.abs(), "{f} vs {fe}");
    }

    #[test]
    fn the_passive_factor_solves_after_rows_are_added_and_deleted() {
        let (g, b, _) = problem(40, 8, 21);
        let n = 8;
        let mut f = PassiveFactor::new(n, 0.0);
        for j in [3, 0, 6, 1, 7, 2] {
            assert!(f.push(&g, j));
        }
        f.remove(&[0, 7]);
        assert!(f.push(&g, 5));
        f.remove(&[3]);
        assert_eq!(f.order, vec![6, 1, 2, 5]);
        // G_PP s = b_P on the set left.
        let s = f.solve(&b).unwrap();
        for (r, &i) in f.order.iter().enumerate() {
            let lhs: f64 = f.order.iter().zip(&s).map(|(&j, v)| g[i * n + j] * v).sum();
            assert!((lhs - b[i]).abs() < 1e-9 * b[i].abs().max(1.0), "row {r}");
        }
        // An indefinite Gram (a noisy cross product can be one): the third column's pivot
        // is negative, it is refused and the factor is left as it was.
        let g = [1.0, 0.5, 0.9, 0.5, 1.0, 0.9, 0.9, 0.9, 1.0];
        let mut f = PassiveFactor::new(3, 0.0);
        assert!(f.push(&g, 0) && f.push(&g, 1));
        assert!(!f.push(&g, 2));
        assert_eq!(f.order, vec![0, 1]);
        let s = f.solve(&[1.0, 1.0, 0.0]).unwrap();
        assert!((s[0] - 2.0 / 3.0).abs() < 1e-12 && (s[1] - 2.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn nnls_beats_every_feasible_perturbation() {
        let (g, b, _) = problem(50, 12, 3);
        let s = nnls(&g, &b, 1e-10, 1000, Duration::from_secs(10));
        let f = objective(&g, &b, &s.x);
        let mut r = Rng::new(4);
        for _ in 0..500 {
            let y: Vec<f64> =
                s.x.iter()
                    .map(|&v| (v + (r.next_f32() as f64 - 0.5) * 0.01).max(0.0))
                    .collect();
            assert!(objective(&g, &b, &y) >= f - 1e-9 * f.abs());
        }
    }

    #[test]
    fn gradient_descent_reaches_the_nnls_optimum() {
        let (g, b, _) = problem(80, 10, 7);
        let exact = nnls(&g, &b, 1e-12, 1000, Duration::from_secs(10));
        // Gradient descent converges linearly at a rate set by G's conditioning (all-positive
        // random T is ill-conditioned): ask for 1e-6 of the initial projected gradient.
        let pg = projected_gradient(&g, &b, &[0.0; 10], 1e-6, 1_000_000, Duration::from_secs(60));
        assert!(pg.converged, "{} iterations", pg.iterations);
        let (fe, fp) = (objective(&g, &b, &exact.x), objective(&g, &b, &pg.x));
        assert!((fp - fe).abs() <= 1e-6 * fe.abs(), "{fp} vs {fe}");
        assert!(pg.kkt_violation < 1e-4, "{}", pg.kkt_violation);
        assert!(
            pg.objective.windows(2).all(|w| w[1] <= w[0]),
            "monotone descent"
        );
    }

    #[test]
    fn zero_data_gives_zero() {
        let s = nnls(
            &[1.0, 0.0, 0.0, 1.0],
            &[0.0, 0.0],
            1e-10,
            10,
            Duration::from_secs(1),
        );
        assert_eq!(s.x, vec![0.0, 0.0]);
        assert!(s.converged);
    }
}
