//! The untiled f64 reference renderer: every pixel blends every projected Gaussian in depth
//! order, with the same generic per-Gaussian and per-pixel code as the f32 pipeline but no
//! tiles, sort keys or capacities. The gradient checks differentiate it numerically.

use super::project::{project_splat, ProjectedSplat, ProjectionSetup};
use super::raster_fwd::{blend_pixel, PixelForward, PixelMedium, PixelRay};
use super::{MediumPlanes, RenderConfig, RenderError};
use duv_core::{PinholeCamera, Se3};
use crate::gaussians::GaussianParam;

/// The projected Gaussians of one view, sorted by depth (ties by index, as the stable sort
/// of the pipeline).
#[derive(Clone, Debug)]
pub struct ReferenceView {
    pub setup: ProjectionSetup<f64>,
    pub config: RenderConfig,
    pub splats: Vec<ProjectedSplat<f64>>,
}

impl ReferenceView {
    pub fn new(
        params: &[GaussianParam<f64>],
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        config: &RenderConfig,
    ) -> Result<Self, RenderError> {
        let setup = ProjectionSetup::<f64>::new(camera, cam_from_world, config)?;
        let mut projected: Vec<(f64, usize, ProjectedSplat<f64>)> =
            params.iter().enumerate().filter_map(|(i, p)| project_splat(p, &setup).map(|(s, _)| (s.z, i, s))).collect();
        projected.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Ok(ReferenceView { setup, config: *config, splats: projected.into_iter().map(|(_, _, s)| s).collect() })
    }

    /// Renders pixel `(x, y)` with the given medium.
    pub fn pixel(&self, x: usize, y: usize, medium: &PixelMedium<f64>) -> PixelForward<f64> {
        let s = &self.setup;
        let ray = PixelRay::new(x, y, s.fx, s.fy, s.cx, s.cy);
        blend_pixel(0..self.splats.len(), |k| self.splats[k], &ray, medium, self.config.depth_mode)
    }
}

/// The medium of pixel `(x, y)` in f64.
pub fn medium_f64(medium: &MediumPlanes, x: usize, y: usize) -> PixelMedium<f64> {
    let m = medium.pixel(x, y);
    PixelMedium { c_med: m.c_med.map(f64::from), sigma_att: m.sigma_att.map(f64::from), sigma_bs: m.sigma_bs.map(f64::from) }
}

/// Renders every pixel (row-major).
pub fn render_reference(
    params: &[GaussianParam<f64>],
    camera: &PinholeCamera,
    cam_from_world: &Se3,
    medium: &MediumPlanes,
    config: &RenderConfig,
) -> Result<Vec<PixelForward<f64>>, RenderError> {
    let view = ReferenceView::new(params, camera, cam_from_world, config)?;
    let mut out = Vec::with_capacity(camera.width * camera.height);
    for y in 0..camera.height {
        for x in 0..camera.width {
            out.push(view.pixel(x, y, &medium_f64(medium, x, y)));
        }
    }
    Ok(out)
}
