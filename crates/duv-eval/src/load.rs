//! Reading evaluation inputs from folders: rendered/reference image pairs and keyframe depth
//! maps with their variances and ground truth, paired by file name.

use super::ause::depth_errors;
use super::report::{AuseInput, EvalImage, ImagePair};
use super::EvalError;
use duv_core::PlaneF32;
use duv_core::io::{pfm, png_io, IoError};
use std::path::{Path, PathBuf};

/// Files directly in `dir` whose extension is one of `exts` (case-insensitive), sorted by name.
fn files_with_ext(dir: &Path, exts: &[&str]) -> Result<Vec<PathBuf>, EvalError> {
    let entries = std::fs::read_dir(dir).map_err(|e| IoError::file(dir, e))?;
    let mut out = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| IoError::file(dir, e))?.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
        if path.is_file() && ext.is_some_and(|e| exts.contains(&e.as_str())) {
            out.push(path);
        }
    }
    out.sort();
    Ok(out)
}

/// Image pairs read from two folders: every PNG in `rendered` with a PNG of the same file name
/// in `reference`. Returns the pairs and the names of rendered images without a reference.
pub fn load_image_pairs(rendered: &Path, reference: &Path) -> Result<(Vec<ImagePair>, Vec<String>), EvalError> {
    let mut pairs = Vec::new();
    let mut unmatched = Vec::new();
    for r_path in files_with_ext(rendered, &["png"])? {
        let Some(name) = r_path.file_name().map(|n| n.to_string_lossy().into_owned()) else { continue };
        let ref_path = reference.join(&name);
        if !ref_path.is_file() {
            unmatched.push(name);
            continue;
        }
        let r_img = png_io::read_image(&r_path)?;
        let ref_img = png_io::read_image(&ref_path)?;
        pairs.push(ImagePair {
            name,
            rendered_label: r_path.display().to_string(),
            reference_label: ref_path.display().to_string(),
            rendered: EvalImage::from(&r_img),
            reference: EvalImage::from(&ref_img),
        });
    }
    if pairs.is_empty() {
        return Err(EvalError::NoImagePairs { rendered: rendered.to_path_buf(), reference: reference.to_path_buf() });
    }
    Ok((pairs, unmatched))
}

/// A depth-like plane from a PFM file, or from a 16-bit PNG divided by `png_scale` (TUM depth:
/// 5000 per metre).
pub fn read_depth_plane(path: &Path, png_scale: f64) -> Result<PlaneF32, EvalError> {
    let is_png = path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if is_png {
        let raw = png_io::read_gray16(path)?;
        let data = raw.data.iter().map(|&v| (v as f64 / png_scale) as f32).collect();
        Ok(PlaneF32 { width: raw.width, height: raw.height, data })
    } else {
        Ok(pfm::read_pfm(path)?)
    }
}

/// AUSE inputs from three folders: every `NAME.pfm` (or 16-bit `NAME.png`) estimated depth in
/// `depth` with `NAME.*` in `variance` and in `gt_depth`. PNG depths are divided by
/// `png_scale`. Returns the inputs and the names skipped for want of a counterpart.
pub fn load_depth_inputs(depth: &Path, variance: &Path, gt_depth: &Path, png_scale: f64) -> Result<(Vec<AuseInput>, Vec<String>), EvalError> {
    if !(png_scale.is_finite() && png_scale > 0.0) {
        return Err(EvalError::InvalidParameter { name: "depth scale", value: png_scale.to_string(), reason: "must be a positive number" });
    }
    let find = |dir: &Path, stem: &str| -> Option<PathBuf> {
        ["pfm", "png"].iter().map(|ext| dir.join(format!("{stem}.{ext}"))).find(|p| p.is_file())
    };
    let mut inputs = Vec::new();
    let mut skipped = Vec::new();
    for d_path in files_with_ext(depth, &["pfm", "png"])? {
        let Some(stem) = d_path.file_stem().map(|s| s.to_string_lossy().into_owned()) else { continue };
        let (Some(v_path), Some(g_path)) = (find(variance, &stem), find(gt_depth, &stem)) else {
            skipped.push(stem);
            continue;
        };
        let est = read_depth_plane(&d_path, png_scale)?;
        let var = read_depth_plane(&v_path, png_scale)?;
        let gt = read_depth_plane(&g_path, png_scale)?;
        let (errors, uncertainties) = depth_errors(&est, &gt, &var).map_err(|e| e.within(d_path.display().to_string()))?;
        inputs.push(AuseInput { name: stem, errors, uncertainties });
    }
    if inputs.is_empty() {
        return Err(EvalError::NoDepthTriples { depth: depth.to_path_buf(), variance: variance.to_path_buf(), gt_depth: gt_depth.to_path_buf() });
    }
    Ok((inputs, skipped))
}

/// The ground-truth file: `path` itself, or `path/groundtruth.txt` for a dataset folder.
pub fn ground_truth_file(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("groundtruth.txt")
    } else {
        path.to_path_buf()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::{ImageGray8, ImageRgb8};

    #[test]
    fn pairs_by_name_and_reports_missing() {
        let dir = tempfile::tempdir().unwrap();
        let (r, f) = (dir.path().join("r"), dir.path().join("f"));
        std::fs::create_dir_all(&r).unwrap();
        std::fs::create_dir_all(&f).unwrap();
        let img = ImageRgb8::filled(12, 12, [10, 20, 30]);
        png_io::write_rgb8(&r.join("a.png"), &img).unwrap();
        png_io::write_rgb8(&f.join("a.png"), &img).unwrap();
        png_io::write_rgb8(&r.join("b.png"), &img).unwrap();
        let (pairs, missing) = load_image_pairs(&r, &f).unwrap();
        assert_eq!(pairs.len(), 1);
        assert_eq!(missing, vec!["b.png".to_string()]);
        // Grey against colour is named.
        png_io::write_gray8(&f.join("b.png"), &ImageGray8::filled(12, 12, [3])).unwrap();
        let (pairs, _) = load_image_pairs(&r, &f).unwrap();
        let e = pairs[1].scores(crate::SsimConvention::Skimage).unwrap_err();
        assert!(matches!(e, EvalError::ImageChannelMismatch { .. }) && e.to_string().contains("b.png"), "{e}");
        assert!(matches!(load_image_pairs(&f, &dir.path().join("nowhere")), Err(EvalError::NoImagePairs { .. })));
        assert!(matches!(load_image_pairs(&dir.path().join("nowhere"), &f), Err(EvalError::Io(_))));
    }
}
