//! Subcommands around the stages: table inspection ([`inspect`]), directory validation
//! ([`check`]), exports to splat viewers ([`export`]) and benchmarks ([`bench`]).

pub mod bench;
pub mod check;
pub mod export;
pub mod inspect;
