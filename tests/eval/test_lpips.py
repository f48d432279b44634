"""LPIPS-VGG from a local VGG16 file (supplement B): the distance of the LPIPS authors, computed here without
torchvision, refused in one line where an experiment requires it and cannot have it."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from support.vgg16_layout import VGG16_CONVOLUTIONS, write_vgg16_weights

from tracegs.errors import InputFileError
from tracegs.eval.lpips_vgg import HEADS_FILE, LpipsVgg
from tracegs.eval.metrics import ImageMetrics

# LPIPS's input scaling (the LPIPS authors' ScalingLayer), written out here rather than read from our module.
SHIFT = torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None]
SCALE = torch.tensor([0.458, 0.448, 0.450])[None, :, None, None]
POOLS = (4, 9, 16, 23)  # max-pools of VGG16's trunk before relu5_3
TAPS = (3, 8, 15, 22, 29)


def reference_lpips(state: dict, images: torch.Tensor, targets: torch.Tensor, normalize: bool) -> torch.Tensor:
    """LPIPS-VGG written functionally from the weights: conv/ReLU/pool chain, unit-normalised taps, heads."""
    heads = torch.load(HEADS_FILE, map_location="cpu", weights_only=True)

    def taps(x):
        x, out = (x - SHIFT) / SCALE, []
        for index in range(30):
            if index in VGG16_CONVOLUTIONS:
                x = F.conv2d(x, state[f"features.{index}.weight"], state[f"features.{index}.bias"], padding=1)
            elif index in POOLS:
                x = F.max_pool2d(x, 2)
            else:
                x = F.relu(x)
            if index in TAPS:
                out.append(x / torch.sqrt(1e-8 + (x * x).sum(1, keepdim=True)))
        return out

    if normalize:
        images, targets = images * 2 - 1, targets * 2 - 1
    total = torch.zeros(images.shape[0])
    for k, (a, b) in enumerate(zip(taps(images), taps(targets))):
        total += F.conv2d((a - b) ** 2, heads[f"lin{k}.model.1.weight"]).mean(dim=(1, 2, 3))
    return total


@pytest.fixture(scope="module")
def vgg16_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("hub") / "vgg16-397923af.pth"
    return path, write_vgg16_weights(path)


@pytest.mark.parametrize("normalize", [False, True])
def test_lpips_equals_an_independent_reference(vgg16_file, normalize):
    path, state = vgg16_file
    generator = torch.Generator().manual_seed(0)
    images, targets = torch.rand(2, 3, 48, 72, generator=generator), torch.rand(2, 3, 48, 72, generator=generator)
    ours = LpipsVgg(path)(images, targets, normalize=normalize)
    torch.testing.assert_close(ours, reference_lpips(state, images, targets, normalize), rtol=1e-5, atol=1e-7)
    assert (ours > 0).all()
    assert LpipsVgg(path)(images, images).abs().max().item() == 0.0


def test_metrics_score_lpips_from_the_local_file(vgg16_file):
    path, _ = vgg16_file
    metrics = ImageMetrics(lpips=True, lpips_weights=str(path))
    image = torch.rand(3, 48, 72, generator=torch.Generator().manual_seed(1))
    (row,) = metrics.per_view((image + 0.05).clamp(0, 1), image)
    assert isinstance(row["lpips"], float) and row["lpips"] > 0
    assert metrics.lpips_label.startswith("LPIPS-VGG (unscaled [0,1] images")
    missing = ImageMetrics(lpips=True, lpips_weights=str(path.with_name("absent.pth")))
    assert missing.per_view(image, image)[0]["lpips"] is None
    assert missing.lpips_label == f"LPIPS n/a: VGG16 ImageNet weights not found at {path.with_name('absent.pth')}"


@pytest.mark.parametrize("damage", ["missing_convolution", "other_shape", "extra_layer", "not_a_state_dict"])
def test_a_file_that_is_not_vgg16_is_refused_in_one_line(vgg16_file, tmp_path, damage):
    _, state = vgg16_file
    state = dict(state)
    expected = {"missing_convolution": "'features.28.weight' is missing",
                "other_shape": "'features.0.weight' is (64, 1, 3, 3), VGG16 has (64, 3, 3, 3)",
                "extra_layer": "'features.31.weight' is not in VGG16's trunk",
                "not_a_state_dict": "holds a list, not a state dict"}[damage]
    if damage == "missing_convolution":
        del state["features.28.weight"]
    elif damage == "other_shape":
        state["features.0.weight"] = state["features.0.weight"][:, :1]
    elif damage == "extra_layer":
        state["features.31.weight"] = torch.zeros(1)
    path = tmp_path / "vgg16.pth"
    torch.save([1, 2] if damage == "not_a_state_dict" else state, path)
    with pytest.raises(InputFileError) as error:
        LpipsVgg(path)
    assert str(error.value).startswith(f"{path}: ") and expected in str(error.value)
    assert "\n" not in str(error.value) and "evaluation.lpips_weights" in str(error.value)


@pytest.mark.parametrize("app", ["evaluate", "restore"])
def test_required_lpips_without_its_weights_stops_before_any_work(entry_point, tmp_path, app):
    root = tmp_path / "root"
    root.mkdir()
    absent = tmp_path / "absent.pth"
    overrides = [f"paths.root_dir={root}", "evaluation.require_lpips=true", f"evaluation.lpips_weights={absent}"]
    if app == "restore":
        overrides.append(f"capture.path={tmp_path}")
    result = entry_point(app, overrides, tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr_lines()
    assert line == (f"tracegs-{app}: error: config field 'evaluation.lpips_weights': VGG16 ImageNet weights not "
                    f"found at {absent}; this experiment requires LPIPS (evaluation.require_lpips): put "
                    "torchvision's VGG16 ImageNet weights (vgg16-397923af.pth) there")
    assert not list(root.rglob("*"))  # no run folder, no product
