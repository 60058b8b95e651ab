//! Fixed pools of shared buffers: the frames capture fills and hands to tracking and the log
//! at once, without a copy and without an allocation per frame.
//!
//! A slot is an `Arc<T>` the pool keeps; it is free when the pool holds the only reference
//! (every queue and stage that was handed a clone has dropped it). Taking a slot gives
//! `&mut T` to fill (the buffers inside keep their capacity from the last use), sharing it
//! clones the `Arc` (a reference count, no allocation). When every slot is in use the caller
//! decides (capture drops the frame and counts it): the pool never grows.

use std::sync::Arc;

pub struct Pool<T> {
    slots: Vec<Arc<T>>,
}

impl<T> Pool<T> {
    /// `capacity` slots made by `make` (at start-up; the only allocation of the pool).
    pub fn new(capacity: usize, mut make: impl FnMut() -> T) -> Self {
        Pool { slots: (0..capacity.max(1)).map(|_| Arc::new(make())).collect() }
    }

    pub fn capacity(&self) -> usize {
        self.slots.len()
    }

    /// Slots some holder other than the pool still references.
    pub fn in_use(&self) -> usize {
        self.slots.iter().filter(|s| Arc::strong_count(s) > 1).count()
    }

    /// The first free slot to fill, `None` when every slot is in use. Its contents are
    /// whatever the last user left. The lowest free slot is taken, so slots past what the
    /// pipeline needs at once stay untouched (their buffers never grow).
    pub fn take(&mut self) -> Option<PoolSlot<'_, T>> {
        // A count of 1 cannot rise again: only the pool could clone that handle.
        let slot = self.slots.iter_mut().find(|s| Arc::strong_count(s) == 1)?;
        Some(PoolSlot { slot })
    }
}

/// A free slot: fill it through [`PoolSlot::get_mut`], then [`PoolSlot::share`] it.
pub struct PoolSlot<'a, T> {
    slot: &'a mut Arc<T>,
}

impl<T> PoolSlot<'_, T> {
    pub fn get_mut(&mut self) -> &mut T {
        Arc::get_mut(self.slot).expect("a slot taken from the pool is referenced by the pool alone")
    }

    /// A shared handle to the filled slot; the slot is busy until every handle is dropped.
    pub fn share(self) -> Arc<T> {
        Arc::clone(self.slot)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slots_come_back_when_every_handle_is_dropped_and_the_pool_never_grows() {
        let mut pool = Pool::new(2, || vec![0u8; 4]);
        let mut s = pool.take().unwrap();
        s.get_mut()[0] = 7;
        let a = s.share();
        let a2 = Arc::clone(&a);
        let mut s = pool.take().unwrap();
        s.get_mut()[0] = 9;
        let b = s.share();
        assert_eq!((a[0], b[0]), (7, 9));
        assert_eq!(pool.in_use(), 2);
        assert!(pool.take().is_none(), "both slots are held");
        drop(a);
        assert!(pool.take().is_none(), "slot 0 still has a handle");
        drop(a2);
        let mut s = pool.take().expect("slot 0 is free again");
        assert_eq!(s.get_mut()[0], 7, "a slot keeps what its last user left");
        drop(s);
        drop(b);
        assert_eq!(pool.in_use(), 0);
        assert_eq!(pool.capacity(), 2);
    }
}
