//! Isovox's own tools, kept out of the libraries so that their users carry only what they
//! need: the benchmarks behind the figures in docs/benchmarks.md (`isovox-bench`) and the load
//! tester (`isovox-load`). Not published.
//!
//! Layout:
//! - [`bench`]: `isovox-bench store|icvg|mesh|http|edits|memory|voxelize`, each a module that
//!   measures and prints Markdown tables, next to the papers' figures and the peers run in the
//!   same process.
//! - [`load`]: simulated viewers and editors against a server, through the typed client.
//! - [`args`]: command-line values the benchmarks parse.
//! - [`progress`]: progress bars on a terminal.

pub mod args;
pub mod bench;
pub mod load;
pub mod progress;
