"""The ``vkitti2`` reader on a Virtual KITTI 2 layout written by the test."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from pvslam_core.datasets.base import DatasetError
from pvslam_core.outputs.trajectory_io import pose_to_matrix
from pvslam_plugins.datasets.vkitti2.config import Vkitti2Config
from pvslam_plugins.datasets.vkitti2.reader import Vkitti2Reader

W, H = 40, 24
COLORS = """Category r g b
Terrain 210 0 200
Sky 90 200 255
Road 100 60 100
Truck 160 60 60
Car 255 127 80
Van 0 139 139
Undefined 0 0 0
"""
# category ids = 1 + row (Undefined is void): Terrain 1, Sky 2, Road 3, Truck 4, Car 5, Van 6
SKY, ROAD, CAR, VAN = (90, 200, 255), (100, 60, 100), (255, 127, 80), (0, 139, 139)


def T_cw(i: int, cam: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.02 * i, 0.3 + 0.01 * i, -0.05]))[0]
    T[:3, 3] = [1.0 + 0.5 * cam, -2.0, 3.0 + i]
    return T


def write_frame(d: dict[str, Path], i: int) -> None:
    cv2.imwrite(str(d["rgb"] / f"rgb_{i:05d}.jpg"), np.full((H, W, 3), 40 + 20 * i, np.uint8))
    depth = np.full((H, W), 1234, np.uint16)
    depth[:8] = 65535  # sky
    cv2.imwrite(str(d["depth"] / f"depth_{i:05d}.png"), depth)
    cls = np.zeros((H, W, 3), np.uint8)
    cls[:8] = SKY
    cls[8:] = ROAD
    cls[12:20, 2:10] = CAR  # track 0 -> instance value 1
    cls[12:20, 20:30] = VAN  # track 3 -> instance value 4
    cls[20:, 35:] = CAR  # a car pixel block without an instance -> void
    cv2.imwrite(str(d["cls"] / f"classgt_{i:05d}.png"), cls[..., ::-1].copy())
    inst = np.zeros((H, W), np.uint8)
    inst[12:20, 2:10] = 1
    inst[12:20, 20:30] = 4
    im = Image.fromarray(inst, mode="P")
    im.putpalette([0, 0, 0, 200, 10, 10, 10, 200, 10, 10, 10, 200, 200, 200, 10] + [0] * (256 * 3 - 15))
    im.save(d["inst"] / f"instancegt_{i:05d}.png")


def fake_vkitti2(root: Path, n: int = 3, split_archives: bool = False) -> None:
    rel = Path("Scene02") / "15-deg-left"
    base = {k: root / (f"vkitti_2.0.3_{k}" if split_archives else ".") for k in
            ("rgb", "depth", "classSegmentation", "instanceSegmentation", "textgt")}
    d = {
        "rgb": base["rgb"] / rel / "frames/rgb/Camera_0",
        "depth": base["depth"] / rel / "frames/depth/Camera_0",
        "cls": base["classSegmentation"] / rel / "frames/classSegmentation/Camera_0",
        "inst": base["instanceSegmentation"] / rel / "frames/instanceSegmentation/Camera_0",
    }
    for p in d.values():
        p.mkdir(parents=True)
    for i in range(n):
        write_frame(d, i)
    shutil.copytree(d["rgb"], d["rgb"].parent / "Camera_1")  # right camera: rgb only
    text = base["textgt"] / rel
    text.mkdir(parents=True, exist_ok=True)
    (text / "colors.txt").write_text(COLORS)
    (text / "intrinsic.txt").write_text(
        "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n"
        + "".join(f"{i} {c} 30.5 30.5 19.5 11.5\n" for i in range(n) for c in (0, 1))
    )
    ext = ["frame cameraID r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1"]
    for i in range(n):
        for c in (0, 1):
            ext.append(f"{i} {c} " + " ".join(f"{v:.10f}" for v in T_cw(i, c).reshape(-1)))
    (text / "extrinsic.txt").write_text("\n".join(ext) + "\n")
    bbox = ["frame cameraID trackID left right top bottom number_pixels truncation_ratio occupancy_ratio isMoving"]
    for i in range(n):
        bbox.append(f"{i} 0 0 2 9 12 19 64 0 1 False")
        bbox.append(f"{i} 0 3 20 29 12 19 80 0 1 {'True' if i > 0 else 'False'}")
    (text / "bbox.txt").write_text("\n".join(bbox) + "\n")


def reader(root: Path, **kw) -> Vkitti2Reader:
    kw.setdefault("crop_multiple", 1)
    return Vkitti2Reader(Vkitti2Config(path=str(root), scene="02", variation="15-deg-left", **kw))


def test_poses_are_the_inverted_extrinsics(tmp_path):
    fake_vkitti2(tmp_path)
    r = reader(tmp_path)
    info = r.info()
    assert info.num_frames == 3 and info.has_gt_pose and info.has_gt_depth and info.has_gt_panoptic
    assert info.name == "vkitti2_Scene02_15-deg-left_cam0"
    for f in r:
        T_wc = pose_to_matrix(f.gt_pose.numpy())
        assert np.allclose(T_wc @ T_cw(f.index, 0), np.eye(4), atol=1e-8)
        # the camera centre is -R^T t of the world-to-camera matrix
        R, t = T_cw(f.index, 0)[:3, :3], T_cw(f.index, 0)[:3, 3]
        assert np.allclose(f.gt_pose[:3].numpy(), -R.T @ t, atol=1e-8)
        assert f.timestamp == pytest.approx(0.1 * f.index)
    r1 = reader(tmp_path, camera=1)
    assert np.allclose(pose_to_matrix(r1[2].gt_pose.numpy()), np.linalg.inv(T_cw(2, 1)), atol=1e-8)


def test_intrinsics_depth_and_image(tmp_path):
    fake_vkitti2(tmp_path)
    f = reader(tmp_path)[1]
    k = f.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (30.5, 30.5, 19.5, 11.5, W, H)
    assert f.gt_depth[10, 5].item() == pytest.approx(12.34)  # centimetres -> metres
    assert (f.gt_depth[:8] == 0).all()  # 65535 (sky) -> invalid
    assert abs(int(f.image[0, 5, 5]) - 60) <= 2  # jpeg


def test_panoptic_from_class_and_instance_masks(tmp_path):
    fake_vkitti2(tmp_path)
    r = reader(tmp_path)
    cats = {c.name: c for c in r.info().categories}
    assert [c.name for c in r.info().categories] == ["Terrain", "Sky", "Road", "Truck", "Car", "Van"]
    assert cats["Car"].isthing and cats["Van"].isthing and cats["Truck"].isthing and not cats["Road"].isthing
    assert cats["Car"].color == CAR
    f = r[0]
    ids = f.gt_panoptic.ids.numpy()
    assert ids[0, 0] == 2000  # sky (stuff)
    assert ids[22, 5] == 3000  # road (stuff)
    assert ids[15, 5] == 5001  # car, track 0
    assert ids[15, 25] == 6004  # van, track 3
    assert ids[22, 37] == 0  # car pixel without instance -> void
    segs = {s.id: s for s in f.gt_panoptic.segments}
    assert set(segs) == {2000, 3000, 5001, 6004}
    assert segs[5001].isthing and segs[5001].category_id == 5 and not segs[3000].isthing


def test_dynamic_mask_from_bbox_is_moving(tmp_path):
    fake_vkitti2(tmp_path)
    r = reader(tmp_path)
    assert not r[0].gt_dynamic.any()  # nothing flagged moving in frame 0
    dyn = r[1].gt_dynamic.numpy()
    assert dyn[15, 25] and not dyn[15, 5] and dyn.sum() == 8 * 10  # only the van (track 3) moves


def test_panoptic_follows_resize_and_crop(tmp_path):
    fake_vkitti2(tmp_path)
    f = reader(tmp_path, resize=(80, 48), crop_multiple=16)
    g = f[0]
    assert tuple(g.gt_panoptic.ids.shape) == (g.height, g.width) == (48, 80)
    assert g.gt_panoptic.ids[30, 10].item() == 5001 and g.gt_dynamic is not None


def test_split_archive_layout_is_found(tmp_path):
    fake_vkitti2(tmp_path, split_archives=True)
    r = reader(tmp_path)
    assert r.info().num_frames == 3 and r[2].gt_panoptic.ids[15, 5].item() == 5001


# ------------------------------------------------------------------------------------------------ errors ----
def test_missing_rgb_names_file_and_list(tmp_path):
    fake_vkitti2(tmp_path)
    (tmp_path / "Scene02/15-deg-left/frames/rgb/Camera_0/rgb_00001.jpg").unlink()
    with pytest.raises(DatasetError, match=r"rgb_00001\.jpg: frame missing \(listed in .*extrinsic\.txt\)"):
        reader(tmp_path)


def test_missing_depth_names_file(tmp_path):
    fake_vkitti2(tmp_path)
    (tmp_path / "Scene02/15-deg-left/frames/depth/Camera_0/depth_00002.png").unlink()
    with pytest.raises(DatasetError, match=r"depth_00002\.png: file missing"):
        reader(tmp_path)[2]


def test_bad_extrinsic_line_names_the_file(tmp_path):
    fake_vkitti2(tmp_path)
    p = tmp_path / "Scene02/15-deg-left/extrinsic.txt"
    lines = p.read_text().splitlines()
    lines[3] = lines[3].rsplit(" ", 1)[0]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"extrinsic\.txt:4: expected 18 values, found 17"):
        reader(tmp_path)


def test_corrupt_instance_png_names_the_file(tmp_path):
    fake_vkitti2(tmp_path)
    (tmp_path / "Scene02/15-deg-left/frames/instanceSegmentation/Camera_0/instancegt_00000.png").write_bytes(b"xx")
    with pytest.raises(DatasetError, match=r"instancegt_00000\.png: unreadable or corrupt"):
        reader(tmp_path)[0]


def test_unknown_scene_or_variation(tmp_path):
    fake_vkitti2(tmp_path)
    with pytest.raises(DatasetError, match=r"Scene02/fog.*variation='fog'"):
        Vkitti2Reader(Vkitti2Config(path=str(tmp_path), scene="Scene02", variation="fog"))


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.vkitti2 as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    assert build_registry(extra_modules=(plugin,)).get("dataset", "vkitti2").config_model is Vkitti2Config


def test_invalid_intrinsics_name_the_file(tmp_path):
    fake_vkitti2(tmp_path)
    intr = next(tmp_path.rglob("intrinsic.txt"))
    intr.write_text(intr.read_text().replace("30.5 30.5 19.5 11.5", "30.5 30.5 19.5 900.0"))
    with pytest.raises(DatasetError) as err:
        reader(tmp_path)
    assert str(intr) in str(err.value) and "cy=900.0" in str(err.value)
