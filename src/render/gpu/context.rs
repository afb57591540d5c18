//! The wgpu device and the compiled kernels of the GPU rasterizer.
//!
//! Adapter choice: [`GpuContext::new`] takes the first Vulkan/Metal/DX12 adapter, preferring
//! hardware; a CPU adapter (Mesa's lavapipe, WARP) only when `allow_software` is set, so that
//! `--device auto` never picks a software rasterizer while `--device gpu` runs on lavapipe in
//! CI. Float atomics (`SHADER_FLOAT32_ATOMIC`) are used where the adapter has them; otherwise
//! the accumulating kernels add floats with a compare-exchange loop.

use std::borrow::Cow;

use super::super::Error;

/// Kernel sources. WGSL has no includes: each shader module is its own file with the shared
/// pieces it uses prepended, in the order [`Kernels::new`] lists them (`common.wgsl`:
/// constants, `Params`, the alpha arithmetic; `threads.wgsl`: thread ids of the per-item
/// kernels; `block_scan.wgsl`: the workgroup prefix sum; `geometry.wgsl`: projection;
/// `raster_common.wgsl`: tile threads and batches; a generated float-atomic prelude). A
/// shared piece may use the bindings its kernels declare under the same name (`P`,
/// `splats`, `tile_offsets`, `geom`). Built in; for kernel development,
/// `USPLAT4D_SHADER_DIR=shaders` reads them from disk at start instead.
mod src {
    pub const COMMON: &str = include_str!("../../../shaders/common.wgsl");
    pub const THREADS: &str = include_str!("../../../shaders/threads.wgsl");
    pub const BLOCK_SCAN: &str = include_str!("../../../shaders/block_scan.wgsl");
    pub const GEOMETRY: &str = include_str!("../../../shaders/geometry.wgsl");
    pub const RASTER_COMMON: &str = include_str!("../../../shaders/raster_common.wgsl");
    pub const PROJECT: &str = include_str!("../../../shaders/project.wgsl");
    pub const ISECT: &str = include_str!("../../../shaders/isect.wgsl");
    pub const SCAN: &str = include_str!("../../../shaders/scan.wgsl");
    pub const SORT: &str = include_str!("../../../shaders/sort.wgsl");
    pub const FWD: &str = include_str!("../../../shaders/rasterize_fwd.wgsl");
    pub const BWD: &str = include_str!("../../../shaders/rasterize_bwd.wgsl");
    pub const CONVERGENCE: &str = include_str!("../../../shaders/convergence.wgsl");
    pub const PROJECT_BWD: &str = include_str!("../../../shaders/project_bwd.wgsl");
}

/// How a binding is accessed.
#[derive(Clone, Copy)]
pub(crate) enum Bind {
    /// Uniform block.
    U,
    /// Read-only storage.
    R,
    /// Read-write storage.
    W,
}

/// One shader module's bind group layout and its entry points.
pub(crate) struct Kernel {
    pub(crate) layout: wgpu::BindGroupLayout,
    pipelines: Vec<(&'static str, wgpu::ComputePipeline)>,
}

impl Kernel {
    pub(crate) fn pipeline(&self, entry: &str) -> &wgpu::ComputePipeline {
        &self.pipelines.iter().find(|(e, _)| *e == entry).expect("known entry point").1
    }
}

/// All kernels of the rasterizer.
pub(crate) struct Kernels {
    pub(crate) project: Kernel,
    pub(crate) isect: Kernel,
    pub(crate) scan: Kernel,
    pub(crate) sort: Kernel,
    pub(crate) fwd: Kernel,
    pub(crate) bwd: Kernel,
    pub(crate) convergence: Kernel,
    pub(crate) project_bwd: Kernel,
}

/// A wgpu device with the rasterizer's kernels.
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) kernels: Kernels,
    /// Adapter name and backend, for logs and reports.
    pub info: wgpu::AdapterInfo,
    /// Whether the kernels use hardware float atomics.
    pub float_atomics: bool,
}

/// WGSL declarations of the float-accumulating buffers named in `names`: `AF32` and one
/// `<name>_add(i, v)` per buffer, with float atomics or a compare-exchange loop.
fn atomic_prelude(float_atomics: bool, names: &[&str]) -> String {
    let mut s = String::new();
    if float_atomics {
        s.push_str("alias AF32 = atomic<f32>;\n");
        for n in names {
            s.push_str(&format!("fn {n}_add(i: u32, v: f32) {{ atomicAdd(&{n}[i], v); }}\n"));
        }
    } else {
        s.push_str("alias AF32 = atomic<u32>;\n");
        for n in names {
            s.push_str(&format!(
                "fn {n}_add(i: u32, v: f32) {{\n    var old = atomicLoad(&{n}[i]);\n    loop {{\n        \
                 let r = atomicCompareExchangeWeak(&{n}[i], old, bitcast<u32>(bitcast<f32>(old) + v));\n        \
                 if (r.exchanged) {{ break; }}\n        old = r.old_value;\n    }}\n}}\n"
            ));
        }
    }
    s
}

impl GpuContext {
    /// Open the first usable adapter (see the module doc), or `None` when there is none.
    pub fn new(allow_software: bool) -> Result<Option<GpuContext>, Error> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends: wgpu::Backends::PRIMARY,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let mut adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY));
        adapters.retain(|a| {
            let t = a.get_info().device_type;
            allow_software || t != wgpu::DeviceType::Cpu
        });
        // Hardware first: discrete, integrated, then the rest.
        adapters.sort_by_key(|a| match a.get_info().device_type {
            wgpu::DeviceType::DiscreteGpu => 0,
            wgpu::DeviceType::IntegratedGpu => 1,
            wgpu::DeviceType::VirtualGpu => 2,
            wgpu::DeviceType::Other => 3,
            wgpu::DeviceType::Cpu => 4,
        });
        let Some(adapter) = adapters.into_iter().next() else { return Ok(None) };
        let info = adapter.get_info();
        let float_atomics = adapter.features().contains(wgpu::Features::SHADER_FLOAT32_ATOMIC)
            && std::env::var_os("USPLAT4D_GPU_NO_FLOAT_ATOMICS").is_none();
        let features = if float_atomics {
            wgpu::Features::SHADER_FLOAT32_ATOMIC
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("usplat4d"),
            required_features: features,
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(|e| Error::Gpu(format!("cannot open {}: {e}", info.name)))?;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let kernels = Kernels::new(&device, float_atomics);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("kernels do not compile on {}: {e}", info.name)));
        }
        tracing::info!(adapter = %info.name, backend = ?info.backend, float_atomics, "GPU renderer");
        Ok(Some(GpuContext { device, queue, kernels, info, float_atomics }))
    }
}

impl Kernels {
    fn new(device: &wgpu::Device, fa: bool) -> Kernels {
        use Bind::{R, U, W};
        let dir = std::env::var_os("USPLAT4D_SHADER_DIR").map(std::path::PathBuf::from);
        let k = |name: &str, parts: &[&str], binds: &[Bind], entries: &[&'static str]| {
            let source: String = match &dir {
                None => parts.concat(),
                Some(d) => parts
                    .iter()
                    .map(|p| match p.lines().next().and_then(|l| l.strip_prefix("// file: ")) {
                        Some(f) => {
                            std::fs::read_to_string(d.join(f)).unwrap_or_else(|_| p.to_string())
                        }
                        None => p.to_string(),
                    })
                    .collect(),
            };
            kernel(device, name, &source, binds, entries)
        };
        let stats = atomic_prelude(fa, &["stats"]);
        let grads = atomic_prelude(fa, &["grads"]);
        Kernels {
            project: k(
                "project",
                &[src::COMMON, src::THREADS, src::GEOMETRY, src::PROJECT],
                &[U, R, R, R, W, W, W, W],
                &["main"],
            ),
            isect: k(
                "isect",
                &[src::COMMON, src::THREADS, src::ISECT],
                &[U, R, R, W, W, W, W],
                &["emit", "ranges"],
            ),
            scan: k(
                "scan",
                &[src::THREADS, src::BLOCK_SCAN, src::SCAN],
                &[U, W, W],
                &["scan_blocks", "add_sums"],
            ),
            sort: k(
                "sort",
                &[src::THREADS, src::BLOCK_SCAN, src::SORT],
                &[U, R, R, R, R, W, W, W, W],
                &["count", "scatter"],
            ),
            fwd: k(
                "rasterize_fwd",
                &[src::COMMON, src::RASTER_COMMON, stats.as_str(), src::FWD],
                &[U, R, R, R, R, W, W, W, W],
                &["main"],
            ),
            bwd: k(
                "rasterize_bwd",
                &[src::COMMON, src::RASTER_COMMON, grads.as_str(), src::BWD],
                &[U, R, R, R, R, R, R, R, W, W],
                &["main"],
            ),
            convergence: k(
                "convergence",
                &[src::COMMON, src::THREADS, src::RASTER_COMMON, src::CONVERGENCE],
                &[U, R, R, R, R, R, W],
                &["fail_pairs", "centre"],
            ),
            project_bwd: k(
                "project_bwd",
                &[src::COMMON, src::THREADS, src::GEOMETRY, src::PROJECT_BWD],
                &[U, R, R, R, R, W],
                &["main"],
            ),
        }
    }
}

fn kernel(
    device: &wgpu::Device,
    name: &str,
    source: &str,
    binds: &[Bind],
    entries: &[&'static str],
) -> Kernel {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(source)),
    });
    let layout_entries: Vec<wgpu::BindGroupLayoutEntry> = binds
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: match b {
                    Bind::U => wgpu::BufferBindingType::Uniform,
                    Bind::R => wgpu::BufferBindingType::Storage { read_only: true },
                    Bind::W => wgpu::BufferBindingType::Storage { read_only: false },
                },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(name),
        entries: &layout_entries,
    });
    let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(name),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipelines = entries
        .iter()
        .map(|e| {
            let p = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(e),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(e),
                compilation_options: Default::default(),
                cache: None,
            });
            (*e, p)
        })
        .collect();
    Kernel { layout, pipelines }
}
