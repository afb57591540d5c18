//! Run-wide settings shared by every stage: verbosity, progress bars and the device.
//!
//! A [`Context`] is built once from the global CLI flags. Stages ask it for progress bars,
//! which draw only on an interactive terminal and never with `--quiet`. [`Device`] is the
//! `--device` choice; `stages::device` opens the renderer it names.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

/// Where to rasterize (`--device`).
///
/// The default is `cpu` (bit-deterministic, and no graphics driver is loaded). `auto` takes a
/// hardware GPU adapter when one exists and the CPU otherwise; software adapters (Mesa's
/// lavapipe, WARP) are used only with an explicit `gpu`, so `auto` stays on the
/// deterministic CPU path in CI.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Device {
    /// The CPU reference renderer (bit-deterministic; the default).
    #[default]
    Cpu,
    /// A GPU through wgpu; software adapters (lavapipe) count. An error when there is none.
    Gpu,
    /// A hardware GPU adapter if there is one, else the CPU.
    Auto,
}

/// Global settings of one invocation.
#[derive(Debug, Clone, Default)]
pub struct Context {
    /// Suppress progress bars and informational messages.
    pub quiet: bool,
    /// Extra diagnostic output (0 = normal).
    pub verbose: u8,
    /// Where stages rasterize (`--device`).
    pub device: Device,
}

impl Context {
    /// A context that prints nothing and renders on the CPU (tests, nested pipeline runs).
    pub fn quiet() -> Self {
        Context { quiet: true, verbose: 0, device: Device::Cpu }
    }

    /// A progress bar over `len` items labelled `what`; hidden when quiet or stderr is not
    /// a terminal.
    pub fn progress(&self, len: u64, what: &str) -> ProgressBar {
        if self.quiet || !std::io::stderr().is_terminal() {
            return ProgressBar::hidden();
        }
        let bar = ProgressBar::new(len);
        bar.set_style(
            ProgressStyle::with_template(
                "{msg:>14} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        bar.set_message(what.to_string());
        bar
    }

    /// Print an informational line to stderr unless quiet.
    pub fn info(&self, msg: impl std::fmt::Display) {
        if !self.quiet {
            eprintln!("{msg}");
        }
    }

    /// Print a warning to stderr (always, warnings are never silenced).
    pub fn warn(&self, msg: impl std::fmt::Display) {
        eprintln!("warning: {msg}");
    }
}
