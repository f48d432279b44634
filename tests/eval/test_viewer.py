"""``tracegs-view`` (tracegs.eval.viewer) on a folder the real ``tracegs-restore`` wrote: one splat node per
method, switched in place by the GUI's method dropdown; the captured and held-out cameras as frusta posed as the
evaluation's cameras; the chosen held-out view's render beside its ground truth; a bad folder refused in one
line. In headless Chromium (``browser``, driven over the DevTools protocol: support.chromium): the canvas shows
the splats, and switching the method from the server changes the open page's image."""

from __future__ import annotations

import json
import shutil
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import viser
from support.chromium import CHROMIUM, open_page
from support.inputs import assert_refused, files_under
from support.restores import RESTORE_A, restore, runs, small_capture

from tracegs.eval.labels import METHOD_LABELS
from tracegs.eval.viewer import frustum_pose, serve, splat_arrays
from tracegs.splat.cameras import Camera
from tracegs.splat.ply import load_ply

VIEW = Path(sys.executable).with_name("tracegs-view")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A restore folder (plain 3DGS and A on a 16-view synthetic capture, support.restores)."""
    root = tmp_path_factory.mktemp("view")
    capture = small_capture(tmp_path_factory.mktemp("captures"))
    result = restore(root, *RESTORE_A, f"capture.path={capture}")
    assert result.returncode == 0, result.stderr[-3000:]
    (run,) = runs(root)
    return run


def unit_record(run: Path) -> dict:
    (path,) = run.glob("units/*/views_*.json")
    return json.loads(path.read_text())


@pytest.fixture
def viewer(run_folder):
    served = serve(run_folder, port=0)  # a free port: tests in parallel never collide
    yield served
    served.stop()


def nodes(viewer, kind: type) -> dict[str, object]:
    """The server's scene nodes of ``kind`` by name (what it sends every client that connects)."""
    return {name: handle for name, handle in viewer.server.scene._handle_from_node_name.items()
            if isinstance(handle, kind)}


def test_the_viewer_serves_one_splat_node_per_method_switched_in_place(run_folder, viewer):
    unit = unit_record(run_folder)
    key = f"{unit['scene']}_views{unit['views']}"
    splats = nodes(viewer, viser.GaussianSplatHandle)
    assert set(splats) == {f"/{key}/splats/{method}" for method in unit["models"]} and len(splats) == 2
    # One method visible at a time: the last listed (the restorer) first, then whichever the dropdown names.
    assert [name for name, h in splats.items() if h.visible] == [f"/{key}/splats/baseline"]
    assert viewer.method_choice.options == tuple(METHOD_LABELS[m] for m in unit["models"])
    before = viewer.comparison.image.copy()
    viewer.method_choice.value = METHOD_LABELS["3dgs"]
    assert [name for name, h in splats.items() if h.visible] == [f"/{key}/splats/3dgs"]
    # The held-out panel follows: the 3DGS render beside the same ground truth, with 3DGS's scores of that view.
    assert viewer.comparison.image.shape == before.shape and not np.array_equal(viewer.comparison.image, before)
    psnr = unit["methods"]["3dgs"]["per_view"][0]["psnr"]
    assert f"held-out view {unit['test'][0]}" in viewer.scores.content and f"PSNR {psnr:.3f}" in viewer.scores.content
    # The client is served from the installed package (no internet): the page answers at the printed URL.
    with urllib.request.urlopen(viewer.url, timeout=30) as page:
        assert b"<html" in page.read(2000).lower()


def test_the_frusta_are_the_evaluation_cameras_with_their_images(run_folder, viewer):
    unit = unit_record(run_folder)
    key = f"{unit['scene']}_views{unit['views']}"
    frusta = nodes(viewer, viser.CameraFrustumHandle)
    assert set(frusta) == ({f"/{key}/cameras/captured/view_{v}" for v in unit["captured"]}
                           | {f"/{key}/cameras/held_out/view_{v}" for v in unit["test"]})
    camera = Camera.from_record(unit["cameras"][str(unit["test"][0])])
    frustum = frusta[f"/{key}/cameras/held_out/view_{unit['test'][0]}"]
    # Camera-to-world in OpenCV axes: the frustum sits at the camera centre and its +z is the camera's forward.
    assert np.allclose(frustum.position, camera.center.numpy(), atol=1e-5)
    forward = viser.transforms.SO3(np.asarray(frustum.wxyz)).as_matrix() @ np.array([0.0, 0.0, 1.0])
    assert np.allclose(forward, camera.world_to_camera[2, :3].numpy(), atol=1e-5)
    assert np.isclose(frustum.aspect, 32 / 24) and frustum_pose(camera)["fov"] == pytest.approx(frustum.fov)
    # The chosen held-out view's panel: its render at the scored resolution beside its ground-truth image.
    truth = iio.imread(run_folder / unit["cameras"][str(unit["test"][0])]["image"])
    panel = viewer.comparison.image
    cell = panel.shape[1] // 2
    factor = cell // truth.shape[1]
    shown = panel[-truth.shape[0] * factor:, cell:][::factor, ::factor]
    assert np.array_equal(shown, truth)


def test_splats_are_the_ply_gaussians(run_folder):
    unit = unit_record(run_folder)
    model = load_ply(run_folder / unit["models"]["baseline"])
    arrays = splat_arrays(model)
    assert arrays["centers"].shape == (len(model), 3) and arrays["opacities"].shape == (len(model), 1)
    # Sigma = R diag(s^2) R^T: its eigenvalues are the squared scales, whatever the rotation.
    eigenvalues = np.sort(np.linalg.eigvalsh(arrays["covariances"].astype(np.float64)), axis=1)
    squared = np.sort(torch.exp(2.0 * model.log_scales.detach()).numpy(), axis=1)
    assert np.allclose(eigenvalues, squared, rtol=1e-3, atol=1e-9)
    assert arrays["rgbs"].min() >= 0.0 and arrays["rgbs"].max() <= 1.0


def test_a_missing_or_empty_folder_is_refused_in_one_line(run_folder, tmp_path, entry_point):
    """Through the console script in a child process: exit code 2, one line naming the folder (or the file missing
    from it), nothing written; no server starts."""
    (tmp_path / "empty").mkdir()
    part = shutil.copytree(run_folder, tmp_path / "copied_in_part")
    unit = unit_record(part)
    lost = part / unit["cameras"][str(unit["test"][0])]["image"]
    lost.unlink()
    for folder, named in ((tmp_path / "no_such_run", None), (tmp_path / "empty", None), (part, lost)):
        before = files_under(tmp_path)
        result = entry_point("view", [str(folder), "--port", "0"], tmp_path)
        assert_refused(result, "view", str(named or folder), files_under(tmp_path) - before)


def test_an_address_this_machine_cannot_listen_on_is_refused_in_one_line(run_folder, tmp_path, entry_point):
    """``--host`` naming another machine's address: one line naming ``--host`` and exit 2, instead of waiting for a
    server that never binds (192.0.2.1: TEST-NET-1, reserved for documentation, no machine's address)."""
    before = files_under(tmp_path)
    result = entry_point("view", [str(run_folder), "--host", "192.0.2.1", "--port", "0"], tmp_path)
    assert_refused(result, "view", "--host: 192.0.2.1", files_under(tmp_path) - before)


# viser's notice that WebGL runs in software (it does here: SwiftShader) covers a corner of the canvas.
REMOVE_NOTICES = "document.querySelectorAll('[class*=\"Notification\"]').forEach(e => e.remove())"
# The canvas away from the GUI panel (top right) and the axes (bottom left) of the 1000 x 557 page that a
# 1000 x 700 headless window shows.
MIDDLE = (slice(150, 500), slice(250, 650))


@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (make test-browser installs it)")
def test_chromium_draws_the_splats_and_each_method_differently(run_folder, tmp_path):
    """The viewer's client loads from the installed package and draws the splats (cameras hidden): the middle of
    the canvas varies far more than once every splat is hidden, and switching the method from the GUI's handle
    changes the image in the open page, without reloading it."""
    served = serve(run_folder, port=0)
    served.cameras_shown.value = False
    try:
        with open_page(served.url) as page:
            page.wait_until(lambda: page.evaluate("document.body.innerText.includes('Held-out view')"),
                            what="the viewer's GUI")

            shots: dict[str, np.ndarray] = {}

            def shot_once(name: str, accept: Callable[[np.ndarray], bool]) -> np.ndarray:
                """The middle of the canvas once ``accept`` holds for it (the client draws as data arrives)."""

                def taken() -> bool:
                    page.evaluate(REMOVE_NOTICES)
                    shot = page.screenshot()
                    iio.imwrite(tmp_path / f"{name}.png", shot)
                    shots[name] = shot[MIDDLE].astype(np.int16)
                    return bool(accept(shots[name]))

                page.wait_until(taken, what=f"the {name} image")
                return shots[name]

            shot_once("loading", lambda shot: shot.std() > 10)
            time.sleep(2)  # the client sorts the splats for a few frames after they arrive
            restorer = shot_once("baseline", lambda shot: True)
            served.method_choice.value = METHOD_LABELS["3dgs"]
            plain = shot_once("3dgs", lambda shot: np.abs(shot - restorer).mean() > 1.0)
            for handle in nodes(served, viser.GaussianSplatHandle).values():
                handle.visible = False
            blank = shot_once("blank", lambda shot: shot.std() < 3)
    finally:
        served.stop()
    assert restorer.std() > 4 * blank.std() + 5 and plain.std() > 4 * blank.std() + 5
