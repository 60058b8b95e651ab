"""Independent read-back of a `duv export` COLMAP model with `pycolmap` (COLMAP's own reader).

Usage: check_colmap.py MODEL_DIR EXPECTED_JSON

MODEL_DIR is the export's `sparse/0`. EXPECTED_JSON holds what the test computed with duv's own
camera model: {"images": N, "points": M, "width": W, "height": H,
"points_xyz": [[x, y, z], ...] (world points to project),
"pixels": {"NAME": [[u, v] or null, ...]}} (null: not compared), in COLMAP's pixel convention.

Each point is projected through pycolmap's image and camera API (`Image.project_point`, and
`Camera.img_from_cam(Image.cam_from_world() * X)`). Prints one JSON object: the counts read,
the camera, the number of pixels compared and the largest difference (px) of each projection
path. Exits 1 with a message when the model cannot be read.
"""
import json
import sys

import numpy as np
import pycolmap


def main():
    model_dir, expected_path = sys.argv[1], sys.argv[2]
    with open(expected_path) as f:
        expected = json.load(f)
    rec = pycolmap.Reconstruction(model_dir)
    cameras = list(rec.cameras.values())
    out = {
        "pycolmap": pycolmap.__version__,
        "images": rec.num_images(),
        "registered_images": rec.num_reg_images(),
        "points": rec.num_points3D(),
        "cameras": len(cameras),
        "camera_model": cameras[0].model_name if cameras else None,
        "width": cameras[0].width if cameras else None,
        "height": cameras[0].height if cameras else None,
        "params": list(map(float, cameras[0].params)) if cameras else None,
        "compared": 0,
        "missing_projections": 0,
        "max_error_project_point_px": 0.0,
        "max_error_img_from_cam_px": 0.0,
        "unknown_images": [],
    }
    by_name = {im.name: im for im in rec.images.values()}
    xyz = [np.array(p, dtype=np.float64) for p in expected["points_xyz"]]
    for name, pixels in expected["pixels"].items():
        im = by_name.get(name)
        if im is None:
            out["unknown_images"].append(name)
            continue
        cam_from_world = im.cam_from_world()
        for x, want in zip(xyz, pixels):
            if want is None:
                continue
            got = im.project_point(x)
            via_camera = im.camera.img_from_cam(cam_from_world * x)
            if got is None or via_camera is None:
                out["missing_projections"] += 1
                continue
            want = np.array(want)
            out["compared"] += 1
            out["max_error_project_point_px"] = max(out["max_error_project_point_px"], float(np.abs(np.asarray(got) - want).max()))
            out["max_error_img_from_cam_px"] = max(out["max_error_img_from_cam_px"], float(np.abs(np.asarray(via_camera) - want).max()))
    # The model's own points, as read: their count and the first ones (id order).
    ids = sorted(rec.points3D.keys())
    out["first_points_xyz"] = [list(map(float, rec.points3D[i].xyz)) for i in ids[:5]]
    out["first_points_rgb"] = [list(map(int, rec.points3D[i].color)) for i in ids[:5]]
    json.dump(out, sys.stdout)
    print()


if __name__ == "__main__":
    try:
        main()
    except Exception as e:  # noqa: BLE001: any failure to read is the finding
        print(f"check_colmap.py: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
