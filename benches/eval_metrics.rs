//! Image metrics at 640x480: `cargo bench --bench eval_metrics`. Prints the median of several
//! runs of PSNR and SSIM (both conventions) on RGB and grey images.

use duv_core::{ImageRgbF32, PlaneF32};
use duv_eval::{psnr, ssim, SsimConvention};
use std::time::Instant;

fn median_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    f(); // warm-up
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[runs / 2]
}

fn main() {
    let (w, h) = (640, 480);
    let val = |i: usize, k: usize| ((i * k) % 251) as f32 / 255.0;
    let a = ImageRgbF32::from_vec(w, h, (0..w * h * 3).map(|i| val(i, 7)).collect()).unwrap();
    let b = ImageRgbF32::from_vec(w, h, (0..w * h * 3).map(|i| 0.9 * val(i, 7) + 0.1 * val(i, 13)).collect()).unwrap();
    let ga = PlaneF32::from_vec(w, h, (0..w * h).map(|i| val(i, 7)).collect()).unwrap();
    let gb = PlaneF32::from_vec(w, h, (0..w * h).map(|i| 0.9 * val(i, 7) + 0.1 * val(i, 13)).collect()).unwrap();
    let threads = rayon::current_num_threads();
    println!("640x480, {threads} rayon thread(s), median of 15 runs:");
    println!("  psnr rgb            {:7.2} ms", median_ms(15, || {
        std::hint::black_box(psnr(&a, &b).unwrap());
    }));
    for conv in [SsimConvention::Skimage, SsimConvention::Same] {
        println!("  ssim rgb  {:<9} {:7.2} ms", conv.to_string(), median_ms(15, || {
            std::hint::black_box(ssim(&a, &b, conv).unwrap());
        }));
        println!("  ssim grey {:<9} {:7.2} ms", conv.to_string(), median_ms(15, || {
            std::hint::black_box(ssim(&ga, &gb, conv).unwrap());
        }));
    }
}
