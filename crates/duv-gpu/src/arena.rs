//! Fixed GPU memory: one `VkBuffer` over one `VkDeviceMemory` (`ArenaMemory`), allocated
//! once at start-up with the board's budget: persistently mapped where device-local memory is
//! also host-cached (integrated GPUs, lavapipe), else device-local and reached by the host
//! through a staging buffer (the context's transfers). Buffers are ranges of it handed out by a
//! bump allocator that never grows: a request past the budget is [`GpuError::ArenaFull`]. The
//! high-water mark is the peak GPU memory the mapper used.

use std::marker::PhantomData;

use ash::vk;

use super::GpuError;

/// A byte range of the arena (what a binding sees).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuRange {
    pub offset: u64,
    pub size: u64,
}

/// A typed range of the arena holding `len` elements of `T`.
#[derive(Debug)]
pub struct GpuBuffer<T> {
    pub(crate) what: &'static str,
    pub(crate) offset: u64,
    pub(crate) len: usize,
    _t: PhantomData<T>,
}

impl<T> Clone for GpuBuffer<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for GpuBuffer<T> {}

impl<T> GpuBuffer<T> {
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    pub fn what(&self) -> &'static str {
        self.what
    }
    /// The whole buffer as a binding.
    pub fn range(&self) -> GpuRange {
        GpuRange { offset: self.offset, size: (self.len * std::mem::size_of::<T>()) as u64 }
    }
    /// Elements `start..start + len` as a binding (the offset must keep the device's storage
    /// offset alignment; the arena aligns every buffer, so a whole buffer always does).
    pub fn slice_range(&self, start: usize, len: usize) -> Result<GpuRange, GpuError> {
        if start + len > self.len {
            return Err(GpuError::OutOfRange { what: self.what, requested: start + len, len: self.len });
        }
        let size_of = std::mem::size_of::<T>() as u64;
        Ok(GpuRange { offset: self.offset + start as u64 * size_of, size: len as u64 * size_of })
    }
}

/// The bump allocator over the arena's byte range.
#[derive(Clone, Debug)]
pub(crate) struct Arena {
    capacity: u64,
    alignment: u64,
    top: u64,
    peak: u64,
}

impl Arena {
    pub(crate) fn new(capacity: u64, alignment: u64) -> Self {
        Arena { capacity, alignment: alignment.max(16).next_power_of_two(), top: 0, peak: 0 }
    }

    pub(crate) fn alloc<T>(&mut self, what: &'static str, len: usize) -> Result<GpuBuffer<T>, GpuError> {
        let bytes = (len.max(1) * std::mem::size_of::<T>()) as u64;
        let offset = self.top.div_ceil(self.alignment) * self.alignment;
        let end = offset.saturating_add(bytes);
        if end > self.capacity {
            return Err(GpuError::ArenaFull {
                what,
                requested: bytes,
                free: self.capacity.saturating_sub(offset),
                capacity: self.capacity,
            });
        }
        self.top = end;
        self.peak = self.peak.max(end);
        Ok(GpuBuffer { what, offset, len, _t: PhantomData })
    }

    /// Bytes in use now.
    pub(crate) fn used(&self) -> u64 {
        self.top
    }
    pub(crate) fn peak(&self) -> u64 {
        self.peak
    }
    pub(crate) fn capacity(&self) -> u64 {
        self.capacity
    }
    /// Frees everything allocated after `mark` (a value of [`Arena::used`]): scratch space of
    /// a start-up phase. Buffers handed out after the mark must not be used again.
    pub(crate) fn reset_to(&mut self, mark: u64) {
        self.top = self.top.min(mark);
    }
}

/// The arena's Vulkan objects and its allocator: the part of a `GpuContext` every binding,
/// fill, copy and host transfer points into. Created by the context's start-up (`select`),
/// destroyed by its drop with the other parts, before the device.
pub(crate) struct ArenaMemory {
    /// The byte ranges handed out.
    pub(crate) arena: Arena,
    pub(crate) buffer: vk::Buffer,
    pub(crate) memory: vk::DeviceMemory,
    /// The whole of `memory`, mapped; null when host transfers are staged.
    pub(crate) mapped: *mut u8,
}

impl ArenaMemory {
    /// No Vulkan objects yet (null handles), an allocator of `capacity` bytes.
    pub(crate) fn new(capacity: u64) -> Self {
        ArenaMemory { arena: Arena::new(capacity, 256), buffer: vk::Buffer::null(), memory: vk::DeviceMemory::null(), mapped: std::ptr::null_mut() }
    }

    /// The host reads and writes the arena in place (else through the staging buffer).
    pub(crate) fn is_mapped(&self) -> bool {
        !self.mapped.is_null()
    }

    /// Unmaps and frees the arena.
    ///
    /// # Safety
    /// `device` made these objects and no pending command uses them.
    pub(crate) unsafe fn destroy(&mut self, device: &ash::Device) {
        unsafe {
            if self.is_mapped() {
                device.unmap_memory(self.memory);
            }
            device.destroy_buffer(self.buffer, None);
            device.free_memory(self.memory, None);
        }
        (self.buffer, self.memory, self.mapped) = (vk::Buffer::null(), vk::DeviceMemory::null(), std::ptr::null_mut());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allocations_are_aligned_and_overflow_names_the_buffer() {
        let mut a = Arena::new(1024, 256);
        let b0: GpuBuffer<u32> = a.alloc("first", 10).unwrap();
        let b1: GpuBuffer<u64> = a.alloc("second", 3).unwrap();
        assert_eq!(b0.offset, 0);
        assert_eq!(b1.offset, 256);
        assert_eq!(a.peak(), 256 + 24);
        match a.alloc::<f32>("big", 300) {
            Err(GpuError::ArenaFull { what, requested, free, capacity }) => {
                assert_eq!((what, requested, free, capacity), ("big", 1200, 512, 1024));
            }
            other => panic!("expected ArenaFull, got {other:?}"),
        }
        a.reset_to(256);
        assert_eq!(a.used(), 256);
        assert_eq!(a.peak(), 280);
    }
}
