//! Device buffers of one render, sized by [`FrameKey`] and reused across frames through a
//! small pool: a render takes a [`Frame`] of its sizes from the pool (or allocates one) and
//! gives it back when done; a saved forward state for the backward pass keeps its frame
//! until dropped. Buffers are never assumed zeroed: every kernel writes what it reads or
//! the encoder clears it, and tests fill fresh frames with junk to prove it.

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use super::context::GpuContext;

/// Words of the kernels' uniform block (`Params` in shaders/common.wgsl, packed by
/// `params::pack`).
pub(crate) const PARAM_WORDS: usize = 56;

/// The sizes a frame's buffers depend on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct FrameKey {
    /// N, Gaussians.
    pub(crate) n: usize,
    /// C = 4 + F channels.
    pub(crate) nc: usize,
    /// Floats of colour input per Gaussian (3 + K·3).
    pub(crate) color_stride: usize,
    /// F.
    pub(crate) nf: usize,
    /// Image width and height.
    pub(crate) w: usize,
    /// Image height.
    pub(crate) h: usize,
    /// Capacity of the intersection list (grown when a render needs more).
    pub(crate) pair_cap: usize,
}

impl FrameKey {
    pub(crate) fn pixels(&self) -> usize {
        self.w * self.h
    }
    pub(crate) fn num_tiles(&self) -> usize {
        self.w.div_ceil(16) * self.h.div_ceil(16)
    }
    pub(crate) fn sort_blocks(&self) -> usize {
        self.pair_cap.div_ceil(256)
    }
    /// Floats of the forward readback: image `[H, W, C]`, final T `[H, W]`, statistics
    /// `[N, 4]`, then the scanned tile counts `[N + 1]` (u32; the last is the pair count M).
    pub(crate) fn fwd_readback_len(&self) -> usize {
        self.pixels() * (self.nc + 1) + self.n * 4 + self.n + 1
    }
    pub(crate) fn grad_stride(&self) -> usize {
        16 + (self.color_stride - 3) + self.nf
    }
}

/// One level of a multi-level prefix sum.
pub(crate) struct ScanLevel {
    pub(crate) sums: wgpu::Buffer,
    pub(crate) params: wgpu::Buffer,
    pub(crate) len: usize,
}

/// Buffers of an exclusive prefix sum over `len` u32 (levels of 256-blocks).
pub(crate) struct ScanPlan {
    pub(crate) levels: Vec<ScanLevel>,
}

/// Buffers the backward pass adds to a frame.
pub(crate) struct BwdBuffers {
    pub(crate) v_pix: wgpu::Buffer,
    pub(crate) scratch: wgpu::Buffer,
    pub(crate) g2d: wgpu::Buffer,
    pub(crate) out: wgpu::Buffer,
    pub(crate) staging: wgpu::Buffer,
}

/// Buffers the convergence tests add to a frame.
pub(crate) struct ConvBuffers {
    pub(crate) pass: wgpu::Buffer,
    pub(crate) fail: wgpu::Buffer,
    pub(crate) staging: wgpu::Buffer,
}

/// All device buffers of one render.
pub(crate) struct Frame {
    pub(crate) key: FrameKey,
    pub(crate) params: wgpu::Buffer,
    pub(crate) geom: wgpu::Buffer,
    pub(crate) colors: wgpu::Buffer,
    pub(crate) feats: wgpu::Buffer,
    pub(crate) splats: wgpu::Buffer,
    pub(crate) chans: wgpu::Buffer,
    pub(crate) counts: wgpu::Buffer,
    pub(crate) stats: wgpu::Buffer,
    pub(crate) count_scan: ScanPlan,
    /// Intersection lists (tile id, depth bits, Gaussian index): ping-pong pair of the sort.
    pub(crate) pairs: [[wgpu::Buffer; 3]; 2],
    pub(crate) hist: wgpu::Buffer,
    pub(crate) hist_scan: ScanPlan,
    /// One uniform per sort pass (shift, word, blocks).
    pub(crate) sort_params: Vec<wgpu::Buffer>,
    pub(crate) tile_offsets: wgpu::Buffer,
    pub(crate) img: wgpu::Buffer,
    pub(crate) final_t: wgpu::Buffer,
    pub(crate) last: wgpu::Buffer,
    pub(crate) staging: wgpu::Buffer,
    pub(crate) bwd: Option<BwdBuffers>,
    pub(crate) conv: Option<ConvBuffers>,
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

/// A storage buffer of `len` 4-byte words (at least one).
pub(crate) fn storage(ctx: &GpuContext, label: &str, len: usize) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: 4 * len.max(1) as u64,
        usage: STORAGE,
        mapped_at_creation: false,
    })
}

pub(crate) fn uniform(ctx: &GpuContext, label: &str, words: &[u32]) -> wgpu::Buffer {
    ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::cast_slice(words),
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}

pub(crate) fn staging(ctx: &GpuContext, label: &str, len: usize) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: 4 * len.max(1) as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

impl ScanPlan {
    fn new(ctx: &GpuContext, len: usize) -> ScanPlan {
        let mut levels = Vec::new();
        let mut n = len;
        loop {
            let blocks = n.div_ceil(256).max(1);
            levels.push(ScanLevel {
                sums: storage(ctx, "scan sums", blocks),
                params: uniform(ctx, "scan params", &[n as u32, 0, 0, 0]),
                len: n,
            });
            if blocks == 1 {
                break;
            }
            n = blocks;
        }
        ScanPlan { levels }
    }
}

/// Number of sort passes: 8 over the depth bits, then 4 bits at a time over the tile ids.
pub(crate) fn sort_passes(num_tiles: usize) -> Vec<(u32, u32)> {
    let tile_bits = usize::BITS - num_tiles.saturating_sub(1).leading_zeros();
    let mut passes: Vec<(u32, u32)> = (0..8).map(|p| (4 * p, 0)).collect();
    passes.extend((0..tile_bits.div_ceil(4)).map(|p| (4 * p, 1)));
    passes
}

impl Frame {
    pub(crate) fn new(ctx: &GpuContext, key: FrameKey) -> Frame {
        let cap = key.pair_cap;
        let blocks = key.sort_blocks();
        let pair = |l| [storage(ctx, l, cap), storage(ctx, l, cap), storage(ctx, l, cap)];
        let sort_params = sort_passes(key.num_tiles())
            .iter()
            .map(|&(shift, word)| uniform(ctx, "sort params", &[shift, word, blocks as u32, 0]))
            .collect();
        Frame {
            key,
            params: uniform(ctx, "params", &[0; PARAM_WORDS]),
            geom: storage(ctx, "geom", key.n * 11),
            colors: storage(ctx, "colors", key.n * key.color_stride),
            feats: storage(ctx, "features", key.n * key.nf),
            splats: storage(ctx, "splats", key.n * 12),
            chans: storage(ctx, "channels", key.n * key.nc),
            counts: storage(ctx, "tile counts", key.n + 1),
            stats: storage(ctx, "stats", key.n * 4),
            count_scan: ScanPlan::new(ctx, key.n + 1),
            pairs: [pair("pairs a"), pair("pairs b")],
            hist: storage(ctx, "sort histogram", 16 * blocks),
            hist_scan: ScanPlan::new(ctx, 16 * blocks),
            sort_params,
            tile_offsets: storage(ctx, "tile offsets", key.num_tiles() + 1),
            img: storage(ctx, "image", key.pixels() * key.nc),
            final_t: storage(ctx, "final T", key.pixels()),
            last: storage(ctx, "last contributor", key.pixels()),
            staging: staging(ctx, "forward readback", key.fwd_readback_len()),
            bwd: None,
            conv: None,
        }
    }

    pub(crate) fn bwd(&mut self, ctx: &GpuContext) -> &BwdBuffers {
        let k = self.key;
        self.bwd.get_or_insert_with(|| BwdBuffers {
            v_pix: storage(ctx, "pixel cotangents", k.pixels() * (k.nc + 1)),
            scratch: storage(ctx, "backward scratch", k.pixels() * k.nc),
            g2d: storage(ctx, "2d grads", k.n * (6 + k.nc)),
            out: storage(ctx, "grads", k.n * k.grad_stride()),
            staging: staging(ctx, "backward readback", k.n * k.grad_stride()),
        })
    }

    pub(crate) fn conv(&mut self, ctx: &GpuContext) -> &ConvBuffers {
        let k = self.key;
        self.conv.get_or_insert_with(|| ConvBuffers {
            pass: storage(ctx, "pixel pass", k.pixels()),
            fail: storage(ctx, "fail", k.n),
            staging: staging(ctx, "convergence readback", k.n),
        })
    }

    /// Every storage buffer of the frame (for junk filling in tests).
    fn storage_buffers(&self) -> Vec<&wgpu::Buffer> {
        let mut v = vec![
            &self.geom,
            &self.colors,
            &self.feats,
            &self.splats,
            &self.chans,
            &self.counts,
            &self.stats,
            &self.hist,
            &self.tile_offsets,
            &self.img,
            &self.final_t,
            &self.last,
        ];
        v.extend(self.pairs.iter().flatten());
        v.extend(self.count_scan.levels.iter().map(|l| &l.sums));
        v.extend(self.hist_scan.levels.iter().map(|l| &l.sums));
        if let Some(b) = &self.bwd {
            v.extend([&b.v_pix, &b.scratch, &b.g2d, &b.out]);
        }
        if let Some(c) = &self.conv {
            v.extend([&c.pass, &c.fail]);
        }
        v
    }

    /// Fill every storage buffer with junk (NaN-like and huge bit patterns).
    pub(crate) fn fill_junk(&self, ctx: &GpuContext) {
        fill_junk(ctx, &self.storage_buffers());
    }
}

/// Fill `buffers` with junk (NaN-like and huge bit patterns).
pub(crate) fn fill_junk(ctx: &GpuContext, buffers: &[&wgpu::Buffer]) {
    for b in buffers {
        let words = (b.size() / 4) as usize;
        let junk: Vec<u32> = (0..words)
            .map(|i| [0x7fc0_0001u32, 0xffff_fff0, 0x4f00_0000, 0xdead_beef][i % 4])
            .collect();
        ctx.queue.write_buffer(b, 0, bytemuck::cast_slice(&junk));
    }
}

/// Frames not in use, for reuse by the next render of the same sizes.
#[derive(Default)]
pub(crate) struct FramePool {
    free: Mutex<Vec<Frame>>,
}

/// How many idle frames the pool keeps.
const POOL_SIZE: usize = 4;

impl FramePool {
    /// A frame of sizes `key` (any pair capacity ≥ `key.pair_cap`), reused when possible.
    pub(crate) fn take(&self, ctx: &GpuContext, key: FrameKey) -> Frame {
        let mut free = self.free.lock().expect("frame pool");
        let fits = |f: &Frame| {
            f.key == FrameKey { pair_cap: f.key.pair_cap, ..key } && f.key.pair_cap >= key.pair_cap
        };
        if let Some(i) = free.iter().position(fits) {
            return free.swap_remove(i);
        }
        drop(free);
        Frame::new(ctx, key)
    }

    pub(crate) fn give(&self, frame: Frame) {
        let mut free = self.free.lock().expect("frame pool");
        free.push(frame);
        if free.len() > POOL_SIZE {
            free.remove(0);
        }
    }
}

/// A frame that goes back to its pool when dropped.
pub(crate) struct PooledFrame {
    pub(crate) frame: Option<Frame>,
    pub(crate) pool: Arc<FramePool>,
}

impl Drop for PooledFrame {
    fn drop(&mut self) {
        if let Some(f) = self.frame.take() {
            self.pool.give(f);
        }
    }
}

/// Bind `buffers` in order to `layout`.
pub(crate) fn bind(
    ctx: &GpuContext,
    layout: &wgpu::BindGroupLayout,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = buffers
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry { binding: i as u32, resource: b.as_entire_binding() })
        .collect();
    ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout,
        entries: &entries,
    })
}

/// Workgroups for `n` blocks as a 2D grid (at most 65535 per dimension).
pub(crate) fn grid(blocks: usize) -> (u32, u32) {
    let x = blocks.clamp(1, 65535);
    (x as u32, blocks.div_ceil(x).max(1) as u32)
}

/// Record one dispatch of `pipeline` over `groups`.
pub(crate) fn dispatch(
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    group: &wgpu::BindGroup,
    groups: (u32, u32),
) {
    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, group, &[]);
    pass.dispatch_workgroups(groups.0, groups.1, 1);
}

/// Read `len` words of a mapped-on-demand staging buffer (blocks until the GPU is done).
pub(crate) fn read_words(
    ctx: &GpuContext,
    buf: &wgpu::Buffer,
    len: usize,
) -> Result<Vec<u32>, String> {
    let bytes = 4 * len as u64;
    let (tx, rx) = std::sync::mpsc::channel();
    buf.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
        let _ = tx.send(r);
    });
    ctx.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| e.to_string())?;
    rx.recv().map_err(|e| e.to_string())?.map_err(|e| e.to_string())?;
    let out = {
        let view = buf.get_mapped_range(0..bytes).map_err(|e| e.to_string())?;
        bytemuck::cast_slice::<u8, u32>(&view).to_vec()
    };
    buf.unmap();
    Ok(out)
}
