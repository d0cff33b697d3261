//! lightprobe: estimate the lighting of a 3D scene from images of it.
//!
//! A scene is a glTF 2.0 file plus a RON sidecar ([`scene`]). One path tracer ([`render`])
//! over one BVH ([`accel`]) renders reference images under sphere lights; [`metrics`] measures
//! photometric error; [`imageio`] reads and writes EXR/PNG. Data flows one way:
//! scene → core → outputs. The command-line tool in `src/main.rs` is a thin layer over this.

pub mod accel;
mod checked;
pub mod cleanup;
pub mod envmap;
pub mod error;
pub mod estimate;
pub mod experiment;
pub mod imageio;
pub mod math;
pub mod memory;
pub mod metrics;
pub mod noise;
pub mod output;
pub mod render;
pub mod sampling;
pub mod scene;

pub use error::{Error, Result};

/// The crate version, recorded in every output's metadata.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
