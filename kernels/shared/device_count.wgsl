// Shared by radix_sort.wgsl and tile_ranges.wgsl (`//!include device_count.wgsl`; it needs
// their `count` binding): a count the host passes in the immediates, or, when it passes
// COUNT_ON_DEVICE (`gpu::ops::COUNT_ON_DEVICE`), the one an earlier kernel of the submission
// wrote to count[0] (the host then dispatched the kernels after it indirectly).

const COUNT_ON_DEVICE: u32 = 0xffffffffu;

fn host_or_device_count(host: u32) -> u32 {
    if (host == COUNT_ON_DEVICE) {
        return count[0];
    }
    return host;
}
