//! A process-wide pool of `f32` buffers for feature maps and convolution scratch (shared by
//! the direct and the Winograd convolutions).

use std::sync::Mutex;

/// The pooled buffers.
static POOL: Mutex<Vec<Vec<f32>>> = Mutex::new(Vec::new());
/// Most bytes the pool keeps (the largest buffers of one 512x512 pair are about
/// 17 MB; two pairs run at once on two threads).
const MAX_BYTES: usize = 192 << 20;

/// A buffer of `len` values with **unspecified contents** (the caller overwrites
/// every value): the smallest pooled one that fits, or a new one.
pub fn take(len: usize) -> Vec<f32> {
    let mut pool = POOL.lock().unwrap_or_else(|e| e.into_inner());
    let best =
        (0..pool.len()).filter(|&i| pool[i].capacity() >= len).min_by_key(|&i| pool[i].capacity());
    match best {
        Some(i) => {
            let mut v = pool.swap_remove(i);
            drop(pool);
            v.truncate(len);
            v.resize(len, 0.0);
            v
        }
        None => {
            drop(pool);
            vec![0.0; len]
        }
    }
}

/// Return a buffer to the pool; the smallest buffers are dropped beyond
/// [`MAX_BYTES`].
pub fn give(v: Vec<f32>) {
    let mut pool = POOL.lock().unwrap_or_else(|e| e.into_inner());
    pool.push(v);
    let bytes = |p: &[Vec<f32>]| p.iter().map(|v| v.capacity() * 4).sum::<usize>();
    while bytes(&pool) > MAX_BYTES {
        let smallest = (0..pool.len()).min_by_key(|&i| pool[i].capacity()).expect("non-empty");
        pool.swap_remove(smallest);
    }
}
