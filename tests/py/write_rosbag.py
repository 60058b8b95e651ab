"""Writes a ROS 2 bag (MCAP storage, CDR) with the independent `rosbags` package, for
tests/rosbag.rs: the duv `rosbag:` source must read what a standard tool writes.

    python write_rosbag.py [--compress zstd|lz4] OUT_DIR FX FY CX CY T_NS:IMAGE.png [...]

Topics: /cam/image_raw (sensor_msgs/msg/Image, bgr8, the PNG's pixels), its
/cam/image_raw/compressed (sensor_msgs/msg/CompressedImage, the PNG file as it is),
/cam/camera_info (sensor_msgs/msg/CameraInfo, plumb_bob, no distortion) and
/imu/data (sensor_msgs/msg/Imu, identity orientation) at every image's stamp. PNGs are
8-bit RGB, not interlaced (what duv writes); decoded here with zlib (no imaging library).
`--compress zstd`: chunks compressed by rosbags (rosbag2's default for MCAP); `--compress lz4`:
the bag rewritten chunk by chunk with LZ4 by the `mcap` package.
"""

import struct
import sys
import zlib
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore


def read_png_rgb8(path):
    data = Path(path).read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', f'{path}: not a PNG'
    pos, idat, width, height = 8, b'', 0, 0
    while pos < len(data):
        (length,) = struct.unpack('>I', data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if kind == b'IHDR':
            width, height, depth, colour, _, _, interlace = struct.unpack('>IIBBBBB', body)
            assert (depth, colour, interlace) == (8, 2, 0), f'{path}: expected 8-bit RGB, not interlaced'
        elif kind == b'IDAT':
            idat += body
        pos += 12 + length
    raw = zlib.decompress(idat)
    stride, bpp = width * 3, 3
    out = np.zeros((height, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.int32)
    for y in range(height):
        ftype = raw[y * (stride + 1)]
        line = np.frombuffer(raw, dtype=np.uint8, count=stride, offset=y * (stride + 1) + 1).astype(np.int32)
        cur = np.zeros(stride, dtype=np.int32)
        for x in range(stride):
            a = cur[x - bpp] if x >= bpp else 0
            b = prev[x]
            c = prev[x - bpp] if x >= bpp else 0
            if ftype == 0:
                p = 0
            elif ftype == 1:
                p = a
            elif ftype == 2:
                p = b
            elif ftype == 3:
                p = (a + b) // 2
            else:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                p = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[x] = (line[x] + p) & 0xFF
        out[y] = cur
        prev = cur
    return width, height, out.reshape(height, width, 3), data


def rewrite_lz4(path):
    from mcap.reader import make_reader
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    data = Path(path).read_bytes()
    with open(path, 'wb') as f:
        w = McapWriter(f, compression=CompressionType.LZ4)
        w.start(profile='ros2', library='write_rosbag.py')
        schemas, channels = {}, {}
        for schema, channel, message in make_reader(__import__('io').BytesIO(data)).iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata)
            w.add_message(channels[channel.id], message.log_time, message.data, message.publish_time, message.sequence)
        w.finish()


def main():
    args = sys.argv[1:]
    compress = None
    if args[0] == '--compress':
        compress, args = args[1], args[2:]
    out, fx, fy, cx, cy = args[0], *map(float, args[1:5])
    frames = [arg.split(':', 1) for arg in args[5:]]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image = ts.types['sensor_msgs/msg/Image']
    CompressedImage = ts.types['sensor_msgs/msg/CompressedImage']
    CameraInfo = ts.types['sensor_msgs/msg/CameraInfo']
    RegionOfInterest = ts.types['sensor_msgs/msg/RegionOfInterest']
    Imu = ts.types['sensor_msgs/msg/Imu']
    Quaternion = ts.types['geometry_msgs/msg/Quaternion']
    Vector3 = ts.types['geometry_msgs/msg/Vector3']
    Header = ts.types['std_msgs/msg/Header']
    Time = ts.types['builtin_interfaces/msg/Time']

    writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress == 'zstd':
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer as w:
        c_img = w.add_connection('/cam/image_raw', Image.__msgtype__, typestore=ts)
        c_jpg = w.add_connection('/cam/image_raw/compressed', CompressedImage.__msgtype__, typestore=ts)
        c_info = w.add_connection('/cam/camera_info', CameraInfo.__msgtype__, typestore=ts)
        c_imu = w.add_connection('/imu/data', Imu.__msgtype__, typestore=ts)
        for t_ns, png in frames:
            t_ns = int(t_ns)
            width, height, rgb, png_bytes = read_png_rgb8(png)
            header = Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id='camera')
            bgr = np.ascontiguousarray(rgb[:, :, ::-1]).reshape(-1)
            img = Image(header=header, height=height, width=width, encoding='bgr8', is_bigendian=0, step=width * 3, data=bgr)
            comp = CompressedImage(header=header, format='png', data=np.frombuffer(png_bytes, dtype=np.uint8))
            info = CameraInfo(
                header=header,
                height=height,
                width=width,
                distortion_model='plumb_bob',
                d=np.zeros(5, dtype=np.float64),
                k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
                r=np.eye(3, dtype=np.float64).reshape(-1),
                p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
                binning_x=0,
                binning_y=0,
                roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            imu = Imu(
                header=header,
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9, dtype=np.float64),
                angular_velocity=Vector3(x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9, dtype=np.float64),
                linear_acceleration=Vector3(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9, dtype=np.float64),
            )
            w.write(c_info, t_ns, ts.serialize_cdr(info, CameraInfo.__msgtype__))
            w.write(c_imu, t_ns, ts.serialize_cdr(imu, Imu.__msgtype__))
            w.write(c_img, t_ns, ts.serialize_cdr(img, Image.__msgtype__))
            w.write(c_jpg, t_ns, ts.serialize_cdr(comp, CompressedImage.__msgtype__))
    if compress == 'lz4':
        for f in Path(out).glob('*.mcap'):
            rewrite_lz4(f)
    print(f'wrote {len(frames)} frames to {out}')


if __name__ == '__main__':
    main()
