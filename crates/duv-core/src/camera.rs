//! Pinhole camera with optional radial-tangential (Brown-Conrady / OpenCV `k1 k2 p1 p2 [k3]`)
//! distortion. Camera frame: x right, y down, z forward (optical axis); pixel centres at
//! integer coordinates, (0, 0) the centre of the top-left pixel.

use nalgebra::{Vector2, Vector3};

/// Radial-tangential distortion coefficients in OpenCV order.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RadTan {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

impl RadTan {
    /// Distorts a point on the normalised image plane (z = 1).
    pub fn distort(&self, xn: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Inverts [`RadTan::distort`] by Gauss-Newton from the distorted point. Converges in a few
    /// iterations for lenses within the model's valid field; returns `None` if it does not.
    pub fn undistort(&self, xd: Vector2<f64>) -> Option<Vector2<f64>> {
        let mut xu = xd;
        for _ in 0..30 {
            let f = self.distort(xu) - xd;
            if f.norm() < 1e-12 {
                return Some(xu);
            }
            let j = self.jacobian(xu);
            let step = j.try_inverse()? * f;
            xu -= step;
            if !xu.x.is_finite() || !xu.y.is_finite() {
                return None;
            }
        }
        ((self.distort(xu) - xd).norm() < 1e-9).then_some(xu)
    }

    /// d distort / d xn (2x2).
    pub fn jacobian(&self, xn: Vector2<f64>) -> nalgebra::Matrix2<f64> {
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d_radial_d_r2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let dxx = radial + x * d_radial_d_r2 * 2.0 * x + 2.0 * self.p1 * y + self.p2 * 6.0 * x;
        let dxy = x * d_radial_d_r2 * 2.0 * y + 2.0 * self.p1 * x + self.p2 * 2.0 * y;
        let dyx = y * d_radial_d_r2 * 2.0 * x + self.p1 * 2.0 * x + 2.0 * self.p2 * y;
        let dyy = radial + y * d_radial_d_r2 * 2.0 * y + self.p1 * 6.0 * y + 2.0 * self.p2 * x;
        nalgebra::Matrix2::new(dxx, dxy, dyx, dyy)
    }
}

/// Why a camera description is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraModelError {
    #[error("focal lengths must be finite and positive (fx={fx}, fy={fy})")]
    BadFocal { fx: f64, fy: f64 },
    #[error("principal point must be finite (cx={cx}, cy={cy})")]
    BadPrincipalPoint { cx: f64, cy: f64 },
    #[error("image size must be at least 2x2 pixels (got {width}x{height})")]
    BadSize { width: usize, height: usize },
    #[error("distortion coefficients must be finite")]
    BadDistortion,
}

/// Intrinsics of a pinhole camera and the image size they refer to.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PinholeCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
    pub distortion: Option<RadTan>,
}

impl PinholeCamera {
    /// A validated camera without distortion.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: usize, height: usize) -> Result<Self, CameraModelError> {
        let cam = PinholeCamera { fx, fy, cx, cy, width, height, distortion: None };
        cam.validate()?;
        Ok(cam)
    }

    pub fn with_distortion(mut self, distortion: RadTan) -> Result<Self, CameraModelError> {
        self.distortion = Some(distortion);
        self.validate()?;
        Ok(self)
    }

    pub fn validate(&self) -> Result<(), CameraModelError> {
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(CameraModelError::BadFocal { fx: self.fx, fy: self.fy });
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(CameraModelError::BadPrincipalPoint { cx: self.cx, cy: self.cy });
        }
        if self.width < 2 || self.height < 2 {
            return Err(CameraModelError::BadSize { width: self.width, height: self.height });
        }
        if let Some(d) = self.distortion {
            if ![d.k1, d.k2, d.p1, d.p2, d.k3].iter().all(|v| v.is_finite()) {
                return Err(CameraModelError::BadDistortion);
            }
        }
        Ok(())
    }

    /// A camera with the given horizontal field of view and the principal point at the centre.
    pub fn from_hfov(hfov_deg: f64, width: usize, height: usize) -> Result<Self, CameraModelError> {
        let fx = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
        Self::new(fx, fx, (width as f64 - 1.0) * 0.5, (height as f64 - 1.0) * 0.5, width, height)
    }

    /// The same camera for an image scaled by `factor` (e.g. 0.125 for 1/8 resolution);
    /// pixel centres stay consistent: `u' = (u + 0.5) * factor - 0.5`.
    pub fn scaled(&self, factor: f64) -> PinholeCamera {
        PinholeCamera {
            fx: self.fx * factor,
            fy: self.fy * factor,
            cx: (self.cx + 0.5) * factor - 0.5,
            cy: (self.cy + 0.5) * factor - 0.5,
            width: ((self.width as f64 * factor).round() as usize).max(1),
            height: ((self.height as f64 * factor).round() as usize).max(1),
            distortion: self.distortion,
        }
    }

    /// This camera without its distortion (the model of undistorted images).
    pub fn undistorted(&self) -> PinholeCamera {
        PinholeCamera { distortion: None, ..*self }
    }

    /// Projects a point in the camera frame to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        if !(p_in_cam.z > 1e-12) {
            return None;
        }
        let xn = Vector2::new(p_in_cam.x / p_in_cam.z, p_in_cam.y / p_in_cam.z);
        let xd = match &self.distortion {
            Some(d) => d.distort(xn),
            None => xn,
        };
        Some(Vector2::new(self.fx * xd.x + self.cx, self.fy * xd.y + self.cy))
    }

    /// The normalised-plane point (z = 1) seen at pixel `uv`, undistorting if needed.
    pub fn unproject(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        let xd = Vector2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy);
        let xn = match &self.distortion {
            Some(d) => d.undistort(xd)?,
            None => xd,
        };
        Some(Vector3::new(xn.x, xn.y, 1.0))
    }

    /// Unit-length viewing ray through pixel `uv`.
    pub fn ray(&self, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        self.unproject(uv).map(|v| v.normalize())
    }

    pub fn contains(&self, uv: &Vector2<f64>) -> bool {
        uv.x >= -0.5 && uv.y >= -0.5 && uv.x < self.width as f64 - 0.5 && uv.y < self.height as f64 - 0.5
    }

    /// For each pixel of the undistorted image (modelled by [`Self::undistorted`]), the
    /// position to sample in the distorted input image. Computed once; apply with
    /// [`UndistortMap::apply_rgb8`].
    pub fn undistort_map(&self) -> UndistortMap {
        let mut map = Vec::with_capacity(self.width * self.height);
        for v in 0..self.height {
            for u in 0..self.width {
                let xn = Vector2::new((u as f64 - self.cx) / self.fx, (v as f64 - self.cy) / self.fy);
                let xd = match &self.distortion {
                    Some(d) => d.distort(xn),
                    None => xn,
                };
                map.push([(self.fx * xd.x + self.cx) as f32, (self.fy * xd.y + self.cy) as f32]);
            }
        }
        UndistortMap { width: self.width, height: self.height, source_xy: map }
    }
}

/// A precomputed remap from an undistorted image to sample positions in the distorted one.
#[derive(Clone, Debug)]
pub struct UndistortMap {
    pub width: usize,
    pub height: usize,
    pub source_xy: Vec<[f32; 2]>,
}

impl UndistortMap {
    /// Bilinear remap of an RGB image of the map's size; pixels that fall outside are black.
    /// `out` must have the map's size (it is reused, so no allocation per frame).
    pub fn apply_rgb8(&self, input: &super::frame::ImageRgb8, out: &mut super::frame::ImageRgb8) {
        assert!(input.width == self.width && input.height == self.height && out.same_size(input));
        let (w, h) = (self.width, self.height);
        for (i, &[sx, sy]) in self.source_xy.iter().enumerate() {
            let o = &mut out.data[i * 3..i * 3 + 3];
            if !(sx >= 0.0 && sy >= 0.0 && sx <= (w - 1) as f32 && sy <= (h - 1) as f32) {
                o.fill(0);
                continue;
            }
            let x0 = (sx as usize).min(w - 2);
            let y0 = (sy as usize).min(h - 2);
            let (ax, ay) = (sx - x0 as f32, sy - y0 as f32);
            for c in 0..3 {
                let p = |x: usize, y: usize| input.data[(y * w + x) * 3 + c] as f32;
                let v = (p(x0, y0) * (1.0 - ax) + p(x0 + 1, y0) * ax) * (1.0 - ay)
                    + (p(x0, y0 + 1) * (1.0 - ax) + p(x0 + 1, y0 + 1) * ax) * ay;
                o[c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lens() -> RadTan {
        // A typical wide underwater housing lens (EuRoC cam0-like magnitudes).
        RadTan { k1: -0.283, k2: 0.074, p1: 1.9e-4, p2: 1.8e-5, k3: 0.0 }
    }

    #[test]
    fn project_unproject_round_trip_with_distortion() {
        let cam = PinholeCamera::new(458.6, 457.3, 367.2, 248.4, 752, 480).unwrap().with_distortion(lens()).unwrap();
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.5, 0.35), (0.6, 0.4)] {
            let p = Vector3::new(x * 2.0, y * 2.0, 2.0);
            let uv = cam.project(&p).unwrap();
            let back = cam.unproject(&uv).unwrap();
            assert!((back - Vector3::new(x, y, 1.0)).norm() < 1e-9, "{x} {y}: {back:?}");
        }
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn distortion_jacobian_matches_central_differences() {
        let d = lens();
        let x = Vector2::new(0.31, -0.27);
        let j = d.jacobian(x);
        let h = 1e-6;
        for k in 0..2 {
            let mut e = Vector2::zeros();
            e[k] = h;
            let num = (d.distort(x + e) - d.distort(x - e)) / (2.0 * h);
            assert!((num - j.column(k)).norm() < 1e-8);
        }
    }

    #[test]
    fn rejects_bad_intrinsics() {
        assert!(matches!(PinholeCamera::new(0.0, 1.0, 0.0, 0.0, 10, 10), Err(CameraModelError::BadFocal { .. })));
        assert!(matches!(PinholeCamera::new(1.0, 1.0, f64::NAN, 0.0, 10, 10), Err(CameraModelError::BadPrincipalPoint { .. })));
        assert!(matches!(PinholeCamera::new(1.0, 1.0, 0.0, 0.0, 1, 10), Err(CameraModelError::BadSize { .. })));
    }

    #[test]
    fn scaled_camera_keeps_rays() {
        let cam = PinholeCamera::new(320.0, 320.0, 319.5, 239.5, 640, 480).unwrap();
        let small = cam.scaled(0.125);
        assert_eq!((small.width, small.height), (80, 60));
        let p = Vector3::new(0.4, -0.2, 3.0);
        let a = cam.project(&p).unwrap();
        let b = small.project(&p).unwrap();
        assert!(((a.x + 0.5) * 0.125 - 0.5 - b.x).abs() < 1e-12);
        assert!(((a.y + 0.5) * 0.125 - 0.5 - b.y).abs() < 1e-12);
    }
}
