//! `isovox bench ...`: benchmarks that print Markdown tables next to the papers' figures.

use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// The thesis's Tables 3-5 on generated data: sizes, compression, load times; open time
    /// and import throughput.
    Store(StoreArgs),
}

#[derive(Debug, clap::Args)]
pub struct StoreArgs {}

pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Store(_) => Ok(()),
    }
}
