//! Camera buffer decoding at 640x480: `cargo bench --bench camera_decode`. Prints the median of
//! several runs of each pixel-format conversion (YUYV, GREY, RGB24, BayerRG8 into a reused
//! image; MJPEG of a 38 kB 4:2:2 frame through zune-jpeg) and the frame rate it alone allows.

use duv_camera::pixel::{bayer_rg8_to_rgb8, grey_to_gray8, mjpeg_to_rgb8, rgb24_to_rgb8, yuyv_to_rgb8};
use duv_core::{ImageGray8, ImageRgb8};
use std::time::Instant;

const MJPEG_640X480: &[u8] = include_bytes!("../tests/fixtures/camera/seabed_640x480.jpg");

fn median_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    f(); // warm-up: sizes the output image
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
    let raw: Vec<u8> = (0..w * h * 3).map(|i| ((i * 7) % 251) as u8).collect();
    let mut rgb = ImageRgb8::new(w, h);
    let mut grey = ImageGray8::new(w, h);
    let runs = 31;
    println!("640x480, median of {runs} runs:");
    let report = |name: &str, ms: f64| println!("  {name:<9} {ms:7.3} ms  ({:6.0} frames/s)", 1e3 / ms);
    report("YUYV", median_ms(runs, || yuyv_to_rgb8(&raw[..w * h * 2], w, h, w * 2, &mut rgb).unwrap()));
    report("GREY", median_ms(runs, || grey_to_gray8(&raw[..w * h], w, h, w, &mut grey).unwrap()));
    report("RGB24", median_ms(runs, || rgb24_to_rgb8(&raw, w, h, w * 3, &mut rgb).unwrap()));
    report("BayerRG8", median_ms(runs, || bayer_rg8_to_rgb8(&raw[..w * h], w, h, w, &mut rgb).unwrap()));
    report("MJPEG", median_ms(runs, || mjpeg_to_rgb8(MJPEG_640X480, w, h, &mut rgb).unwrap()));
    std::hint::black_box((&rgb, &grey));
}
