//! What a ray hits in the scene: the seabed, the pipe or the wreck ([`super::scene`] and
//! [`super::structures`] both make hits; [`super::materials`] colours them).

use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// What a ray hit, with the texture coordinates its material needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Surface {
    Seabed,
    /// Distance along the pipe and around its circumference, metres.
    Pipe { along_m: f64, around_m: f64 },
    /// Face coordinates in metres on a wreck part (0 hull, 1 wheelhouse, 2 mast).
    Wreck { part: u8, u: f64, v: f64 },
}

/// A ray hit: distance along the (unit) ray, point, unit normal facing the ray, surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub point: V3,
    pub normal: V3,
    pub surface: Surface,
}
