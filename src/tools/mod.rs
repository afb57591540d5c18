//! Subcommands around the stages: table inspection ([`inspect`]), directory validation
//! ([`check`]) and benchmarks ([`bench`]).

pub mod bench;
pub mod check;
pub mod inspect;
