//! Memory figures of this process and machine, and the budget that every allocation sized by an
//! input is checked against before it is made (Linux reads /proc and the cgroup files;
//! elsewhere only a limit set with [`set_limit`] applies).
//!
//! The budget is the smallest headroom of: the limit the user set ([`set_limit`], the CLI's
//! `--memory-limit`, against this process's resident memory), the address-space and data
//! limits (`ulimit -v`, `ulimit -d`, against this process's virtual and data sizes), the
//! cgroup's `memory.max` (containers, Slurm jobs; every ancestor group counts) and the memory
//! the machine has available. A job that would pass it is refused with what needed how much,
//! before it allocates; an allocation failure is then a defect, never the expected outcome.

use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{Error, Result};

/// Peak resident memory of this process, bytes (Linux; 0 elsewhere).
pub fn peak_bytes() -> u64 {
    status_kib("VmHWM:").map_or(0, |kb| kb * 1024)
}

/// A `kB` figure of /proc/self/status.
fn status_kib(key: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    kib_field(&s, key)
}

/// The number after `key` on its line of a /proc text, in kB.
fn kib_field(text: &str, key: &str) -> Option<u64> {
    text.lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// The user's limit on this process's memory, bytes (0: none).
static LIMIT: AtomicU64 = AtomicU64::new(0);

/// Sets the limit on this process's resident memory that [`budget`] respects (the CLI's
/// `--memory-limit`); `None` removes it.
pub fn set_limit(bytes: Option<u64>) {
    LIMIT.store(bytes.unwrap_or(0), Ordering::Relaxed);
}

/// What bounds the memory budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bound {
    /// The limit set with [`set_limit`].
    Set,
    /// The address-space limit (RLIMIT_AS, `ulimit -v`).
    AddressSpace,
    /// The data-segment limit (RLIMIT_DATA, `ulimit -d`).
    Data,
    /// A cgroup's `memory.max` (a container's or a batch job's limit).
    Cgroup,
    /// The memory the machine has available (MemAvailable).
    Machine,
}

impl std::fmt::Display for Bound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Bound::Set => "under the memory limit set",
            Bound::AddressSpace => "under this process's address-space limit (ulimit -v)",
            Bound::Data => "under this process's data-size limit (ulimit -d)",
            Bound::Cgroup => "under the memory limit of this process's cgroup",
            Bound::Machine => "available on this machine",
        })
    }
}

/// How much more memory this process may use, and what says so.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// Bytes left.
    pub bytes: u64,
    /// The tightest of the limits.
    pub bound: Bound,
}

/// This process's memory budget now: the smallest headroom under every limit there is, or
/// `None` when nothing can be read (no /proc, no limit set).
pub fn budget() -> Option<Budget> {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let used = |key| kib_field(&status, key).map_or(0, |kb| kb * 1024);
    let mut heads = Vec::new();
    let set = LIMIT.load(Ordering::Relaxed);
    if set > 0 {
        heads.push((set.saturating_sub(used("VmRSS:")), Bound::Set));
    }
    if let Ok(limits) = std::fs::read_to_string("/proc/self/limits") {
        if let Some(max) = soft_limit(&limits, "Max address space") {
            heads.push((max.saturating_sub(used("VmSize:")), Bound::AddressSpace));
        }
        if let Some(max) = soft_limit(&limits, "Max data size") {
            heads.push((max.saturating_sub(used("VmData:")), Bound::Data));
        }
    }
    if let Some(free) = cgroup_headroom() {
        heads.push((free, Bound::Cgroup));
    }
    if let Some(avail) = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|m| kib_field(&m, "MemAvailable:"))
    {
        heads.push((avail * 1024, Bound::Machine));
    }
    heads
        .into_iter()
        .min_by_key(|&(bytes, _)| bytes)
        .map(|(bytes, bound)| Budget { bytes, bound })
}

/// Refuses, before allocating, work that needs `need` bytes more than nine tenths of the
/// [`budget`] (the rest is left for what the estimate does not count). `what` names the work
/// for the message.
pub fn reserve(need: u64, what: impl FnOnce() -> String) -> Result<()> {
    match budget() {
        Some(b) if need > b.bytes / 10 * 9 => Err(Error::Memory {
            what: what(),
            need,
            left: b.bytes,
            bound: b.bound.to_string(),
        }),
        _ => Ok(()),
    }
}

/// The soft limit, bytes, of a /proc/self/limits row (`None` when unlimited or unreadable).
fn soft_limit(limits: &str, row: &str) -> Option<u64> {
    limits
        .lines()
        .find(|l| l.starts_with(row))?
        .get(row.len()..)?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// The least headroom (`memory.max` − `memory.current`) of this process's cgroup and its
/// ancestors (cgroup v2; v1's memory controller at its root), or `None` without a limit.
fn cgroup_headroom() -> Option<u64> {
    let read = |p: &std::path::Path| std::fs::read_to_string(p).ok();
    let number = |s: Option<String>| s?.trim().parse::<u64>().ok();
    let mut best: Option<u64> = None;
    let mut take = |max: Option<u64>, current: Option<u64>| {
        if let Some(max) = max {
            let free = max.saturating_sub(current.unwrap_or(0));
            best = Some(best.map_or(free, |b| b.min(free)));
        }
    };
    let root = std::path::Path::new("/sys/fs/cgroup");
    if let Some(groups) = read(std::path::Path::new("/proc/self/cgroup")) {
        for line in groups.lines() {
            if let Some(path) = line.strip_prefix("0::") {
                // cgroup v2: the group and every ancestor up to the mount's root.
                let mut dir = root.join(path.trim_start_matches('/'));
                loop {
                    take(
                        number(read(&dir.join("memory.max"))),
                        number(read(&dir.join("memory.current"))),
                    );
                    if dir == root || !dir.pop() {
                        break;
                    }
                }
            }
        }
    }
    let v1 = root.join("memory");
    // v1 reports "no limit" as a huge number; anything beyond 2^60 bytes is no limit.
    take(
        number(read(&v1.join("memory.limit_in_bytes"))).filter(|&m| m < 1 << 60),
        number(read(&v1.join("memory.usage_in_bytes"))),
    );
    best
}

/// Reads an input file whole, after checking that it is a regular file (not a device, a pipe
/// or a folder, which have no size and may never end) and that its size fits the budget.
pub fn read_input(path: &std::path::Path) -> Result<Vec<u8>> {
    let meta = regular_file(path)?;
    reserve(meta.len(), || format!("{}: reading it", path.display()))?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // Read no more than the size checked, even if the file grows meanwhile.
    std::io::Read::read_to_end(
        &mut std::io::Read::take(
            std::fs::File::open(path).map_err(|e| Error::io(path, e))?,
            meta.len(),
        ),
        &mut bytes,
    )
    .map_err(|e| Error::io(path, e))?;
    Ok(bytes)
}

/// The metadata of `path`, which must be a regular file: a device or a pipe has no size and
/// may never end, so no input is read from one.
pub fn regular_file(path: &std::path::Path) -> Result<std::fs::Metadata> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(Error::file(
            path,
            "is not a regular file (a device, a pipe or a folder)",
        ));
    }
    Ok(meta)
}

/// [`read_input`] as UTF-8 text.
pub fn read_input_text(path: &std::path::Path) -> Result<String> {
    String::from_utf8(read_input(path)?).map_err(|_| Error::file(path, "is not UTF-8 text"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_rows_parse_and_unlimited_is_none() {
        let limits = "Limit                     Soft Limit           Hard Limit           Units     \n\
            Max data size             unlimited            unlimited            bytes     \n\
            Max address space         1610612736           unlimited            bytes     \n";
        assert_eq!(soft_limit(limits, "Max address space"), Some(1_610_612_736));
        assert_eq!(soft_limit(limits, "Max data size"), None);
        assert_eq!(soft_limit(limits, "Max stack size"), None);
    }

    #[test]
    fn a_set_limit_bounds_the_budget_and_refuses_beyond_it() {
        set_limit(Some(1 << 40));
        let before = budget().expect("a limit is set");
        assert!(before.bytes < 1 << 40);
        // 2^40 bytes minus this test process's resident memory, unless something is tighter.
        if before.bound == Bound::Set {
            assert!(before.bytes > (1 << 40) - (1 << 32));
        }
        let err = reserve(1 << 41, || "a test buffer".into()).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("a test buffer") && text.contains("2048.0 GiB"),
            "{text}"
        );
        assert!(reserve(1 << 20, || "a small buffer".into()).is_ok());
        set_limit(None);
    }
}
