//! The renderer every stage uses: the one `--device` names ([`Device`]), opened once per
//! process and device and shared (opening a GPU compiles its kernels).

use std::sync::Mutex;

use crate::context::{Context, Device};
use crate::render::gpu::{AnyRenderer, GpuRenderer};
use crate::render::{CpuRenderer, Error};

/// The renderer of `ctx.device`: the CPU for `cpu`; any GPU adapter (software ones
/// included) for `gpu`, an error without one; a hardware GPU adapter for `auto`, else the CPU.
pub fn renderer(ctx: &Context) -> anyhow::Result<AnyRenderer> {
    static OPENED: Mutex<Vec<(Device, AnyRenderer)>> = Mutex::new(Vec::new());
    let mut opened = OPENED.lock().map_err(|_| anyhow::anyhow!("renderer lock poisoned"))?;
    if let Some((_, r)) = opened.iter().find(|(d, _)| *d == ctx.device) {
        return Ok(r.clone());
    }
    let r = open(ctx.device).map_err(|e| anyhow::anyhow!("--device: {e}"))?;
    tracing::info!(renderer = %r.tag(), "renderer");
    opened.push((ctx.device, r.clone()));
    Ok(r)
}

fn open(device: Device) -> Result<AnyRenderer, Error> {
    Ok(match device {
        Device::Cpu => AnyRenderer::Cpu(CpuRenderer),
        Device::Gpu => AnyRenderer::Gpu(
            GpuRenderer::new(true)?
                .ok_or_else(|| Error::Gpu("--device gpu: no GPU adapter found".into()))?,
        ),
        Device::Auto => match GpuRenderer::new(false)? {
            Some(g) => AnyRenderer::Gpu(g),
            None => AnyRenderer::Cpu(CpuRenderer),
        },
    })
}
