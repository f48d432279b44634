"""Where a run's scenes come from: the procedural benchmark (``data.source.preset=synthetic``, scenes generated from
seeds and known exactly) or captured scenes in COLMAP layout (a dataset on disk, or a capture of the user's own).
Every difference between the two that a command meets is answered here, so no other module tests the preset:
which scenes each split holds, whether scenes are generated before use, and whether ground truth exists at any
pose (the procedural scenes' Gaussians) or only at the captured views.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from tracegs.data.colmap import Scene, list_scenes, training_scenes
from tracegs.data.config import SceneSourceConfig, SyntheticConfig, is_procedural
from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark, render_ground_truth
from tracegs.splat.cameras import Camera

# Ground truth at arbitrary poses, where the scene is known (the procedural benchmark): (scene, cameras) ->
# [F,3,H,W] in [0,1]. Used for the videos' GT column and the per-step (Fig. 6) curves.
GroundTruthRenderer = Callable[[Scene, Sequence[Camera]], Tensor]


@dataclass(frozen=True)
class SceneSource:
    """The scenes of a run's ``data`` group: ``source`` always, and ``procedural`` (``data.synthetic``) when they
    are the procedural benchmark's, None for captured scenes."""

    source: SceneSourceConfig
    procedural: SyntheticConfig | None

    @classmethod
    def of(cls, data: DictConfig) -> SceneSource:
        """The scene source a composed ``data`` node describes."""
        source: SceneSourceConfig = OmegaConf.to_object(data.source)
        return cls(source, OmegaConf.to_object(data.synthetic) if is_procedural(source) else None)

    def training_scene_names(self) -> list[str]:
        """The scenes restorers train on: the benchmark's training seeds, or the dataset's training list."""
        if self.procedural is not None:
            return benchmark_scene_names(self.procedural, "train")
        return training_scenes(self.source)

    def test_scene_names(self) -> list[str]:
        """The scenes evaluation deploys on: the benchmark's test seeds, or the dataset's test list."""
        if self.procedural is not None:
            return benchmark_scene_names(self.procedural, "test")
        return list_scenes(self.source, "test")

    def generate(self, splits: tuple[str, ...], progress: bool = True) -> None:
        """Write the procedural scenes of ``splits`` where missing; captured scenes are already on disk."""
        if self.procedural is not None:
            generate_benchmark(self.procedural, splits=splits, progress=progress)

    @property
    def ground_truth_renderer(self) -> GroundTruthRenderer | None:
        """Renders ground truth at any pose where the scene is known (the procedural benchmark), else None."""
        return render_ground_truth if self.procedural is not None else None
