//! `duv-tools convert` end to end: a plain image folder becomes a TUM-layout folder that
//! `duv dataset` would read, with a summary line; bad sources fail with the reason.

use std::process::Command;

fn tools(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_duv-tools")).args(args).output().unwrap()
}

#[test]
fn converts_a_folder_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("src");
    std::fs::create_dir(&src).unwrap();
    let img = duv_core::ImageRgb8 { width: 4, height: 3, data: (0..36).collect() };
    for name in ["0.100000", "0.200000"] {
        duv_core::io::png_io::write_rgb8(&src.join(format!("{name}.png")), &img).unwrap();
    }
    std::fs::write(src.join("calibration.txt"), "3 3 1.5 1 4 3\n").unwrap();
    let out = dir.path().join("out");
    let o = tools(&["convert", "--source", &format!("folder:{}", src.display()), "--out", &out.display().to_string()]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("2 frames, 0 depth maps"), "{stdout}");
    let rgb_txt = std::fs::read_to_string(out.join("rgb.txt")).unwrap();
    assert!(rgb_txt.contains("0.100000000 rgb/0.100000000.png"), "{rgb_txt}");
    assert!(out.join("calibration.txt").is_file() && !out.join("groundtruth.txt").exists());
    let back = duv_camera::dataset::open_dataset(&format!("tum:{}", out.display())).unwrap();
    assert_eq!(back.load_frame(1).unwrap().image, duv_core::FrameImage::Rgb8(img));

    let o = tools(&["convert", "--source", "folder:/definitely/not/here", "--out", &dir.path().join("x").display().to_string()]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("is not a directory"));
}
