"""The scenes as deployment fits, restores and scores them (``deployment_source``), on a tiny scene written to disk
at 24x32 whose restorer works on 16x24 clips (another aspect ratio, as DL3DV's images_4 against 480x720).

Size (``deploy.resolution``).
GSFixer's release (``dataset``): the scene's own images, each clip resized bilinearly to the restorer's size
(gsfixer/extrapolation/outpaint/base.py l. 63, sparse.py l. 287-296), the restored frames kept at that size and each
pseudo view's render resized bilinearly to them (train.py l. 204-208); corrected (``frame``): every image resized
to data.source's 16x24 on load, and everything at that size.

Sparse views (``deploy.view_rule``): GSFixer's one loader picks every dataset's, DL3DV's included, by np.linspace
(datasets/colmap_debug.py l. 402-422); the DL3DV config's own rule is nested.
"""

import json

import pytest
import torch

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig, SyntheticConfig, ViewRule
from tracegs.data.splits import every_nth_test, linspace_views
from tracegs.data.synthetic import generate_scene, scene_name
from tracegs.deploy.config import EvaluationConfig, RefinementConfig, Resolution
from tracegs.deploy.refine import cold_start, repair_round
from tracegs.deploy.scenes import deployment_source, initial_model, load_unit
from tracegs.errors import ConfigError
from tracegs.eval.merge import unit_path
from tracegs.eval.scoring import score_units
from tracegs.splat.config import DensificationConfig, GaussianFitConfig, TrajectoryConfig
from tracegs.splat.fit import GaussianFitter, View

SEED = 100
STORED = (24, 32)  # the dataset's own images (GSFixer's images_4)
CLIP = (16, 24)  # the restorer's frames (480x720 at the paper scale)


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("stored")
    cfg = SyntheticConfig(root=str(root), num_views=16, height=STORED[0], width=STORED[1], num_objects=1,
                          gaussians_per_unit_area=150, init_points=400)
    generate_scene(SEED, cfg, root)
    return root


def _source(root) -> SceneSourceConfig:
    return SceneSourceConfig(root=str(root), height=CLIP[0], width=CLIP[1])


def _configs(resolution: Resolution) -> tuple[GaussianFitConfig, RefinementConfig]:
    fit_cfg = GaussianFitConfig(iterations=30, snapshot_iters=[], densification=DensificationConfig(enabled=False))
    refine_cfg = RefinementConfig(total_iters=30, repair_iters=[8, 20], max_clips_per_round=1,
                                  trajectory=TrajectoryConfig(frames_per_clip=9, ellipse_frames=24,
                                                              captured_ends=True),
                                  resolution=resolution, clip_size=list(CLIP))
    return fit_cfg, refine_cfg


class _Echo:
    """A restorer that hands back the frames it was given: what reached it is what the pseudo views hold."""

    identity = "echo"

    def __init__(self):
        self.seen = []

    def restore(self, clips, seed):
        self.seen.extend(clips)
        return [clip.frames.clone() for clip in clips]


def _bilinear(images: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.interpolate(images, size=CLIP, mode="bilinear", align_corners=False)


@pytest.mark.parametrize("resolution, fitted", [(Resolution.dataset, STORED), (Resolution.frame, CLIP)])
def test_clips_reach_the_restorer_at_its_size_and_the_fit_stays_at_the_protocols(scene_root, resolution, fitted):
    fit_cfg, refine_cfg = _configs(resolution)
    source = deployment_source(_source(scene_root), refine_cfg)
    unit = load_unit(load_scene(source, scene_name(SEED)), 3, source)
    assert all(tuple(v.image.shape[-2:]) == fitted for v in unit.captured)
    assert all(tuple(image.shape[-2:]) == fitted for image in unit.test_images)  # scored at this size
    cold = cold_start(unit.captured, initial_model(unit.scene, unit.captured_ids, unit.captured, fit_cfg),
                      refine_cfg, fit_cfg)
    echo = _Echo()
    rnd = repair_round(cold, unit.captured, echo, 0, refine_cfg, fit_cfg, "", torch.Generator().manual_seed(0))
    (clip,) = echo.seen
    assert tuple(clip.frames.shape[-2:]) == CLIP and tuple(clip.references.shape[-2:]) == CLIP
    assert all((c.height, c.width) == fitted for c in clip.cameras)  # rendered at the fit's size
    # The captured ends are the reference images resized bilinearly (as the renders are), not Lanczos-loaded ones.
    first = min(unit.captured, key=lambda v: float((v.camera.center - clip.cameras[0].center).norm())).image
    expected = _bilinear(first[None])[0] if resolution == Resolution.dataset else first
    assert torch.allclose(clip.frames[0], expected, atol=1e-6)
    # Pseudo views: the restored frame at the restorer's size, at the camera it was rendered from.
    assert all(tuple(v.image.shape[-2:]) == CLIP and (v.camera.height, v.camera.width) == fitted for v in rnd.pseudo)


def test_a_pseudo_view_at_the_clips_size_is_compared_with_its_render_resized_bilinearly(scene_root):
    """train.py l. 204-208: the render of a pseudo view of another size is resized (bilinear) to its image."""
    fit_cfg, refine_cfg = _configs(Resolution.dataset)
    source = deployment_source(_source(scene_root), refine_cfg)
    unit = load_unit(load_scene(source, scene_name(SEED)), 3, source)
    fitter = GaussianFitter(initial_model(unit.scene, unit.captured_ids, unit.captured, fit_cfg), fit_cfg, 3.0)
    camera = unit.test_cameras[0]
    with torch.no_grad():
        full = fitter._render(View(image=unit.test_images[0], camera=camera), 0)[0]
        rendered = fitter._render(View(image=_bilinear(unit.test_images[0][None])[0], camera=camera), 0)[0]
    assert tuple(rendered.shape[-2:]) == CLIP
    assert torch.allclose(rendered, _bilinear(full[None])[0], atol=1e-6)


@pytest.mark.parametrize("resolution, scored", [(Resolution.dataset, STORED), (Resolution.frame, CLIP)])
def test_evaluation_scores_the_test_views_at_the_protocols_size(scene_root, tmp_path, resolution, scored):
    fit_cfg, refine_cfg = _configs(resolution)
    cfg = EvaluationConfig(out_dir=str(tmp_path / "eval"), views=[3], methods=["3dgs"], lpips=False,
                           per_step=False, save_media=False, save_models=True, progress=False, workers=1)
    score_units(cfg, _source(scene_root), refine_cfg, fit_cfg, {"3dgs": None}, scenes=[scene_name(SEED)])
    record = json.loads(unit_path(cfg.out_dir, scene_name(SEED), 3).read_text())
    assert {tuple(view["size"]) for view in record["cameras"].values()} == {scored}


def test_the_datasets_own_size_needs_the_restorers_clip_size():
    with pytest.raises(ConfigError, match="clip_size"):
        RefinementConfig(resolution=Resolution.dataset, clip_size=None).validate()


@pytest.mark.parametrize("rule", [ViewRule.linspace, None])
def test_deployment_picks_the_sparse_views_by_its_own_rule_over_the_datasets(scene_root, rule):
    """DL3DV's config nests its view sets; under GSFixer's release deployment takes linspace's, each set on its own
    (datasets/colmap_debug.py l. 416-422); ``view_rule: null`` keeps the dataset's."""
    _, refine_cfg = _configs(Resolution.frame)
    refine_cfg.view_rule = rule
    nested = SceneSourceConfig(root=str(scene_root), view_rule=ViewRule.nested)
    source = deployment_source(nested, refine_cfg)
    scene = load_scene(source, scene_name(SEED))
    test = every_nth_test(len(scene), 8)
    train = [i for i in range(len(scene)) if i not in test]
    chosen = {k: load_unit(scene, k, source).captured_ids for k in (3, 6)}
    if rule == ViewRule.linspace:
        assert chosen == {k: linspace_views(train, k) for k in (3, 6)}
        assert not set(chosen[3]) <= set(chosen[6])  # not nested: 14 training views, linspace's ends move
    else:
        assert set(chosen[3]) <= set(chosen[6]) and chosen[3] != linspace_views(train, 3)
