//! Estimating the environment map that best explains reference images.
//!
//! The one path tracer estimates the transport T ([`transport`]); solvers ([`nnls`]) fit the
//! per-cell radiance λ ≥ 0 to the references, per colour channel, over the masked pixels of
//! every view jointly.

pub mod nnls;
pub mod transport;
