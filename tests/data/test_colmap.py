import shutil

import numpy as np
import pytest
import torch
from scene_builders import ring_cameras, write_scene

from tracegs.data.colmap import SceneFormatError, load_scene, write_colmap_model
from tracegs.data.config import SceneSourceConfig


def source(root, **kwargs) -> SceneSourceConfig:
    return SceneSourceConfig(root=str(root), preset="custom", normalize=False, **kwargs)


def test_written_model_loads_back_with_identical_intrinsics_and_poses(colmap_scene):
    root, cameras = colmap_scene
    scene = load_scene(source(root.parent), root.name)
    assert scene.image_names == [f"img_{i:03d}.png" for i in range(len(cameras))]
    for loaded, original in zip(scene.cameras, cameras):
        assert (loaded.width, loaded.height) == (original.width, original.height)
        torch.testing.assert_close(loaded.K, original.K, atol=1e-5, rtol=0)
        torch.testing.assert_close(loaded.world_to_camera, original.world_to_camera, atol=1e-5, rtol=0)
    # Tracks survive: the conftest observes every point in images 0, 3, 6, ...
    assert scene.points.shape == (50, 3)
    assert scene.visibility[:, 0].all() and not scene.visibility[:, 1].any()
    points, _ = scene.points_seen_by([0, 3], 2)
    assert len(points) == 50 and len(scene.points_seen_by([0, 1], 2)[0]) == 0
    # GSFixer's rule (one sparse view suffices) keeps the points image 0 alone sees.
    assert len(scene.points_seen_by([0, 1], 1)[0]) == 50


def test_simple_pinhole_and_downscaled_folder(tmp_path):
    import pycolmap

    root, cameras = write_scene(tmp_path / "s" / "a", n=4, image_dir="images_4", image_scale=4)
    # Rewrite camera 1 as SIMPLE_PINHOLE (f, cx, cy) at full resolution 4x the stored images.
    model = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    for camera in model.cameras.values():
        camera.model = pycolmap.CameraModelId.SIMPLE_PINHOLE
        camera.params = [40.0, 18.0, 12.0]
    model.write(str(root / "sparse" / "0"))
    scene = load_scene(source(tmp_path / "s", image_dir="images_4"), "a")
    K = scene.cameras[0].K
    assert (scene.cameras[0].width, scene.cameras[0].height) == (9, 6)
    torch.testing.assert_close(K, torch.tensor([[10.0, 0, 4.5], [0, 10.0, 3.0], [0, 0, 1.0]]))
    assert scene.load_image(0).shape == (3, 6, 9)


def test_normalisation_keeps_projections(colmap_scene):
    root, _ = colmap_scene
    raw = load_scene(source(root.parent), root.name)
    norm = load_scene(SceneSourceConfig(root=str(root.parent), preset="custom", normalize=True), root.name)
    centres = torch.stack([c.center for c in norm.cameras])
    assert centres.mean(0).abs().max() < 1e-5
    assert abs(float(centres.norm(dim=1).max()) - 1 / 1.1) < 1e-5
    for a, b in zip(raw.cameras, norm.cameras):
        pa = a.K @ (a.rotation @ raw.points.T + a.translation[:, None])
        pb = b.K @ (b.rotation @ norm.points.T + b.translation[:, None])
        torch.testing.assert_close(pa[:2] / pa[2], pb[:2] / pb[2], atol=1e-3, rtol=0)


def test_radial_camera_model_asks_for_undistortion(colmap_scene):
    import pycolmap

    root, _ = colmap_scene
    model = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    for camera in model.cameras.values():
        camera.model = pycolmap.CameraModelId.OPENCV
        camera.params = [30.0, 30.0, 18.0, 12.0, 0.01, 0.0, 0.0, 0.0]
    model.write(str(root / "sparse" / "0"))
    with pytest.raises(SceneFormatError, match="OPENCV.*undistort"):
        load_scene(source(root.parent), root.name)


def test_missing_image_folder_and_missing_image_fail_clearly(colmap_scene):
    root, _ = colmap_scene
    (root / "images" / "img_005.png").unlink()
    with pytest.raises(FileNotFoundError, match="img_005.png"):
        load_scene(source(root.parent), root.name)
    shutil.rmtree(root / "images")
    with pytest.raises(FileNotFoundError, match="image folder not found"):
        load_scene(source(root.parent), root.name)


def test_write_colmap_model_replaces_atomically(tmp_path):
    cameras = ring_cameras(3)
    path = tmp_path / "sparse" / "0"
    write_colmap_model(path, cameras, ["a.png", "b.png", "c.png"], np.zeros((1, 3)), np.ones((1, 3)), [[(0, [1, 1])]])
    write_colmap_model(path, cameras[:2], ["a.png", "b.png"])
    import pycolmap

    assert pycolmap.Reconstruction(str(path)).num_images() == 2
    assert [p.name for p in tmp_path.joinpath("sparse").iterdir()] == ["0"]


def test_deployment_starts_from_the_points_its_init_rule_keeps(tmp_path):
    """``data.prepare.fit.init_min_views``: GSFixer's release starts from every SfM point one sparse view sees
    (datasets/colmap_debug.py l. 354-369); two views (what V_s triangulates) leave images 0 and 1 too few points,
    so the fit starts from random Gaussians."""
    from tracegs.deploy.scenes import initial_model
    from tracegs.splat.config import GaussianFitConfig
    from tracegs.splat.fit import View

    root, _ = write_scene(tmp_path / "scenes" / "ring", points=80)  # more than MIN_INIT_POINTS
    scene = load_scene(source(root.parent), root.name)
    captured = [View(image=scene.load_image(i), camera=scene.cameras[i]) for i in (0, 1)]
    released = initial_model(scene, [0, 1], captured, GaussianFitConfig(init_min_views=1))
    torch.testing.assert_close(released.means, scene.points)
    corrected = initial_model(scene, [0, 1], captured, GaussianFitConfig(init_min_views=2, init_num_points=7))
    assert len(corrected) == 7
