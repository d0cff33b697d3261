//! `export-envmap` and `import-envmap`: ring envmaps to and from lat-long OpenEXR.

use std::path::PathBuf;

use lightprobe::envmap::latlong::{self, Filter, Target};
use lightprobe::envmap::{Envmap, MAX_RINGS};
use lightprobe::imageio;

use super::{FilterArg, TargetArg, outln, say};

#[derive(clap::Args)]
pub struct ExportArgs {
    /// The ring envmap (envmap.ron).
    envmap: PathBuf,
    /// Output lat-long EXR.
    #[arg(long, short)]
    out: PathBuf,
    /// Image width in pixels (height = width / 2), 8..=16384. Renderers interpolate between
    /// pixels, which blurs cell edges by half a pixel: measured in Mitsuba, the worst cell
    /// (a pole cap of 9 rings) loses 2.7% of its power at 1024 and 0.7% at 4096.
    #[arg(long, default_value_t = 4096)]
    width: u32,
    /// Whose lat-long convention to write.
    #[arg(long, value_enum, default_value_t = TargetArg::Mitsuba)]
    target: TargetArg,
    /// `box`: the cell under each pixel centre (import-envmap gives the cells back exactly);
    /// `smooth`: interpolated between grid points.
    #[arg(long, value_enum, default_value_t = FilterArg::Box)]
    filter: FilterArg,
}

#[derive(clap::Args)]
pub struct ImportArgs {
    /// A lat-long map: OpenEXR (RGB or RGBA) or Radiance .hdr.
    image: PathBuf,
    /// Ring count of the grid to average onto (1..=1000).
    #[arg(long)]
    rings: u32,
    /// Output envmap.ron.
    #[arg(long, short)]
    out: PathBuf,
    /// Whose lat-long convention the image follows.
    #[arg(long, value_enum, default_value_t = TargetArg::Mitsuba)]
    target: TargetArg,
}

pub fn export(a: ExportArgs) -> anyhow::Result<()> {
    let (target, filter): (Target, Filter) = (a.target.into(), a.filter.into());
    if !(8..=16384).contains(&a.width) {
        anyhow::bail!(
            "--width must be between 8 and 16384 pixels, got {}",
            a.width
        );
    }
    let env = Envmap::load(&a.envmap)?;
    if same_file(&a.envmap, &a.out) {
        anyhow::bail!(
            "{}: is the input; --out must name another file",
            a.out.display()
        );
    }
    // The image (f32 RGB) and the encoder's copy of it.
    let pixels = a.width as u64 * (a.width as u64 / 2);
    super::check_memory(
        pixels * 24,
        || format!("a {}×{} lat-long image", a.width, a.width / 2),
        "; use a smaller --width",
    )?;
    let img = latlong::export(&env, target, filter, a.width);
    imageio::write_latlong_exr(&a.out, &img)?;
    outln!(
        "{}: {}×{} lat-long ({:?}, {:?} filter) of {} rings / {} cells",
        a.out.display(),
        img.width,
        img.height,
        target,
        filter,
        env.grid.rings(),
        env.grid.cell_count()
    )?;
    Ok(())
}

pub fn import(a: ImportArgs) -> anyhow::Result<()> {
    let target: Target = a.target.into();
    if !(1..=MAX_RINGS).contains(&a.rings) {
        anyhow::bail!(
            "--rings must be between 1 and {}, got {}",
            MAX_RINGS,
            a.rings
        );
    }
    if same_file(&a.image, &a.out) {
        anyhow::bail!(
            "{}: is the input; --out must name another file",
            a.out.display()
        );
    }
    let img = imageio::read_latlong(&a.image)?;
    if img.width != 2 * img.height {
        // Any size is read as lat-long, but one that is not 2:1 is probably something else.
        say(&format!(
            "lightprobe: warning: {} is {}×{}, not 2:1 like a lat-long map; reading it as one anyway",
            a.image.display(),
            img.width,
            img.height
        ));
    }
    let env =
        latlong::import(&img, target, a.rings).map_err(|m| lightprobe::Error::file(&a.image, m))?;
    env.save(&a.out)?;
    outln!(
        "{}: {} rings / {} cells from {}×{} {}",
        a.out.display(),
        a.rings,
        env.grid.cell_count(),
        img.width,
        img.height,
        a.image.display()
    )?;
    Ok(())
}

/// Whether `a` and `b` name the same existing file.
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y)
}
