//! The binary's allocator: the system's, except that a failed allocation ends the process
//! with one line and exit status 1 (and this process's temporary files removed) instead of
//! Rust's default abort. Work sized by an input is checked against the memory budget before
//! it starts (`lightprobe::memory`); this is the net under what the checks cannot foresee,
//! such as the address space threads and allocator arenas reserve under `ulimit -v`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// [`System`], with a clean exit on failure.
pub struct Guarded;

// SAFETY: every method forwards to `System` with the caller's arguments unchanged, so it
// upholds `GlobalAlloc`'s contract exactly as `System` does; on failure it never returns.
unsafe impl GlobalAlloc for Guarded {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        checked(unsafe { System.alloc(layout) }, layout.size())
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        checked(unsafe { System.alloc_zeroed(layout) }, layout.size())
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        checked(unsafe { System.realloc(ptr, layout, new_size) }, new_size)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged (see the impl).
        unsafe { System.dealloc(ptr, layout) }
    }
}

/// `ptr`, or the end of the process if it is null.
#[inline]
fn checked(ptr: *mut u8, size: usize) -> *mut u8 {
    if ptr.is_null() {
        out_of_memory(size);
    }
    ptr
}

/// The thread reporting the failure (its [`thread_mark`]; 0: none yet), and whether the
/// report is written.
static REPORTER: AtomicUsize = AtomicUsize::new(0);
static REPORTED: AtomicBool = AtomicBool::new(false);

thread_local! {
    static MARK: u8 = const { 0 };
}

/// A number unique to the calling thread, found without allocating.
fn thread_mark() -> usize {
    MARK.with(|m| m as *const u8 as usize)
}

#[cold]
fn out_of_memory(size: usize) -> ! {
    let me = thread_mark();
    match REPORTER.compare_exchange(0, me, Ordering::SeqCst, Ordering::SeqCst) {
        Ok(_) => {}
        // The report itself ran out: say the least and go.
        Err(reporter) if reporter == me => {
            if !REPORTED.swap(true, Ordering::SeqCst) {
                let _ = std::io::stderr().write_all(b"lightprobe: error: out of memory\n");
            }
            std::process::exit(1);
        }
        // Another thread reports and ends the process; wait for it (one error line).
        Err(_) => loop {
            std::thread::sleep(std::time::Duration::from_secs(1));
            if REPORTED.load(Ordering::SeqCst) {
                std::process::exit(1);
            }
        },
    }
    lightprobe::cleanup::remove_all();
    let budget = lightprobe::memory::budget().map_or(String::new(), |b| {
        format!("; {} is left {}", lightprobe::error::size(b.bytes), b.bound)
    });
    let _ = writeln!(
        std::io::stderr(),
        "lightprobe: error: out of memory: {} more could not be allocated{budget}; \
         reduce the work (rings, views, image or file sizes) or raise the limit",
        lightprobe::error::size(size as u64)
    );
    REPORTED.store(true, Ordering::SeqCst);
    std::process::exit(1);
}
