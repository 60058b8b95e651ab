//! [`ItemEncoder`]: log items into message bodies in the log's format (the Foxglove schemas,
//! [`super::schema`], or a ROS 2 bag's CDR, [`super::ros2`]), and the schema of each topic in
//! that format. Above both formats, so neither imports the other.

use super::schema::{encode_item, Encoded, FrameEncoding, LogFormat, LogItem, Templates, Topic, TopicSchema};
use super::LogError;
use duv_core::{Se3, Timestamp};

/// Encodes [`LogItem`]s into MCAP message bodies, with the buffers it reuses from item to item
/// (the message body and the JPEG stream) and the frame encoding.
#[derive(Debug, Default)]
pub struct ItemEncoder {
    format: LogFormat,
    frames: FrameEncoding,
    scratch: Vec<u8>,
    jpeg: Vec<u8>,
    templates: Templates,
    /// The previous pose (ROS 2 format: the odometry's velocity).
    odometry_prev: Option<(Timestamp, Se3)>,
}

impl ItemEncoder {
    pub fn new(frames: FrameEncoding) -> Self {
        Self::with_format(LogFormat::Foxglove, frames)
    }

    pub fn with_format(format: LogFormat, frames: FrameEncoding) -> Self {
        ItemEncoder { format, frames, scratch: Vec::new(), jpeg: Vec::new(), templates: Templates::default(), odometry_prev: None }
    }

    pub fn frame_encoding(&self) -> FrameEncoding {
        self.frames
    }

    pub fn format(&self) -> LogFormat {
        self.format
    }

    /// Encodes `item` into one or more messages; `emit` gets each with its body.
    pub fn encode(&mut self, item: &LogItem, emit: impl FnMut(Encoded, &[u8]) -> Result<(), LogError>) -> Result<(), LogError> {
        match self.format {
            LogFormat::Foxglove => encode_item(item, self.frames, &mut self.scratch, &mut self.jpeg, &mut self.templates, emit),
            LogFormat::Ros2 => super::ros2::encode_item(item, self.frames, &mut self.scratch, &mut self.jpeg, &mut self.templates.jpeg, &mut self.odometry_prev, emit),
        }
    }
}

/// The schema of the topic in `format` (see [`Topic::schema_for`]); every topic has one in
/// the ROS 2 format.
pub fn schema_in(topic: Topic, format: LogFormat, frames: FrameEncoding) -> Option<TopicSchema> {
    match format {
        LogFormat::Foxglove => topic.schema_for(frames),
        LogFormat::Ros2 => Some(super::ros2::topic_schema(topic, frames)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::*;
    use crate::schema::field2_wire_type;
    use duv_core::{Frame, FrameImage, Keyframe, PinholeCamera, Se3, Timestamp};
    use foxglove::messages as fg;
    use foxglove::Encode;
    use nalgebra::{Translation3, UnitQuaternion};
    use duv_core::ImageRgb8;

    #[test]
    fn navigation_samples_round_trip_in_both_formats() {
        use duv_core::nav::NavSample;
        let full = NavSample {
            t_ns: Timestamp::from_ns(2_345_000_001),
            depth_m: Some(12.25),
            altitude_m: Some(2.5),
            vel_cam_mps: Some(nalgebra::Vector3::new(0.1, -0.02, 0.5)),
            world_from_cam_rot: Some(UnitQuaternion::from_euler_angles(0.3, -0.1, 2.0)),
        };
        let depth_only = NavSample { depth_m: Some(7.0), ..NavSample::empty(Timestamp::from_ns(9)) };
        for format in LogFormat::ALL {
            let mut enc = ItemEncoder::with_format(format, FrameEncoding::Raw);
            for sample in [full, depth_only] {
                let mut got = Vec::new();
                enc.encode(&LogItem::Nav(sample), |e, b| {
                    got.push((e.topic, e.log_time_ns, b.to_vec()));
                    Ok(())
                })
                .unwrap();
                assert_eq!((got.len(), got[0].0, got[0].1), (1, Topic::Nav, sample.t_ns.t_ns() as u64), "{format:?}");
                let back = decode_nav(&got[0].2).unwrap();
                assert_eq!((back.t_ns, back.depth_m, back.altitude_m, back.vel_cam_mps), (sample.t_ns, sample.depth_m, sample.altitude_m, sample.vel_cam_mps), "{format:?}");
                match (back.world_from_cam_rot, sample.world_from_cam_rot) {
                    (Some(a), Some(b)) => assert!(a.angle_to(&b) < 1e-12, "{format:?}"),
                    (a, b) => assert_eq!(a.is_none(), b.is_none(), "{format:?}"),
                }
            }
        }
        assert!(decode_nav(b"{\"depth_m\": 3}").is_err(), "no time");
    }

    #[test]
    fn frame_and_pose_round_trip() {
        let mut img = ImageRgb8::new(5, 3);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i * 7 % 251) as u8;
        }
        let frame = Frame { t_ns: Timestamp::from_ns(1_500_000_123), seq: 42, image: FrameImage::Rgb8(img) };
        let mut enc = ItemEncoder::new(FrameEncoding::Raw);
        let mut got = Vec::new();
        enc.encode(&LogItem::Frame(std::sync::Arc::new(frame.clone())), |e, b| {
            got.push((e.topic, e.sequence, e.log_time_ns, b.to_vec()));
            Ok(())
        })
        .unwrap();
        assert_eq!(got.len(), 1);
        assert_eq!((got[0].0, got[0].1, got[0].2), (Topic::CameraImage, 42, 1_500_000_123));
        assert_eq!(decode_frame(&got[0].3, 42, 0).unwrap(), frame);

        let pose = Se3::from_parts(Translation3::new(1.0, -2.0, 0.5), UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3));
        let rec = PoseRecord { t_ns: Timestamp::from_ns(7), seq: 3, world_from_cam: pose, state: "tracking", tracked: true, keyframe: Some(1), new_keyframe: None, loop_closed: false, segment: 2, why: None, value: None, limit: None };
        got.clear();
        enc.encode(&LogItem::Pose(rec), |e, b| {
            got.push((e.topic, e.sequence, e.log_time_ns, b.to_vec()));
            Ok(())
        })
        .unwrap();
        assert_eq!(got.iter().map(|g| g.0).collect::<Vec<_>>(), vec![Topic::Pose, Topic::Transform, Topic::State]);
        let back = decode_pose(&got[0].3).unwrap();
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-12);
        let state: StateMessage = serde_json::from_slice(&got[2].3).unwrap();
        assert_eq!((state.seq, state.state.as_str(), state.keyframe, state.segment), (3, "tracking", Some(1), 2));
        assert_eq!(Topic::from_name("/slam/pose"), Some(Topic::Pose));
        assert_eq!(Topic::CameraImage.schema().unwrap().name, "foxglove.RawImage");
        assert_eq!(Topic::Pose.schema().unwrap().name, "foxglove.PoseInFrame");
        assert_eq!(Topic::Transform.schema().unwrap().name, "foxglove.FrameTransform");
        assert_eq!(Topic::MapGaussians.schema().unwrap().name, "foxglove.PointCloud");
        assert_eq!(Topic::CameraCalibration.schema().unwrap().encoding, "protobuf");
    }

    /// A smooth test image (JPEG's case: gradients and a few edges, like a seabed).
    fn smooth(w: usize, h: usize) -> ImageRgb8 {
        let mut img = ImageRgb8::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let v = [(x * 255 / w) as u8, (y * 255 / h) as u8, if (x / 8 + y / 8) % 2 == 0 { 60 } else { 190 }];
                img.set_pixel(x, y, v);
            }
        }
        img
    }

    #[test]
    fn jpeg_frames_round_trip_colour_and_grey() {
        let mut enc = ItemEncoder::new(FrameEncoding::Jpeg { quality: 90 });
        let rgb = smooth(37, 23); // not a multiple of the 8x8 / 16x16 MCU
        let grey = duv_core::ImageGray8::from_vec(37, 23, rgb.data.iter().step_by(3).copied().collect()).unwrap();
        for image in [FrameImage::Rgb8(rgb.clone()), FrameImage::Gray8(grey)] {
            let frame = Frame { t_ns: Timestamp::from_ns(2_000_000_007), seq: 9, image };
            let mut body = Vec::new();
            enc.encode(&LogItem::Frame(std::sync::Arc::new(frame.clone())), |e, b| {
                assert_eq!((e.topic, e.sequence, e.log_time_ns), (Topic::CameraImage, 9, 2_000_000_007));
                body = b.to_vec();
                Ok(())
            })
            .unwrap();
            assert_eq!(field2_wire_type(&body), Some(2), "CompressedImage carries its data in field 2");
            let back = decode_frame(&body, 9, 0).unwrap();
            assert_eq!((back.t_ns, back.seq), (frame.t_ns, 9));
            let (a, b): (&[u8], &[u8]) = match (&frame.image, &back.image) {
                (FrameImage::Rgb8(a), FrameImage::Rgb8(b)) => (&a.data, &b.data),
                (FrameImage::Gray8(a), FrameImage::Gray8(b)) => (&a.data, &b.data),
                _ => panic!("colour kind changed"),
            };
            let mse = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
            let psnr = 10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10();
            assert!(psnr > 30.0, "quality 90: PSNR {psnr:.1} dB");
        }
        assert_eq!(Topic::CameraImage.schema_for(FrameEncoding::Jpeg { quality: 90 }).unwrap().name, "foxglove.CompressedImage");
        assert_eq!(Topic::CameraImage.schema_for(FrameEncoding::Raw).unwrap().name, "foxglove.RawImage");
        assert_eq!(Topic::KeyframeImage.schema_for(FrameEncoding::Jpeg { quality: 90 }).unwrap().name, "foxglove.RawImage");
    }

    #[test]
    fn bad_jpeg_input_is_an_error_not_a_panic() {
        let img = FrameImage::Rgb8(smooth(16, 16));
        let e = encode_jpeg(&img, 0, &mut Vec::new()).unwrap_err();
        assert!(e.to_string().contains("quality 0"), "{e}");
        // A CompressedImage whose JPEG is cut short, and one in another format.
        let mut out = Vec::new();
        encode_jpeg(&img, 80, &mut out).unwrap();
        for (data, format, want) in [(out[..out.len() / 2].to_vec(), "jpeg", "jpeg"), (out.clone(), "png", "format \"png\"")] {
            let msg = fg::CompressedImage { timestamp: None, frame_id: String::new(), data: data.into(), format: format.into() };
            let mut body = Vec::new();
            msg.encode(&mut body).unwrap();
            let e = decode_frame(&body, 0, 0).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
        assert!(decode_frame(&[0xff, 0xff, 0xff], 0, 0).is_err());
    }

    #[test]
    fn keyframe_planes_round_trip_and_bad_planes_are_errors() {
        let camera = PinholeCamera::new(50.0, 50.0, 2.0, 1.5, 4, 3).unwrap();
        let mut inv = duv_core::PlaneF32::new(4, 3);
        let mut var = duv_core::PlaneF32::new(4, 3);
        // Inverse depths over the range underwater (1/m), variances from subnormal-f16 small to
        // beyond f16's range, infinity and NaN.
        let vars = [0.0, 3e-8, 1e-6, 5e-5, 1e-4, 0.01, 0.37, 12.5, 6e4, 1e9, f32::INFINITY, f32::NAN];
        for (i, (d, v)) in inv.data.iter_mut().zip(var.data.iter_mut()).enumerate() {
            *d = 0.0123 + i as f32 * 0.7311;
            *v = vars[i];
        }
        let kf = Keyframe { index: 9, t_ns: Timestamp::from_ns(3_000_000_001), image: ImageRgb8::new(4, 3), world_from_cam: Se3::identity(), camera, inv_depth: inv.clone(), inv_depth_variance: var.clone() };
        let (mut scratch, mut jpeg) = (Vec::new(), Vec::new());
        let mut got = Vec::new();
        encode_item(&LogItem::Keyframe(std::sync::Arc::new(kf)), FrameEncoding::Raw, &mut scratch, &mut jpeg, &mut Templates::default(), |e, b| {
            got.push((e.topic, e.sequence, b.to_vec()));
            Ok(())
        })
        .unwrap();
        assert_eq!(got.iter().map(|g| (g.0, g.1)).collect::<Vec<_>>(), vec![(Topic::KeyframeImage, 9), (Topic::KeyframeInvDepth, 9), (Topic::KeyframeVariance, 9), (Topic::KeyframePose, 9)]);
        // Logged as f16: half the bytes of f32, within the bound the schema states.
        let (d16, v16) = (decode_plane_f32(&got[1].2).unwrap(), decode_plane_f32(&got[2].2).unwrap());
        assert!(got[1].2.len() < 12 * 2 + 64 && got[1].2.len() >= 12 * 2, "{} bytes", got[1].2.len());
        let within = |x: f32, y: f32| {
            if x.is_nan() {
                return y.is_nan();
            }
            if x.is_infinite() {
                return y == x;
            }
            if x.abs() > 65504.0 {
                return y == 65504.0f32.copysign(x);
            }
            let bound = if x.abs() >= 6.104e-5 { x.abs() * 2f32.powi(-11) } else { 2f32.powi(-25) };
            (x - y).abs() <= bound
        };
        for (planes, name) in [((&inv, &d16), "inverse depth"), ((&var, &v16), "variance")] {
            for (&x, &y) in planes.0.data.iter().zip(&planes.1.data) {
                assert!(within(x, y), "{name}: {x} logged as {y}");
            }
        }
        assert!(d16.data.iter().zip(&inv.data).any(|(a, b)| a != b), "f16 is lossy for these values");
        assert_eq!(v16.data[9], 65504.0);
        // A 32FC1 plane (an older log) is read exactly.
        let mut old = Vec::new();
        let mut tpl = fg::RawImage { encoding: String::new(), ..Default::default() };
        crate::schema::encode_raw_image_for_test(&mut tpl, Timestamp::from_ns(1), 4, 3, "32FC1", 16, &var.data, &mut old);
        let back = decode_plane_f32(&old).unwrap();
        assert!(back.data.iter().zip(&var.data).all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
        let err = decode_plane_f32(&got[0].2).unwrap_err().to_string();
        assert!(err.contains("rgb8"), "{err}");
    }

    #[test]
    fn odometry_carries_the_velocity_since_the_previous_pose_in_the_camera_frame() {
        use crate::cdr::decode_odometry;
        
        use nalgebra::{Translation3, UnitQuaternion, Vector3};
        let rot0 = UnitQuaternion::from_euler_angles(0.2, -0.1, 0.5);
        // 0.1 s later: moved 5 cm along world x, turned 0.02 rad about the camera's own y.
        let rot1 = rot0 * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.02);
        let p0 = Se3::from_parts(Translation3::new(1.0, 2.0, 3.0), rot0);
        let p1 = Se3::from_parts(Translation3::new(1.05, 2.0, 3.0), rot1);
        let rec = |seq: u64, t: i64, p: Se3| PoseRecord { t_ns: Timestamp::from_ns(t), seq, world_from_cam: p, state: "tracking", tracked: true, keyframe: None, new_keyframe: None, loop_closed: false, segment: 0, why: None, value: None, limit: None };
        let mut enc = ItemEncoder::with_format(LogFormat::Ros2, FrameEncoding::Raw);
        let mut odom = Vec::new();
        for (seq, t, p) in [(0, 1_000_000_000, p0), (1, 1_100_000_000, p1)] {
            enc.encode(&LogItem::Pose(rec(seq, t, p)), |e, b| {
                if e.topic == Topic::Odometry {
                    odom.push(decode_odometry(b).unwrap());
                }
                Ok(())
            })
            .unwrap();
        }
        assert_eq!(odom.len(), 2);
        let (t, pos, _, v0, w0) = odom[0];
        assert_eq!((t, pos, v0, w0), (1_000_000_000, [1.0, 2.0, 3.0], [0.0; 3], [0.0; 3]), "no velocity before a second pose");
        let (_, _, q, v, w) = odom[1];
        assert!((UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2])).angle_to(&rot1)) < 1e-12);
        let v_expected = rot1.inverse() * Vector3::new(0.5, 0.0, 0.0);
        assert!((Vector3::from(v) - v_expected).norm() < 1e-9, "{v:?} vs {v_expected}");
        assert!((Vector3::from(w) - Vector3::new(0.0, 0.2, 0.0)).norm() < 1e-9, "{w:?}");
    }
}
