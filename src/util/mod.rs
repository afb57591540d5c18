//! Small helpers every layer may use: the seeded generator ([`rng`]), atomic file writes
//! ([`fs`]) and order statistics ([`stats`]) and image filters ([`filter`]).

pub mod filter;
pub mod fs;
pub mod rng;
pub mod stats;

/// A subcommand's arguments parsed from a command line without the binary name (unit tests).
#[cfg(test)]
pub(crate) fn parse_args<A: clap::Args + clap::FromArgMatches>(
    args: &[&str],
) -> Result<A, clap::Error> {
    let cmd = A::augment_args(clap::Command::new("test").no_binary_name(true));
    A::from_arg_matches(&cmd.try_get_matches_from(args)?)
}
