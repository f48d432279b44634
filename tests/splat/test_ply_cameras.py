"""PLY round trip and camera conventions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from support.scenes import PARAMETER_NAMES, random_scene

from tracegs.splat.cameras import Camera
from tracegs.splat.ply import PROPERTIES, load_ply, save_ply


def test_ply_round_trip_is_exact(tmp_path):
    model = random_scene(37, seed=5)
    path = tmp_path / "scene" / "point_cloud.ply"
    save_ply(model, path)
    loaded = load_ply(path)
    for name in PARAMETER_NAMES:
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    header = [prop.name for prop in PlyData.read(str(path))["vertex"].properties]
    assert header == PROPERTIES and len(PROPERTIES) == 62  # the 3DGS layout at SH degree 3
    assert not list(path.parent.glob("*.tmp"))


def test_ply_of_degree_zero_scene_loads_with_zero_rest(tmp_path):
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros(4, dtype=[(name, "f4") for name in names])
    data["x"] = np.arange(4)
    data["rot_0"] = 1.0
    data["f_dc_2"] = 0.5
    path = tmp_path / "dc_only.ply"
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    model = load_ply(path)
    assert len(model) == 4 and torch.equal(model.means[:, 0], torch.arange(4.0))
    assert model.sh_dc[:, 0, 2].eq(0.5).all() and not model.sh_rest.any()


def test_ply_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        load_ply(tmp_path / "missing.ply")
    path = tmp_path / "points.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")]), "vertex")]).write(
        str(path))
    with pytest.raises(ValueError, match="points.ply"):
        load_ply(path)


def test_look_at_follows_opencv_convention():
    eye, target = torch.tensor([-5.0, 0.0, 0.0]), torch.zeros(3)
    camera = Camera.look_at(eye, target, torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=90.0, width=64, height=48)
    assert torch.allclose(camera.center, eye, atol=1e-6)
    assert torch.allclose(camera.rotation[2], torch.tensor([1.0, 0.0, 0.0]))  # z forward
    assert torch.allclose(camera.rotation[1], torch.tensor([0.0, 0.0, -1.0]))  # y down = world -z
    assert torch.allclose(camera.rotation @ camera.rotation.T, torch.eye(3), atol=1e-6)
    assert camera.K[0, 0].item() == pytest.approx(32.0)  # 90 degrees: f = W / 2
    above = camera.rotation @ torch.tensor([0.0, 0.0, 1.0]) + camera.translation
    assert above[1] < 0  # world up projects upwards in the image


def test_rescaled_camera_keeps_the_image_plane():
    camera = Camera.look_at(torch.tensor([1.0, 2.0, 3.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]),
                            fov_x_deg=60.0, width=72, height=48)
    big = camera.rescaled(720, 480)
    point = torch.tensor([0.2, -0.1, 0.3])

    def project(cam):
        p = cam.K @ (cam.rotation @ point + cam.translation)
        return p[:2] / p[2]

    assert torch.allclose(project(big), 10.0 * project(camera), atol=1e-3)
    assert (big.width, big.height) == (720, 480)


def test_bad_camera_inputs_raise():
    with pytest.raises(ValueError, match="K"):
        Camera(torch.eye(4), torch.eye(4), 10, 10)
    with pytest.raises(ValueError, match="fov_x_deg"):
        Camera.look_at(torch.ones(3), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=0.0)
