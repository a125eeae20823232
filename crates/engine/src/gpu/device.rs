//! What every file of the GPU engine that touches the device shares, below the context: the
//! size a buffer really takes ([`padded`]), making a buffer of it ([`buffer`]), and whether the
//! device is still usable ([`Health`]).
//!
//! Invariants: every buffer the engine sizes from its input is made through [`buffer`] (or
//! `GpuContext::init`), so the bytes charged to the memory budget, [`padded`], are the bytes
//! allocated; a device's health, once failed, never recovers (the first reason is kept).

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use super::GpuError;

/// Whether the device is still usable, and why not.
#[derive(Default)]
pub(super) struct Health {
    lost: AtomicBool,
    reason: Mutex<Option<String>>,
}

impl Health {
    pub(super) fn fail(&self, reason: String) {
        if let Ok(mut r) = self.reason.lock() {
            r.get_or_insert(reason);
        }
        self.lost.store(true, Ordering::SeqCst);
    }
    pub(super) fn check(&self) -> Result<(), GpuError> {
        if self.lost.load(Ordering::SeqCst) {
            let reason = self
                .reason
                .lock()
                .ok()
                .and_then(|r| r.clone())
                .unwrap_or_default();
            Err(GpuError::Lost(reason))
        } else {
            Ok(())
        }
    }
}

/// Bytes of a buffer [`buffer`] (and so `GpuContext::buffer`) or `GpuContext::init` makes for `size` bytes: bindings may not
/// be empty, so tiny arrays are padded to 16 bytes, and sizes to whole words.
pub(super) fn padded(size: u64) -> u64 {
    size.max(16).next_multiple_of(4)
}

/// A buffer of `size` bytes, [`padded`], not mapped.
pub(super) fn buffer(
    device: &wgpu::Device,
    label: &str,
    size: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: padded(size),
        usage,
        mapped_at_creation: false,
    })
}
