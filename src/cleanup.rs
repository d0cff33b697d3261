//! Files this process must not leave behind if it is interrupted: the temporaries of atomic
//! writes and the lock of an output folder. The CLI's signal handler calls [`remove_all`]
//! before it exits; normal paths unregister their files as they rename or remove them.
//! Temporaries carry the writer's process id in their name, so those of a process that died
//! without cleaning up (SIGKILL, power loss) are found by [`remove_stale`].

use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// A list of files to remove on interruption.
struct Registry(Mutex<Vec<PathBuf>>);

static FILES: Registry = Registry(Mutex::new(Vec::new()));

impl Registry {
    fn register(&self, path: &Path) {
        if let Ok(mut files) = self.0.lock() {
            files.push(path.to_path_buf());
        }
    }

    fn unregister(&self, path: &Path) {
        if let Ok(mut files) = self.0.lock()
            && let Some(i) = files.iter().rposition(|p| p == path)
        {
            files.swap_remove(i);
        }
    }

    fn remove_all(&self) -> usize {
        // A thread holding the lock is adding or dropping one path: waiting for it is brief.
        let files = std::mem::take(&mut *self.0.lock().unwrap_or_else(|p| p.into_inner()));
        // Newest first, so a folder goes after the files registered in it; a folder is removed
        // only if empty.
        files
            .iter()
            .rev()
            .filter(|p| std::fs::remove_file(p).is_ok() || std::fs::remove_dir(p).is_ok())
            .count()
    }
}

/// Registers `path` to be removed if the process is interrupted (a folder: if it is empty).
pub fn register(path: &Path) {
    FILES.register(path);
}

/// Unregisters `path` (it was renamed into place or removed).
pub fn unregister(path: &Path) {
    FILES.unregister(path);
}

/// Removes every registered file (for a signal handler, which runs on its own thread).
/// Returns how many were removed.
pub fn remove_all() -> usize {
    FILES.remove_all()
}

/// The name of the temporary an atomic write of `name` uses in this process.
pub fn temporary_name(name: &str) -> String {
    format!(".{name}.{}.tmp", std::process::id())
}

/// Removes, in `dir` and its subfolders down to `depth` levels, the temporaries
/// ([`temporary_name`]) of processes that no longer run (on Linux, where that can be told;
/// elsewhere nothing is removed). Returns how many were removed.
pub fn remove_stale(dir: &Path, depth: usize) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let path = entry.path();
        let Ok(kind) = entry.file_type() else {
            continue;
        };
        if kind.is_dir() && depth > 0 {
            removed += remove_stale(&path, depth - 1);
        } else if kind.is_file()
            && is_stale(&entry.file_name().to_string_lossy())
            && std::fs::remove_file(&path).is_ok()
        {
            removed += 1;
        }
    }
    removed
}

/// Removes the temporaries of `path` ([`temporary_name`]) that processes which no longer run
/// left beside it. Returns how many were removed.
pub fn remove_stale_of(path: &Path) -> usize {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
        return 0;
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let prefix = format!(".{}.", name.to_string_lossy());
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.starts_with(&prefix) && is_stale(&n) && e.file_type().is_ok_and(|t| t.is_file())
        })
        .filter(|e| std::fs::remove_file(e.path()).is_ok())
        .count()
}

/// Whether `file_name` is a temporary ([`temporary_name`]) of a process that has ended.
fn is_stale(file_name: &str) -> bool {
    temporary_pid(file_name).is_some_and(|pid| pid != std::process::id() && process_is_gone(pid))
}

/// The process id in a temporary's name `.NAME.PID.tmp`.
fn temporary_pid(file_name: &str) -> Option<u32> {
    let rest = file_name.strip_prefix('.')?.strip_suffix(".tmp")?;
    let (_, pid) = rest.rsplit_once('.')?;
    pid.parse().ok()
}

/// Whether process `pid` has certainly ended (Linux: no /proc entry).
pub fn process_is_gone(pid: u32) -> bool {
    Path::new("/proc/self").exists() && !Path::new(&format!("/proc/{pid}")).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn temporary_names_carry_the_pid() {
        let name = temporary_name("envmap.exr");
        assert_eq!(temporary_pid(&name), Some(std::process::id()));
        assert_eq!(temporary_pid(".envmap.exr.tmp"), None);
        assert_eq!(temporary_pid("envmap.exr"), None);
    }

    #[test]
    fn stale_temporaries_go_and_live_ones_stay() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("estimate");
        std::fs::create_dir(&sub).unwrap();
        // PIDs above the kernel's maximum (2^22) never run.
        let dead = sub.join(".view.exr.4194305.tmp");
        let mine = dir.path().join(temporary_name("envmap.exr"));
        let other = dir.path().join("envmap.exr");
        for p in [&dead, &mine, &other] {
            std::fs::write(p, b"x").unwrap();
        }
        if Path::new("/proc/self").exists() {
            assert_eq!(remove_stale(dir.path(), 1), 1);
            assert!(!dead.exists());
        }
        assert!(mine.exists() && other.exists());
    }

    #[test]
    fn registered_files_are_removed_once() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        std::fs::write(&a, b"x").unwrap();
        std::fs::write(&b, b"x").unwrap();
        let registry = Registry(Mutex::new(Vec::new()));
        registry.register(&a);
        registry.register(&b);
        registry.unregister(&b);
        assert_eq!(registry.remove_all(), 1);
        assert!(!a.exists() && b.exists());
        assert_eq!(registry.remove_all(), 0);
    }
}
