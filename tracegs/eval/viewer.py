"""``tracegs-view``: a result folder's refined 3DGS in the browser (viser), one method at a time from one camera.

The folder is one that ``tracegs-demo``, ``tracegs-evaluate`` or ``tracegs-restore`` wrote: its evaluation units
(``units/<scene>/views_<K>.json``, read as the report page reads them) name each method's refined PLY and, since
the evaluation records them, the unit's captured and held-out cameras with their images. The viewer serves

- each method's splats as its own scene node; the method dropdown toggles which node is visible, so the client's
  camera stays where the reader put it and the methods are compared from the same viewpoint;
- the captured views (blue) and the held-out views (orange) as frusta carrying their images;
- for the held-out view picked in the GUI, the selected method's render (the project's rasterizer, at the
  resolution it was scored at) beside its ground truth, with the scores the evaluation gave that view.

Everything is read from the folder alone, so a copied or moved folder views the same.
"""

from __future__ import annotations

import math
import socket
import threading
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import viser

from tracegs.errors import InputFileError, TraceGSError
from tracegs.eval.labels import METHOD_LABELS
from tracegs.eval.merge import unit_records
from tracegs.eval.tables_and_figures import qualitative_grid
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.gaussians import SH_C0, GaussianModel
from tracegs.splat.ply import load_ply
from tracegs.splat.projection import covariance_factor
from tracegs.splat.render import render_views

CAPTURED_COLOUR = (40, 110, 230)
HELD_OUT_COLOUR = (240, 140, 20)
CHOSEN_COLOUR = (220, 30, 30)
# Frustum images are thumbnails: the browser receives one per camera, and a real capture has hundreds.
THUMBNAIL_PIXELS = 256


@dataclass
class UnitView:
    """One evaluation unit as the viewer shows it: its refined models, cameras and view images."""

    folder: Path
    record: dict
    models: dict[str, GaussianModel]
    cameras: dict[int, Camera] = field(default_factory=dict)

    @property
    def label(self) -> str:
        return f"{self.record['scene']}, {self.record['views']} input views"

    @property
    def key(self) -> str:
        """The unit's scene-tree name (a scene name is a plain folder name, tracegs.config.validate)."""
        return f"{self.record['scene']}_views{self.record['views']}"

    def image(self, view: int) -> np.ndarray:
        """View ``view``'s image (H x W x 3 uint8) as the evaluation fitted to or scored on it."""
        return iio.imread(self.folder / self.record["cameras"][str(view)]["image"])[..., :3]

    def scores(self, method: str, view: int) -> dict:
        """The evaluation's scores of ``method`` at held-out view ``view``."""
        return self.record["methods"][method]["per_view"][self.record["test"].index(view)]


def load_run(folder: str | Path) -> list[UnitView]:
    """The units of ``folder`` that name refined PLYs, loaded; refused in one line (tracegs.errors) when the
    folder is missing or holds no refined PLY."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise InputFileError(folder, "no such run folder", "name a folder tracegs-demo or tracegs-restore wrote")
    units = []
    for record in unit_records(folder):
        paths = {method: folder / ply for method, ply in record.get("models", {}).items()}
        if not paths or not all(path.is_file() for path in paths.values()):
            continue
        cameras = {int(view): Camera.from_record(camera) for view, camera in record.get("cameras", {}).items()}
        images = [folder / camera["image"] for camera in record.get("cameras", {}).values()]
        missing = [path for path in images if not path.is_file()]
        if missing:
            raise InputFileError(missing[0], "a view image the unit's record names is missing",
                                 "copy or move the whole run folder")
        try:
            models = {method: load_ply(path) for method, path in paths.items()}
        except ValueError as error:  # a file named .ply that is not a 3DGS PLY
            raise InputFileError(folder, str(error), "make the run again") from error
        units.append(UnitView(folder, record, models, cameras))
    if not units:
        raise InputFileError(folder, "holds no refined PLY (no units/<scene>/views_<K>.json naming models/)",
                             "view the folder of a tracegs-demo or tracegs-restore run (evaluation.save_models=true)")
    return units


def splat_arrays(model: GaussianModel) -> dict[str, np.ndarray]:
    """``model`` as viser's splat arguments: centres, world covariances (R S)(R S)^T, the degree-0 colour
    (view-independent: the browser does not evaluate SH) and opacities."""
    with torch.no_grad():
        factor = covariance_factor(model.quats, model.log_scales)
        return {"centers": model.means.numpy().astype(np.float32),
                "covariances": (factor @ factor.transpose(1, 2)).numpy().astype(np.float32),
                "rgbs": (0.5 + SH_C0 * model.sh_dc[:, 0, :]).clamp(0.0, 1.0).numpy().astype(np.float32),
                "opacities": model.opacities[:, None].numpy().astype(np.float32)}


def frustum_pose(camera: Camera) -> dict:
    """viser's frustum of ``camera``: camera-to-world rotation (wxyz) and centre, vertical field of view, aspect.

    The project's cameras are world-to-camera in OpenCV axes (tracegs.splat.cameras), which viser's frusta use
    too, so only the inverse is taken."""
    camera_to_world = camera.camera_to_world.double().numpy()
    return {"wxyz": viser.transforms.SO3.from_matrix(camera_to_world[:3, :3]).wxyz,
            "position": camera_to_world[:3, 3],
            "fov": 2.0 * math.atan(camera.height / (2.0 * float(camera.K[1, 1]))),
            "aspect": camera.width / camera.height}


def thumbnail(image: np.ndarray) -> np.ndarray:
    step = max(1, math.ceil(max(image.shape[:2]) / THUMBNAIL_PIXELS))
    return image[::step, ::step]


def world_up(cameras: list[Camera]) -> np.ndarray:
    """The scene's up: the mean of the cameras' up axes (-y in OpenCV axes); captures are mostly taken upright."""
    ups = -np.stack([c.camera_to_world[:3, 1].double().numpy() for c in cameras])
    mean = ups.mean(axis=0)
    return mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 1e-6 else np.array([0.0, 0.0, 1.0])


def initial_view(unit: UnitView) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Where the viewer's camera starts for ``unit`` (which has cameras): (position, look-at point, up, vertical
    field of view in radians). A little behind its first held-out camera with a wider view: the splats as that
    camera saw them, its frustum and its neighbours in sight."""
    cameras = list(unit.cameras.values())
    held_out = [unit.cameras[v] for v in unit.record["test"] if v in unit.cameras] or cameras
    pose = frustum_pose(held_out[0])
    forward = held_out[0].camera_to_world[:3, 2].double().numpy()
    centres = np.stack([c.center.double().numpy() for c in cameras])
    # Where the held-out camera's axis passes closest to the middle of the cameras: what they look at.
    depth = max(float((centres.mean(axis=0) - pose["position"]) @ forward), 1e-3)
    return (pose["position"] - 0.25 * depth * forward, pose["position"] + depth * forward, world_up(cameras),
            min(1.4 * pose["fov"], math.radians(90.0)))


class Viewer:
    """A viser server showing ``units`` (see the module docstring); ``url`` is where to open it."""

    def __init__(self, units: list[UnitView], host: str = "127.0.0.1", port: int = 8080):
        self.units = {unit.key: unit for unit in units}
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host = host
        self.background = GaussianFitConfig().background
        self.splats: dict[str, dict[str, viser.GaussianSplatHandle]] = {}
        self.frusta: dict[str, dict[int, viser.CameraFrustumHandle]] = {}
        self._lock = threading.Lock()
        for unit in units:
            self._add_unit(unit)
        first = units[0]
        gui = self.server.gui
        self.unit_choice = gui.add_dropdown("Scene", [u.label for u in units], initial_value=first.label,
                                            visible=len(units) > 1)
        self.method_choice = gui.add_dropdown("Method", self._method_labels(first),
                                              initial_value=self._method_labels(first)[-1])
        self.cameras_shown = gui.add_checkbox("Cameras", initial_value=True)
        self.view_choice = gui.add_dropdown("Held-out view", self._view_labels(first) or ("none",))
        self.comparison = gui.add_image(np.zeros((8, 16, 3), np.uint8), label="render | ground truth",
                                        format="png")
        self.scores = gui.add_markdown("")
        self.unit_choice.on_update(lambda _: self._select_unit())
        self.method_choice.on_update(lambda _: self.show())
        self.view_choice.on_update(lambda _: self.show())
        self.cameras_shown.on_update(lambda _: self.show())
        self._select_unit()

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.server.get_port()}"

    @property
    def unit(self) -> UnitView:
        return next(u for u in self.units.values() if u.label == self.unit_choice.value)

    @property
    def method(self) -> str:
        # Another scene's methods while the dropdown's options are being swapped: its restorer, as at the start.
        methods = {METHOD_LABELS.get(m, m): m for m in self.unit.models}
        return methods.get(self.method_choice.value, list(methods.values())[-1])

    @property
    def view(self) -> int | None:
        label = self.view_choice.value
        return int(label.removeprefix("view ")) if label.startswith("view ") else None

    @staticmethod
    def _method_labels(unit: UnitView) -> list[str]:
        return [METHOD_LABELS.get(m, m) for m in unit.models]

    @staticmethod
    def _view_labels(unit: UnitView) -> list[str]:
        return [f"view {v}" for v in unit.record["test"] if v in unit.cameras]

    def _add_unit(self, unit: UnitView) -> None:
        scene = self.server.scene
        self.splats[unit.key] = {method: scene.add_gaussian_splats(f"/{unit.key}/splats/{method}",
                                                                   **splat_arrays(model), visible=False)
                                 for method, model in unit.models.items()}
        centres = np.stack([c.center.numpy() for c in unit.cameras.values()]) if unit.cameras else np.zeros((1, 3))
        # Frusta a twentieth of the cameras' spread: visible around the splats without hiding them.
        size = 0.05 * float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)) or 1.0)
        captured = set(unit.record["captured"])
        self.frusta[unit.key] = {
            view: scene.add_camera_frustum(
                f"/{unit.key}/cameras/{'captured' if view in captured else 'held_out'}/view_{view}",
                scale=size, thickness=2.0, thickness_units="screen", image=thumbnail(unit.image(view)), visible=False,
                color=CAPTURED_COLOUR if view in captured else HELD_OUT_COLOUR, **frustum_pose(camera))
            for view, camera in unit.cameras.items()}

    def _select_unit(self) -> None:
        """Another unit: its methods and held-out views in the GUI, the viewpoint reset to look as its first
        held-out camera does (each unit lives in its own normalised world)."""
        unit = self.unit
        self.method_choice.options = self._method_labels(unit)
        self.view_choice.options = self._view_labels(unit) or ("none",)
        if unit.cameras:
            position, look_at, up, fov = initial_view(unit)
            self.server.scene.set_up_direction(tuple(up))
            self.server.initial_camera.position = tuple(position)
            self.server.initial_camera.look_at = tuple(look_at)
            self.server.initial_camera.fov = fov
        self.show()

    def show(self) -> None:
        """Make the GUI's choice visible: the chosen method's splats (the others hidden), the frusta, and the
        chosen held-out view's render beside its ground truth."""
        with self._lock:
            unit, method, view = self.unit, self.method, self.view
            for key, handles in self.splats.items():
                for name, handle in handles.items():
                    handle.visible = key == unit.key and name == method
            for key, frusta in self.frusta.items():
                for index, handle in frusta.items():
                    handle.visible = key == unit.key and self.cameras_shown.value
                    if key == unit.key and index in unit.record["test"]:
                        handle.color = CHOSEN_COLOUR if index == view else HELD_OUT_COLOUR
            if view is None:
                self.comparison.visible = False
                self.scores.content = ("This folder's evaluation recorded no cameras (made before it did); "
                                       "evaluate it again to see them.")
                return
            self.comparison.visible = True
            self.comparison.image = self.comparison_image(unit, method, view)
            scores = unit.scores(method, view)
            shown = ", ".join(f"{name.upper()} {value:.3f}" for name, value in scores.items() if value is not None)
            self.scores.content = f"**{METHOD_LABELS.get(method, method)}**, held-out view {view}: {shown}"

    def comparison_image(self, unit: UnitView, method: str, view: int) -> np.ndarray:
        """``method``'s render of held-out ``view`` beside its ground truth, laid out as a row of the
        evaluation's qualitative grid (captions on top, small views upscaled)."""
        render = render_views(unit.models[method], [unit.cameras[view]], self.background, None)[0]
        truth = torch.from_numpy(unit.image(view)).permute(2, 0, 1).float() / 255.0
        return qualitative_grid({METHOD_LABELS.get(method, method): [render], "GT": [truth]})

    def stop(self) -> None:
        self.server.stop()



def serve(folder: str | Path, host: str = "127.0.0.1", port: int = 8080) -> Viewer:
    """Load ``folder`` (refusing a bad one before any server starts) and serve it; the caller stops it."""
    units = load_run(folder)
    require_listenable(host)
    return Viewer(units, host, port)


def require_listenable(host: str) -> None:
    """Refuse in one line an address this machine cannot listen on: viser's server thread would fail to bind
    there and leave the command waiting for it."""
    try:
        family = socket.getaddrinfo(host, None)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((host, 0))
    except OSError as error:
        raise TraceGSError("--host", f"{host}: this machine cannot listen there ({error.strerror or error})",
                           "give one of its addresses, 127.0.0.1 or 0.0.0.0") from error
