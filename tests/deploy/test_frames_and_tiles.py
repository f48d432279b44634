"""A capture at a size a person can look at, with its views' aspect ratios kept (tracegs.deploy.tiles,
Camera.reframed, data.source.long_side): on small tensors and a tiny scene, with the real renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from PIL import Image

from tracegs.data.colmap import load_scene, write_colmap_model
from tracegs.data.config import SceneSourceConfig
from tracegs.deploy.config import RefinementConfig, Upscale
from tracegs.deploy.refine import repair_round
from tracegs.deploy.restorers import Clip
from tracegs.deploy.tiles import blend_tiles, cut_tiles, restore_at_frame, tile_boxes, tile_starts
from tracegs.eval.tables_and_figures import qualitative_grid
from tracegs.splat.cameras import Camera, reframe_image
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render
from tracegs.splat.trajectory import TrajectoryConfig

UP = torch.tensor([0.0, 0.0, 1.0])


@pytest.mark.parametrize("length, tile", [(360, 72), (240, 48), (73, 72), (72, 72), (100, 48), (1000, 72)])
def test_tiles_cover_the_frame_and_overlap_their_neighbours(length, tile):
    starts = tile_starts(length, tile, 0.25)
    assert starts[0] == 0 and starts[-1] == max(0, length - tile) and starts == sorted(set(starts))
    covered = np.zeros(length, dtype=bool)
    for start in starts:
        covered[start:start + tile] = True
    assert covered.all()
    assert all(b - a <= 0.75 * tile for a, b in zip(starts, starts[1:]))  # a quarter of each tile shared
    fewer = math.ceil((length - tile) / (0.75 * tile)) if length > tile else 0
    assert len(starts) == fewer + 1  # no more tiles than the overlap needs


class Recording:
    """A restorer with a known pixelwise effect (``effect``) that records the frame sizes it was handed."""

    def __init__(self, effect):
        self.effect, self.sizes = effect, set()

    def restore(self, clips, seed):
        self.sizes |= {tuple(c.frames.shape[-2:]) for c in clips} | {tuple(c.references.shape[-2:]) for c in clips}
        return [self.effect(c.frames) for c in clips]


def clip(height: int, width: int, seed: int = 0) -> Clip:
    g = torch.Generator().manual_seed(seed)
    return Clip(frames=torch.rand(5, 3, height, width, generator=g), cameras=[],
                references=torch.rand(2, 3, height, width, generator=g), caption="")


@pytest.mark.parametrize("upscale", list(Upscale))
def test_a_large_clip_reaches_the_restorer_at_its_frame_and_comes_back_whole(upscale):
    """Feathered tiles sum to one: a restorer that changes each pixel alone (here a gamma curve) gives the same
    frames as applied to the whole clip; the residual way keeps the rendering and adds the upsampled correction."""
    gamma = Recording(lambda frames: frames ** 0.8)
    clips = [clip(60, 90), clip(48, 72, seed=1)]
    out = restore_at_frame(gamma, clips, 0, [24, 36], upscale, 0.25)
    assert gamma.sizes == {(24, 36)}
    assert [tuple(o.shape) for o in out] == [tuple(c.frames.shape) for c in clips]
    if upscale == Upscale.tiles:
        assert all(torch.allclose(o, c.frames ** 0.8, atol=1e-5) for o, c in zip(out, clips))
    else:  # the rendering's detail kept: frames + upsampled (restored - downsized)
        lifted = Recording(lambda frames: frames + 0.1)
        out = restore_at_frame(lifted, clips, 0, [24, 36], upscale, 0.25)
        assert all(torch.allclose(o, (c.frames + 0.1).clamp(0, 1), atol=1e-5) for o, c in zip(out, clips))


def test_clips_at_the_restorers_frame_or_smaller_than_it_are_not_tiled():
    same = Recording(lambda frames: frames)
    small = clip(20, 30)
    assert torch.equal(restore_at_frame(same, [clip(24, 36)], 0, None, Upscale.tiles, 0.25)[0], clip(24, 36).frames)
    out = restore_at_frame(same, [small], 0, [24, 36], Upscale.tiles, 0.25)[0]  # no tile fits: residual
    assert same.sizes == {(24, 36)} and tuple(out.shape[-2:]) == (20, 30)
    assert torch.allclose(out, small.frames, atol=1e-5)


def test_blending_puts_each_tile_where_it_was_cut():
    image = torch.rand(3, 50, 70, generator=torch.Generator().manual_seed(2))
    boxes = tile_boxes((50, 70), (20, 30), 0.25)
    assert torch.allclose(blend_tiles(cut_tiles(image, boxes, (20, 30)), boxes, (50, 70)), image, atol=1e-6)


def scene_model() -> GaussianModel:
    model = GaussianModel.random(300, radius=0.8, generator=torch.Generator().manual_seed(0), initial_opacity=0.9)
    with torch.no_grad():
        model.log_scales.fill_(math.log(0.08))
    return model


def camera(angle: float, width: int, height: int) -> Camera:
    eye = torch.tensor([2.6 * math.cos(angle), 2.6 * math.sin(angle), 0.5])
    return Camera.look_at(eye, torch.zeros(3), UP, fov_x_deg=55.0, width=width, height=height)


def test_a_reframed_portrait_view_sees_the_same_rays_as_the_portrait_view():
    """Camera.reframed and reframe_image move the image plane alike: rendered with the real rasterizer, the part
    of a 16x24 portrait view that its 24x16 landscape frame keeps is the same pixels, none stretched."""
    model, portrait = scene_model(), camera(0.3, 16, 24)
    landscape = portrait.reframed(24, 16)
    assert landscape.K[0, 0] == portrait.K[0, 0] and landscape.K[1, 1] == portrait.K[1, 1]
    upright = render(model, portrait, torch.zeros(3), 0, backend="torch").image
    wide = render(model, landscape, torch.zeros(3), 0, backend="torch").image
    moved = reframe_image(upright, 24, 16)
    assert torch.allclose(moved[..., 4:20], wide[..., 4:20], atol=1e-4)  # the portrait's columns, its middle rows
    assert torch.equal(moved[..., :4], torch.zeros(3, 16, 4))  # beyond the portrait: filled, not stretched
    assert portrait.reframed(16, 24) is portrait


def test_portrait_and_landscape_photos_load_at_the_long_side_with_their_aspect(tmp_path):
    """data.source.long_side: each image downsized to it on its longer side, its own aspect and focal length kept
    (the squashed 72x48 portrait of a fixed frame size is gone); a smaller one is not enlarged."""
    scene = tmp_path / "room"
    sizes = {"a_landscape.png": (90, 60), "b_portrait.png": (60, 90), "c_small.png": (30, 20)}
    cameras = [camera(0.4 * i, w, h) for i, (w, h) in enumerate(sizes.values())]
    (scene / "images").mkdir(parents=True)
    for name, (w, h) in sizes.items():
        Image.fromarray(np.full((h, w, 3), 120, dtype=np.uint8)).save(scene / "images" / name)
    write_colmap_model(scene / "sparse" / "0", cameras, list(sizes))
    loaded = load_scene(SceneSourceConfig(root=str(tmp_path), preset="custom", long_side=36), "room")
    assert [(c.width, c.height) for c in loaded.cameras] == [(36, 24), (24, 36), (30, 20)]
    assert [tuple(loaded.load_image(i).shape[-2:]) for i in range(3)] == [(24, 36), (36, 24), (20, 30)]
    for original, resized in zip(cameras, loaded.cameras):
        fx, fy = float(resized.K[0, 0]) / resized.width, float(resized.K[1, 1]) / resized.height
        assert fx == pytest.approx(float(original.K[0, 0]) / original.width, rel=1e-4)
        assert fy == pytest.approx(float(original.K[1, 1]) / original.height, rel=1e-4)


def test_a_round_over_portrait_and_landscape_views_renders_clips_of_one_frame_and_restores_tiles():
    """Captured views of both orientations share one scene: every clip is rendered at the restorer's aspect with
    the views' longer side (24x16), the restorer sees its own 8x12 frames only, and each pseudo view's restored
    frame has its camera's size."""
    model = scene_model()
    captured = [View(image=torch.rand(3, h, w), camera=camera(a, w, h))
                for a, (w, h) in zip((0.0, 2.1, 4.2), ((24, 16), (16, 24), (24, 16)))]
    fit_cfg = GaussianFitConfig(iterations=40, snapshot_iters=[], seed=0, backend="torch")
    cfg = RefinementConfig(total_iters=40, repair_iters=[10, 20], trajectory=TrajectoryConfig(frames_per_clip=9,
                           ellipse_frames=24), max_clips_per_round=2, restorer_frame=[8, 12])
    cfg.validate()
    fitter = GaussianFitter(model, fit_cfg, 3.0)
    fitter.iteration = 10
    seen = Recording(lambda frames: frames)
    result = repair_round(fitter, captured, seen, 0, cfg, fit_cfg, "", torch.Generator().manual_seed(0))
    assert seen.sizes == {(8, 12)}
    assert {(c.width, c.height) for clip in result.clips for c in clip.cameras} == {(24, 16)}
    assert all(tuple(v.image.shape[-2:]) == (v.camera.height, v.camera.width) for v in result.pseudo)


def test_a_grid_of_portrait_and_landscape_views_keeps_each_shape():
    landscape, portrait = torch.zeros(3, 16, 24), torch.ones(3, 24, 16)
    grid = qualitative_grid({"3DGS": [landscape, portrait], "GT": [landscape, portrait]}, min_cell_height=16)
    assert grid.shape[1] == 2 * 24 and grid.shape[0] == 28 + 16 + 24  # label strip, then one row per view
    assert (grid[28 + 16:, 4:20] == 255).all() and (grid[28 + 16:, :4] == 255).all()  # the portrait centred
