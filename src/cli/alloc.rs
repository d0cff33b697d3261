//! The binary's allocator: the system's, except that a failed allocation ends the process
//! with one line and exit status 1 (and this process's temporary files removed) instead of
//! Rust's default abort. Work sized by an input is checked against the memory budget before
//! it starts (`lightprobe::memory`); this is the net under what the checks cannot foresee,
//! such as the address space threads and allocator arenas reserve under `ulimit -v`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};

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

static FAILING: AtomicBool = AtomicBool::new(false);

#[cold]
fn out_of_memory(size: usize) -> ! {
    // The report below allocates a little (a path, a message); if even that fails, say the
    // least and go.
    if FAILING.swap(true, Ordering::SeqCst) {
        let _ = std::io::stderr().write_all(b"lightprobe: error: out of memory\n");
        std::process::exit(1);
    }
    lightprobe::cleanup::remove_all();
    let budget = lightprobe::memory::budget().map_or(String::new(), |b| {
        format!(
            "; {:.1} GiB is left {}",
            b.bytes as f64 / (1u64 << 30) as f64,
            b.bound
        )
    });
    let _ = writeln!(
        std::io::stderr(),
        "lightprobe: error: out of memory: {:.1} MiB more could not be allocated{budget}. \
         Use fewer rings, views or pixels, or raise the limit",
        size as f64 / (1u64 << 20) as f64
    );
    std::process::exit(1);
}
