//! The binary's allocator (declared by `main.rs`, not part of the library): mimalloc, told to
//! give freed arena memory back to the system at once. Besides `store/mapping.rs`, the only
//! module with an `unsafe` block: one call into mimalloc's C API.
#![allow(unsafe_code)]

// The server allocates small, short-lived buffers per request (headers, paths, response
// parts) from every worker thread; mimalloc's thread-local free lists serve that pattern with
// less locking than glibc's malloc.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// `mi_option_arena_purge_mult` in mimalloc 3's `mi_option_e` (the version libmimalloc-sys
/// builds without its `v2` feature); the crate's bindings do not name it.
const MI_OPTION_ARENA_PURGE_MULT: libmimalloc_sys::mi_option_t = 24;

/// Large bodies (a 64 MiB level, a raw batch) live in mimalloc's arenas. Freed, mimalloc keeps
/// such memory committed for its purge delay (1 s) times the arena multiplier (1), and purges
/// it only when the thread that owns it allocates again: a server whose CPU threads go idle
/// after building a few large answers kept them resident, several times past the bound the
/// response budget promises (the memory-bound tests catch it). A multiplier of 0 purges arenas
/// when their memory is freed; small pages keep their delay. It costs the per-request path a
/// few percent of brick requests/s (docs/benchmarks.md), which the bound is worth.
/// `MIMALLOC_ARENA_PURGE_MULT` in the environment still decides, when set.
pub(crate) fn purge_freed_arenas_at_once() {
    if std::env::var_os("MIMALLOC_ARENA_PURGE_MULT").is_none() {
        // SAFETY: mi_option_set stores an option's value; mimalloc allows it at any time.
        unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_ARENA_PURGE_MULT, 0) };
    }
}
