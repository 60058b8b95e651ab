//! Projection forward on the device (`project_forward.wgsl`), twin of `render::project`: the
//! splat layout, the setup words, [`GpuProjection`].

use super::ops::{record_exclusive_scan, ScanScratch};
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::gaussians::{Gaussians, PARAMS_PER_GAUSSIAN};
use crate::render::{
    ProjectedSplat, ProjectionSetup, TileGrid, TileRect,
};

/// Floats per projected splat on the GPU: three vec4s, `mean2d, conic[0..2] | conic[2], z,
/// opacity, q_max | colour, 0` (what the rasterisers load as vectors; [`splat_floats`]).
pub const SPLAT_FLOATS: usize = 12;

/// A [`ProjectedSplat`] in the GPU layout ([`SPLAT_FLOATS`]).
pub fn splat_floats(s: &ProjectedSplat<f32>) -> [f32; SPLAT_FLOATS] {
    [s.mean2d[0], s.mean2d[1], s.conic[0], s.conic[1], s.conic[2], s.z, s.opacity, s.q_max, s.colour[0], s.colour[1], s.colour[2], 0.0]
}
/// Words of the `Setup` struct of `project_forward.wgsl`.
pub const SETUP_WORDS: usize = 32;

/// The `Setup` struct of `project_forward.wgsl` as words: the [`ProjectionSetup`] floats, then
/// `n, width, height, tile_size, tiles_x, tiles_y` as u32.
pub fn projection_setup_words(s: &ProjectionSetup<f32>, grid: &TileGrid, n: usize) -> [u32; SETUP_WORDS] {
    let r = &s.cam_from_world_rot;
    let floats = [
        r[0][0],
        r[0][1],
        r[0][2],
        r[1][0],
        r[1][1],
        r[1][2],
        r[2][0],
        r[2][1],
        r[2][2],
        s.cam_from_world_trans[0],
        s.cam_from_world_trans[1],
        s.cam_from_world_trans[2],
        s.cam_centre_in_world[0],
        s.cam_centre_in_world[1],
        s.cam_centre_in_world[2],
        s.fx,
        s.fy,
        s.cx,
        s.cy,
        s.lim_x[0],
        s.lim_x[1],
        s.lim_y[0],
        s.lim_y[1],
        s.near_z,
        s.blur,
    ];
    let mut w = [0u32; SETUP_WORDS];
    for (o, f) in w.iter_mut().zip(floats) {
        *o = f.to_bits();
    }
    let ints = [n, grid.width, grid.height, grid.tile_size, grid.tiles_x, grid.tiles_y, 0];
    for (o, v) in w[floats.len()..].iter_mut().zip(ints) {
        *o = v as u32;
    }
    w
}

/// Projection and tile-count scan buffers for up to `capacity` Gaussians.
pub struct GpuProjection {
    pub capacity: usize,
    pub setup: GpuBuffer<u32>,
    /// [`PARAMS_PER_GAUSSIAN`] floats per Gaussian, [`crate::gaussians::GaussianParam::to_array`] order.
    pub params: GpuBuffer<f32>,
    pub splats: GpuBuffer<f32>,
    pub rects: GpuBuffer<[u32; 4]>,
    pub tiles_touched: GpuBuffer<u32>,
    /// `capacity + 1` exclusive offsets of the tile counts.
    pub isect_offsets: GpuBuffer<u32>,
    pub scan: ScanScratch,
    /// Host staging of the parameters and the offsets (allocated once).
    staging: Vec<f32>,
    pub(crate) staging_offsets: Vec<u32>,
}

impl GpuProjection {
    pub fn new(ctx: &mut GpuContext, capacity: usize) -> Result<Self, GpuError> {
        Ok(GpuProjection {
            capacity,
            setup: ctx.alloc("projection setup", SETUP_WORDS)?,
            params: ctx.alloc("Gaussian parameters", capacity * PARAMS_PER_GAUSSIAN)?,
            splats: ctx.alloc("projected splats", capacity * SPLAT_FLOATS)?,
            rects: ctx.alloc("tile rectangles", capacity)?,
            tiles_touched: ctx.alloc("tiles touched", capacity)?,
            isect_offsets: ctx.alloc("intersection offsets", capacity + 1)?,
            scan: ScanScratch::new(ctx, capacity)?,
            staging: vec![0.0; capacity * PARAMS_PER_GAUSSIAN],
            staging_offsets: vec![0; capacity + 1],
        })
    }

    /// Uploads the map (SoA on the host, AoS on the GPU).
    pub fn upload(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians) -> Result<(), GpuError> {
        let n = gaussians.len();
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity });
        }
        for i in 0..n {
            self.staging[i * PARAMS_PER_GAUSSIAN..(i + 1) * PARAMS_PER_GAUSSIAN].copy_from_slice(&gaussians.get(i).to_array());
        }
        ctx.write(&self.params, &self.staging[..n * PARAMS_PER_GAUSSIAN])
    }

    /// Reads the device map into `gaussians` (its `len()` Gaussians; AoS on the GPU, SoA on
    /// the host).
    pub fn read_params(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians) -> Result<(), GpuError> {
        let n = gaussians.len();
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity });
        }
        ctx.read(&self.params, &mut self.staging[..n * PARAMS_PER_GAUSSIAN])?;
        gaussians
            .copy_from_aos(&self.staging[..n * PARAMS_PER_GAUSSIAN])
            .map_err(|_| GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity })
    }

    /// Records `project_forward` over `n` Gaussians (setup written by
    /// [`GpuProjection::write_setup`]), then the exclusive scan of the tile counts with
    /// `max_intersections` as the limit.
    pub fn record(&self, ctx: &mut GpuContext, n: usize, max_intersections: usize) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "projected splats", requested: n, len: self.capacity });
        }
        if n == 0 {
            return Ok(());
        }
        let bufs = [self.setup.range(), self.params.range(), self.splats.range(), self.rects.range(), self.tiles_touched.range()];
        ctx.dispatch(Kernel::ProjectForwardProjectForward, &bufs, &[], [n.div_ceil(256) as u32, 1, 1])?;
        record_exclusive_scan(ctx, &self.tiles_touched, n, &self.isect_offsets, &self.scan, max_intersections.min(u32::MAX as usize) as u32)
    }

    /// Writes the camera/pose setup for `n` Gaussians (before `begin()`).
    pub fn write_setup(&self, ctx: &mut GpuContext, setup: &ProjectionSetup<f32>, grid: &TileGrid, n: usize) -> Result<(), GpuError> {
        ctx.write(&self.setup, &projection_setup_words(setup, grid, n))
    }

    /// Reads the splats, rectangles and counts of `n` Gaussians back (tests, debugging).
    pub fn read(
        &self,
        ctx: &GpuContext,
        n: usize,
        splats: &mut [ProjectedSplat<f32>],
        rects: &mut [TileRect],
        tiles_touched: &mut [u32],
    ) -> Result<(), GpuError> {
        let mut raw = vec![0.0f32; n * SPLAT_FLOATS];
        ctx.read(&self.splats, &mut raw)?;
        for (s, r) in splats[..n].iter_mut().zip(raw.chunks_exact(SPLAT_FLOATS)) {
            *s = ProjectedSplat {
                mean2d: [r[0], r[1]],
                conic: [r[2], r[3], r[4]],
                z: r[5],
                opacity: r[6],
                colour: [r[8], r[9], r[10]],
                q_max: r[7],
            };
        }
        let mut raw_rects = vec![[0u32; 4]; n];
        ctx.read(&self.rects, &mut raw_rects)?;
        for (r, w) in rects[..n].iter_mut().zip(&raw_rects) {
            *r = TileRect { x0: w[0], y0: w[1], x1: w[2], y1: w[3] };
        }
        ctx.read(&self.tiles_touched, &mut tiles_touched[..n])
    }
}
