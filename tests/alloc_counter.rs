//! The counting allocator itself: counts, scopes, and live / peak bytes.

use duv_core::alloc::{self, CountScope, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

#[test]
fn counts_scopes_and_bytes() {
    assert!(alloc::is_installed());
    // Counted on this thread when marked; not counted when the scope is marked threads and
    // the allocating thread is unmarked.
    assert_eq!(alloc::count_allocations_on_this_thread(|| drop(std::hint::black_box(vec![1u8; 10]))), 1);
    let unmarked = alloc::count_allocations(CountScope::MarkedThreads, || {
        std::thread::scope(|s| drop(s.spawn(|| std::hint::black_box(vec![1u8; 10])).join()));
    });
    let all = alloc::count_allocations(CountScope::AllThreads, || {
        std::thread::scope(|s| drop(s.spawn(|| std::hint::black_box(vec![1u8; 10])).join()));
    });
    assert!(all > unmarked, "all threads {all}, marked only {unmarked}");

    // A live 8 MiB block shows in live and peak bytes, and leaves live bytes when freed.
    let before = alloc::live_bytes();
    alloc::reset_peak_bytes();
    let block = std::hint::black_box(vec![0u8; 8 << 20]);
    assert!(alloc::live_bytes() >= before + (8 << 20));
    drop(block);
    assert!(alloc::peak_bytes() >= before + (8 << 20));
    assert!(alloc::live_bytes() < before + (8 << 20));
}
