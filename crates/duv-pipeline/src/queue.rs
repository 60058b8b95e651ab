//! Bounded queues with a written policy per edge (ARCHITECTURE.md, "Threads and queues").
//!
//! One type, [`BoundedQueue`], bounded in items and optionally in bytes, whose `push` never
//! blocks: when full it drops the oldest item ([`FullPolicy::DropOldest`]), drops the item
//! whose neighbours lie closest together in time so that what is kept spans the wait evenly
//! ([`FullPolicy::Spread`], frames), or refuses the new one ([`FullPolicy::DropNewest`], log
//! records), and counts the drop (keyframes have their own queue, `keyframe_queue`, which
//! defers instead). End of stream is [`BoundedQueue::close`]: the consumer drains what is left
//! and then gets `None`. The storage is allocated once, at construction.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// What `push` does when the queue is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FullPolicy {
    /// Evict the oldest item to make room (the freshest item matters most).
    DropOldest,
    /// Evict the queued item whose neighbours lie closest together by the items' keys (their
    /// times, [`BoundedQueue::push_at`]); the new item is always kept, and the item the consumer
    /// took last counts as the oldest one's older neighbour. After the consumer was held up
    /// (a tracker's long solve), what waits for it is spread evenly over the wait, from just
    /// after what it saw last to the newest: it crosses the gap in steps it can follow instead
    /// of one jump to the newest items. Ties go to the older item.
    Spread,
    /// Refuse the new item (the producer must never wait).
    DropNewest,
}

/// Counters of a queue.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct QueueStats {
    pub pushed: u64,
    pub popped: u64,
    pub dropped: u64,
    /// Items taken out of the queue to make room but not lost (the keyframe queue's deferred
    /// keyframes, mapped from the log at the end of the run; see `keyframe_queue`).
    pub deferred: u64,
    pub depth: usize,
    pub depth_bytes: usize,
    pub max_depth: usize,
}

struct Inner<T> {
    /// Each item with its bytes and its key.
    items: VecDeque<(T, usize, i64)>,
    /// The key of the item the consumer took last.
    last_popped_key: Option<i64>,
    bytes: usize,
    closed: bool,
    stats: QueueStats,
}

/// A bounded multi-producer, multi-consumer queue that never blocks its producers.
pub struct BoundedQueue<T> {
    name: &'static str,
    capacity: usize,
    capacity_bytes: usize,
    policy: FullPolicy,
    inner: Mutex<Inner<T>>,
    not_empty: Condvar,
    not_full: Condvar,
}

/// What a push did.
#[derive(Debug, PartialEq, Eq)]
pub enum Pushed<T> {
    Queued,
    /// Queued after evicting an older item (the oldest, or with [`FullPolicy::Spread`] the
    /// one whose neighbours lay closest), which is handed back.
    QueuedDropped(T),
    /// Refused (full, or the item alone is larger than the byte budget).
    Refused(T),
    /// The queue is closed.
    Closed(T),
}

impl<T> BoundedQueue<T> {
    /// A queue of at most `capacity` items and, if `capacity_bytes > 0`, at most that many
    /// bytes (as the caller measures each item).
    pub fn new(name: &'static str, capacity: usize, capacity_bytes: usize, policy: FullPolicy) -> Self {
        assert!(capacity > 0, "queue {name}: capacity must be > 0");
        BoundedQueue {
            name,
            capacity,
            capacity_bytes,
            policy,
            inner: Mutex::new(Inner { items: VecDeque::with_capacity(capacity), last_popped_key: None, bytes: 0, closed: false, stats: QueueStats::default() }),
            not_empty: Condvar::new(),
            not_full: Condvar::new(),
        }
    }

    pub fn name(&self) -> &'static str {
        self.name
    }
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner<T>> {
        // A panicking holder cannot leave the VecDeque inconsistent; keep going.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Pushes an item of `bytes` bytes (0 when the queue is not byte-bounded). Never blocks.
    /// Its key is its place in the order of pushes (see [`push_at`](Self::push_at)).
    pub fn push(&self, item: T, bytes: usize) -> Pushed<T> {
        self.push_keyed(item, bytes, None)
    }

    /// [`push`](Self::push) with the item's key, a time in any unit that does not decrease
    /// from one push to the next: [`FullPolicy::Spread`] keeps the queued keys evenly spaced.
    pub fn push_at(&self, item: T, bytes: usize, key: i64) -> Pushed<T> {
        self.push_keyed(item, bytes, Some(key))
    }

    fn push_keyed(&self, item: T, bytes: usize, key: Option<i64>) -> Pushed<T> {
        let mut g = self.lock();
        let key = key.unwrap_or(g.stats.pushed as i64);
        if g.closed {
            return Pushed::Closed(item);
        }
        let over_bytes = |g: &Inner<T>| self.capacity_bytes > 0 && g.bytes + bytes > self.capacity_bytes;
        if self.capacity_bytes > 0 && bytes > self.capacity_bytes {
            g.stats.dropped += 1;
            return Pushed::Refused(item);
        }
        let mut evicted = None;
        if g.items.len() >= self.capacity || over_bytes(&g) {
            match self.policy {
                FullPolicy::DropNewest => {
                    g.stats.dropped += 1;
                    return Pushed::Refused(item);
                }
                FullPolicy::DropOldest | FullPolicy::Spread => {
                    while g.items.len() >= self.capacity || over_bytes(&g) {
                        let i = match self.policy {
                            FullPolicy::Spread => spread_victim(&g.items, g.last_popped_key, key),
                            _ => 0,
                        };
                        let Some((old, b, _)) = g.items.remove(i) else { break };
                        g.bytes -= b;
                        g.stats.dropped += 1;
                        evicted = Some(old);
                    }
                }
            }
        }
        g.items.push_back((item, bytes, key));
        g.bytes += bytes;
        g.stats.pushed += 1;
        g.stats.max_depth = g.stats.max_depth.max(g.items.len());
        drop(g);
        self.not_empty.notify_one();
        match evicted {
            Some(old) => Pushed::QueuedDropped(old),
            None => Pushed::Queued,
        }
    }

    /// Pushes, waiting while the queue is full (offline sources: nothing may be lost and the
    /// producer may wait). Never used where the producer must not wait.
    pub fn push_wait(&self, item: T, bytes: usize) -> Pushed<T> {
        let mut g = self.lock();
        while !g.closed && (g.items.len() >= self.capacity || (self.capacity_bytes > 0 && g.bytes + bytes > self.capacity_bytes && !g.items.is_empty())) {
            g = self.not_full.wait(g).unwrap_or_else(|p| p.into_inner());
        }
        drop(g);
        self.push(item, bytes)
    }

    /// Waits up to `timeout` for an item. `Ok(None)`: timed out; `Err(())`: closed and drained
    /// (end of stream).
    #[allow(clippy::result_unit_err)]
    pub fn pop_timeout(&self, timeout: Duration) -> Result<Option<T>, ()> {
        let mut g = self.lock();
        if g.items.is_empty() && !g.closed {
            g = self.not_empty.wait_timeout_while(g, timeout, |g| g.items.is_empty() && !g.closed).unwrap_or_else(|p| p.into_inner()).0;
        }
        match g.items.pop_front() {
            Some((item, b, key)) => {
                g.bytes -= b;
                g.last_popped_key = Some(key);
                g.stats.popped += 1;
                drop(g);
                self.not_full.notify_one();
                Ok(Some(item))
            }
            None if g.closed => Err(()),
            None => Ok(None),
        }
    }

    /// Blocks until an item arrives; `None` at end of stream.
    pub fn pop(&self) -> Option<T> {
        loop {
            match self.pop_timeout(Duration::from_secs(3600)) {
                Ok(Some(item)) => return Some(item),
                Ok(None) => continue,
                Err(()) => return None,
            }
        }
    }

    /// Takes an item if one is waiting.
    pub fn try_pop(&self) -> Option<T> {
        self.pop_timeout(Duration::ZERO).ok().flatten()
    }

    /// Ends the stream: producers are refused from now on, the consumer drains and stops.
    pub fn close(&self) {
        self.lock().closed = true;
        self.not_empty.notify_all();
        self.not_full.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    pub fn stats(&self) -> QueueStats {
        let g = self.lock();
        QueueStats { depth: g.items.len(), depth_bytes: g.bytes, ..g.stats }
    }
}

/// Which of `queued` (oldest first) to take out so that `newest` fits with what stays spread
/// out: the one whose neighbours lie closest together by `distance` (`anchor`, the item the
/// consumer took last, is the first one's older neighbour; `newest` the last one's newer
/// one); ties to the older. Without an anchor the first has no neighbour before it and is
/// kept unless it is the only one. [`FullPolicy::Spread`] measures in time; the keyframe queue
/// in view distance (`keyframe_queue::choose_deferred`).
pub(crate) fn closest_neighbours<'a, V: 'a>(anchor: Option<&'a V>, queued: impl Iterator<Item = &'a V>, newest: &'a V, distance: impl Fn(&V, &V) -> f64) -> usize {
    let mut best = (0, f64::INFINITY);
    let mut prev = anchor;
    let mut it = queued.peekable();
    let mut i = 0;
    while let Some(v) = it.next() {
        let next = it.peek().copied().unwrap_or(newest);
        let gap = prev.map_or(f64::INFINITY, |p| distance(p, next));
        if gap < best.1 {
            best = (i, gap);
        }
        prev = Some(v);
        i += 1;
    }
    best.0
}

/// The index of the queued item [`FullPolicy::Spread`] evicts before `new_key` is queued
/// ([`closest_neighbours`] by key).
fn spread_victim<T>(items: &VecDeque<(T, usize, i64)>, last_popped_key: Option<i64>, new_key: i64) -> usize {
    closest_neighbours(last_popped_key.as_ref(), items.iter().map(|(_, _, k)| k), &new_key, |a, b| b.abs_diff(*a) as f64)
}

/// A single-value cell the producer overwrites (map -> tracking feedback).
pub struct LatestCell<T> {
    value: Mutex<Option<T>>,
}

impl<T> Default for LatestCell<T> {
    fn default() -> Self {
        LatestCell { value: Mutex::new(None) }
    }
}

impl<T> LatestCell<T> {
    pub fn set(&self, v: T) {
        *self.value.lock().unwrap_or_else(|p| p.into_inner()) = Some(v);
    }
    pub fn take(&self) -> Option<T> {
        self.value.lock().unwrap_or_else(|p| p.into_inner()).take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn drop_oldest_keeps_the_newest_and_counts() {
        let q = BoundedQueue::new("frames", 3, 0, FullPolicy::DropOldest);
        for i in 0..10 {
            q.push(i, 0);
        }
        let s = q.stats();
        assert_eq!((s.pushed, s.dropped, s.depth), (10, 7, 3));
        q.close();
        assert_eq!(std::iter::from_fn(|| q.pop()).collect::<Vec<_>>(), vec![7, 8, 9]);
    }

    #[test]
    fn byte_bound_refuses_and_counts() {
        let q = BoundedQueue::new("log", 100, 1000, FullPolicy::DropNewest);
        assert_eq!(q.push(1, 600), Pushed::Queued);
        assert_eq!(q.push(2, 600), Pushed::Refused(2));
        assert_eq!(q.push(3, 400), Pushed::Queued);
        assert_eq!(q.push(4, 2000), Pushed::Refused(4));
        let s = q.stats();
        assert_eq!((s.depth, s.depth_bytes, s.dropped), (2, 1000, 2));
        assert_eq!(q.try_pop(), Some(1));
        assert_eq!(q.push(5, 500), Pushed::Queued);
        assert_eq!(q.stats().depth_bytes, 900);
    }

    #[test]
    fn close_drains_then_ends() {
        let q = Arc::new(BoundedQueue::new("k", 4, 0, FullPolicy::DropNewest));
        q.push(1, 0);
        q.push(2, 0);
        q.close();
        assert_eq!(q.push(3, 0), Pushed::Closed(3));
        let q2 = q.clone();
        let h = std::thread::spawn(move || std::iter::from_fn(|| q2.pop()).collect::<Vec<_>>());
        assert_eq!(h.join().unwrap(), vec![1, 2]);
    }

    /// A producer at full speed against a consumer that takes 2 ms per item: the producer is
    /// never held up, the queue never exceeds its capacity, every drop is counted, and what
    /// the consumer gets is in order and ends with the newest item (drop oldest, spread).
    #[test]
    fn slow_consumer_never_blocks_the_producer_and_drops_are_counted() {
        for policy in [FullPolicy::DropOldest, FullPolicy::Spread, FullPolicy::DropNewest] {
            let q = Arc::new(BoundedQueue::new("slow", 4, 0, policy));
            let c = q.clone();
            let consumer = std::thread::spawn(move || {
                let mut got = Vec::new();
                while let Some(v) = c.pop() {
                    got.push(v);
                    std::thread::sleep(Duration::from_millis(2));
                }
                got
            });
            let mut worst = Duration::ZERO;
            for i in 0..500u32 {
                let t0 = std::time::Instant::now();
                q.push(i, 0);
                worst = worst.max(t0.elapsed());
                assert!(q.stats().depth <= 4);
            }
            q.close();
            let got = consumer.join().unwrap();
            let s = q.stats();
            // Pushing never waits for the consumer (a generous bound for a loaded machine;
            // the consumer alone needs 2 ms per item).
            assert!(worst < Duration::from_millis(50), "{policy:?}: a push took {worst:?}");
            assert!(s.dropped > 300, "{policy:?}: only {} dropped", s.dropped);
            assert_eq!(s.pushed - (if policy == FullPolicy::DropNewest { 0 } else { s.dropped }), got.len() as u64, "{policy:?}");
            assert_eq!(got.len() as u64 + s.dropped, 500, "{policy:?}");
            assert!(got.windows(2).all(|w| w[0] < w[1]), "{policy:?}: out of order");
            if policy != FullPolicy::DropNewest {
                assert_eq!(*got.last().unwrap(), 499);
            } else {
                assert_eq!(got[0], 0);
            }
        }
    }

    /// The consumer takes item 0 and is then held up while items 1..=30 arrive (a tracker's
    /// 3 s solve at 10 frames/s). Drop oldest leaves it 27..=30: a jump of 27 from what it saw
    /// last. Spread leaves four items spaced evenly from 0 to 30 (at most 9 apart), the newest
    /// among them, in order.
    #[test]
    fn spread_keeps_what_waits_evenly_spaced_after_a_stall() {
        let waiting = |policy| {
            let q = BoundedQueue::new("frames", 4, 0, policy);
            q.push_at(0i64, 0, 0);
            assert_eq!(q.try_pop(), Some(0));
            for k in 1..=30i64 {
                q.push_at(k, 0, 10 * k);
                assert!(q.stats().depth <= 4);
            }
            assert_eq!(q.stats().dropped, 26);
            std::iter::once(0).chain(std::iter::from_fn(|| q.try_pop())).collect::<Vec<i64>>()
        };
        let max_step = |v: &[i64]| v.windows(2).map(|w| w[1] - w[0]).max().unwrap();
        let oldest = waiting(FullPolicy::DropOldest);
        assert_eq!(oldest, vec![0, 27, 28, 29, 30]);
        let spread = waiting(FullPolicy::Spread);
        assert_eq!((spread.len(), *spread.last().unwrap()), (5, 30), "{spread:?}");
        assert!(spread.windows(2).all(|w| w[0] < w[1]), "{spread:?}");
        assert!(max_step(&spread) <= 9, "{spread:?}: a step of {}", max_step(&spread));
        assert!(spread[1] > 1, "{spread:?}: the first step is wasted on the next item");
    }

    /// A consumer a little slower than the producer (4 items taken per 5 pushed), for 1000
    /// pushes: with Spread, what it takes is never older than with drop oldest (3 pushes), and
    /// it never skips more than 2 items at once.
    #[test]
    fn spread_under_a_steady_overload_stays_fresh() {
        let run = |policy| {
            let q = BoundedQueue::new("frames", 4, 0, policy);
            let (mut worst_age, mut worst_skip, mut last) = (0i64, 0i64, -1i64);
            for k in 0..1000i64 {
                q.push_at(k, 0, k);
                if k % 5 != 4 {
                    if let Some(v) = q.try_pop() {
                        worst_age = worst_age.max(k - v);
                        worst_skip = worst_skip.max(v - last);
                        last = v;
                    }
                }
            }
            (worst_age, worst_skip)
        };
        let (age_oldest, _) = run(FullPolicy::DropOldest);
        let (age_spread, skip_spread) = run(FullPolicy::Spread);
        assert_eq!(age_oldest, 3);
        assert!(age_spread <= age_oldest, "age {age_spread} against {age_oldest}");
        assert!(skip_spread <= 2, "skipped {skip_spread}");
    }

    /// The byte-bounded log queue under a slow writer: bytes never exceed the budget.
    #[test]
    fn byte_bounded_queue_under_a_slow_consumer_stays_within_budget() {
        let q = Arc::new(BoundedQueue::new("log", 1 << 16, 10_000, FullPolicy::DropNewest));
        let c = q.clone();
        let consumer = std::thread::spawn(move || {
            let mut n = 0u64;
            while c.pop().is_some() {
                n += 1;
                std::thread::sleep(Duration::from_millis(1));
            }
            n
        });
        let mut max_bytes = 0;
        for i in 0..300usize {
            q.push(i, 1000 + (i % 7) * 300);
            max_bytes = max_bytes.max(q.stats().depth_bytes);
        }
        q.close();
        let n = consumer.join().unwrap();
        let s = q.stats();
        assert!(max_bytes <= 10_000, "{max_bytes} bytes queued");
        assert_eq!(n + s.dropped, 300);
        assert!(s.dropped > 0);
    }
}
