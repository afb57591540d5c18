//! Run-wide settings shared by every stage: verbosity, progress bars and the renderer.
//!
//! A [`Context`] is built once from the global CLI flags. Stages ask it for progress bars,
//! which draw only on an interactive terminal and never with `--quiet`, and for the
//! renderer of `--device` ([`Context::renderer`], opened once and shared).

use std::io::IsTerminal;
use std::sync::{Arc, Mutex};

use indicatif::{ProgressBar, ProgressStyle};

use crate::render::gpu::{AnyRenderer, Device};

/// Global settings of one invocation.
#[derive(Debug, Clone, Default)]
pub struct Context {
    /// Suppress progress bars and informational messages.
    pub quiet: bool,
    /// Extra diagnostic output (0 = normal).
    pub verbose: u8,
    /// Where stages rasterize (`--device`).
    pub device: Device,
    /// The renderer of `device`, opened on first use.
    renderer: Arc<Mutex<Option<AnyRenderer>>>,
}

impl Context {
    /// A context with these flags.
    pub fn new(quiet: bool, verbose: u8, device: Device) -> Self {
        Context { quiet, verbose, device, renderer: Arc::default() }
    }

    /// A context that prints nothing and renders on the CPU (tests, nested pipeline runs).
    pub fn quiet() -> Self {
        Context::new(true, 0, Device::Cpu)
    }

    /// The same context with other verbosity flags, sharing the opened renderer.
    pub fn with_flags(&self, quiet: bool, verbose: u8, device: Option<Device>) -> Self {
        match device {
            Some(d) if d != self.device => Context::new(quiet, verbose, d),
            _ => Context { quiet, verbose, ..self.clone() },
        }
    }

    /// The renderer the stages use (see [`Device`]); opened once per context.
    pub fn renderer(&self) -> anyhow::Result<AnyRenderer> {
        let mut slot =
            self.renderer.lock().map_err(|_| anyhow::anyhow!("renderer lock poisoned"))?;
        if let Some(r) = &*slot {
            return Ok(r.clone());
        }
        let r = AnyRenderer::open(self.device).map_err(|e| anyhow::anyhow!("--device: {e}"))?;
        tracing::info!(renderer = %r.tag(), "renderer");
        *slot = Some(r.clone());
        Ok(r)
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
