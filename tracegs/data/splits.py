"""Train/test splits and nested sparse/dense view sets (paper Sec. 4.1 "Training Data").

TRACE-GS pairs a sparse view set V_s (K = 3, 6, 9) with a denser V_d (12, 18, all training views) and
requires V_s to be a subset of V_d. Mip-NeRF 360 / ReconFusion publish ``train_test_split_{n}.json``
(``train_ids`` / ``test_ids`` index the images sorted by name); they are honoured when present.
Otherwise the test views are every 8th image and each view set is spread evenly around the capture,
grown greedily so that V_3 in V_6 in V_9 in V_12 in V_18 in all (``view_rule`` nested), or, with ``view_rule``
linspace, picked as GSFixer picks its sparse views: ``linspace_views``, each set on its own.

Every split builds the whole ladder ``NESTED_VIEW_COUNTS`` (as far as the scene has views), whatever
counts the caller asks for, so a K-view set is the same set in prepare, training and evaluation.
``split_scene`` is the one entry point all of them use.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from tracegs.data.colmap import Scene
    from tracegs.data.config import SceneSourceConfig

# The paper's view-set ladder (Sec. 4.1): sparse K = 3, 6, 9, dense 12, 18 (and all training views).
NESTED_VIEW_COUNTS = (3, 6, 9, 12, 18)


class SplitError(ValueError):
    """A split cannot be built from the given scene and view counts."""


def view_set_key(count: int | None) -> str:
    """Name of a view set: ``"3"``, ``"12"``, ... or ``"all"`` for ``None`` (every training view)."""
    return "all" if count is None else str(int(count))


@dataclass(frozen=True)
class SceneSplit:
    """Image indices of one scene: held-out test views, all training views and the nested view sets."""

    test: list[int]
    train: list[int]
    view_sets: dict[str, list[int]]

    def views(self, count: int | None) -> list[int]:
        key = view_set_key(count)
        if key not in self.view_sets:
            raise KeyError(f"view set {key!r} was not built (have {sorted(self.view_sets)})")
        return self.view_sets[key]

    def to_dict(self) -> dict:
        return {"test": self.test, "train": self.train, "view_sets": self.view_sets}

    @classmethod
    def from_dict(cls, data: dict) -> SceneSplit:
        return cls(test=list(data["test"]), train=list(data["train"]), view_sets=dict(data["view_sets"]))


def every_nth_test(num_images: int, test_every: int) -> list[int]:
    """The LLFF / Mip-NeRF 360 convention: images 0, n, 2n, ... are held out."""
    if test_every <= 1:
        raise SplitError(f"test_every must be >= 2, got {test_every}")
    return list(range(0, num_images, test_every))


def even_centres(n: int, count: int) -> list[float]:
    """Positions ``(i + 1/2) n / count - 1/2`` of the centres of ``count`` equal shares of ``n`` items."""
    return [(i + 0.5) * n / count - 0.5 for i in range(count)]


def spread_evenly(candidates: Sequence[int], count: int) -> list[int]:
    """The ``count`` of ``candidates`` nearest the centres of ``count`` equal shares, in candidate order
    (distinct when ``count <= len(candidates)``: the centres are at least one item apart)."""
    n = len(candidates)
    return [candidates[min(n - 1, round(c))] for c in even_centres(n, count)]


def grow_evenly(candidates: Sequence[int], keep: Sequence[int], count: int) -> list[int]:
    """Extend ``keep`` to ``count`` indices drawn from ``candidates``, spread evenly around the capture.

    Distances are taken around the loop of ``candidates`` (capture order), because on a 360-degree capture
    the first and last images are neighbours. The first set (``keep`` empty) takes the centres of ``count``
    equal shares, ``(i + 1/2) n / count``; later, nested sets add one candidate at a time, the one farthest
    (around the loop) from every chosen one, ties to the one nearest such a centre, then to the earliest.
    Written by hand because no library does nested even spacing.
    """
    n = len(candidates)
    if count > n:
        raise SplitError(f"asked for {count} training views but the scene has only {n}")
    position = {c: i for i, c in enumerate(candidates)}
    centres = even_centres(n, count)
    if not keep:
        return sorted(spread_evenly(candidates, count))

    def loop_distance(a: float, b: float) -> float:
        return min(abs(a - b), n - abs(a - b))

    chosen = {position[index] for index in keep}
    while len(chosen) < count:
        # Farthest from the chosen views; among equals, nearest to one of this count's even centres.
        chosen.add(max((i for i in range(n) if i not in chosen),
                       key=lambda i: (min(loop_distance(i, c) for c in chosen),
                                      -min(loop_distance(i, c) for c in centres), -i)))
    return sorted(candidates[i] for i in chosen)


def linspace_views(candidates: Sequence[int], count: int) -> list[int]:
    """GSFixer's sparse views (its release, datasets/colmap_debug.py l. 419-422): ``count`` positions of
    ``np.linspace(0, n - 1, count)``, both ends included, rounded half to even as Python's ``round``."""
    n = len(candidates)
    if count > n:
        raise SplitError(f"asked for {count} training views but the scene has only {n}")
    return [candidates[round(float(i))] for i in np.linspace(0, n - 1, count)]


def read_split_json(path: Path, num_images: int) -> tuple[list[int], list[int]]:
    """``(train_ids, test_ids)`` from a ReconFusion split file, validated against the image count."""
    try:
        data = json.loads(path.read_text())
        train, test = [int(i) for i in data["train_ids"]], [int(i) for i in data["test_ids"]]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise SplitError(f"{path}: not a valid split file ({error})") from error
    bad = [i for i in train + test if not 0 <= i < num_images]
    if bad:
        raise SplitError(f"{path}: indices {bad[:5]} out of range for {num_images} images")
    return sorted(train), sorted(test)


def make_split(
    num_images: int,
    view_counts: Sequence[int | None],
    test_every: int = 8,
    split_dir: Path | None = None,
    test_indices: Sequence[int] | None = None,
    view_rule: str = "nested",
) -> SceneSplit:
    """Build the test split and the view sets of one scene (``view_rule``: see ``data.config.ViewRule``).

    ``split_dir`` is searched for ``train_test_split_{n}.json``; a file found for a count is used
    verbatim for that view set (and its ``test_ids`` for the test split). ``test_indices`` overrides
    the every-``test_every`` rule (e.g. NeRFBusters' separate evaluation capture). The ladder
    ``NESTED_VIEW_COUNTS`` is always built too (the counts the scene has views for), so each set does not
    depend on which other counts the caller asked for.
    """
    requested = {c for c in view_counts if c is not None}
    json_sets: dict[int, tuple[Path, list[int]]] = {}
    json_test: list[int] | None = None
    if split_dir is not None:
        for count in sorted(requested | set(NESTED_VIEW_COUNTS)):
            path = Path(split_dir) / f"train_test_split_{count}.json"
            if path.is_file():
                train_ids, test_ids = read_split_json(path, num_images)
                if len(train_ids) != count:
                    raise SplitError(f"{path}: lists {len(train_ids)} train_ids, expected {count}")
                if json_test is not None and test_ids != json_test:
                    raise SplitError(f"{path}: test_ids differ from the other split files")
                json_test = test_ids
                json_sets[count] = (path, train_ids)
    if json_test is not None:
        test = json_test
    elif test_indices is not None:
        test = sorted(int(i) for i in test_indices)
    else:
        test = every_nth_test(num_images, test_every)
    held_out = set(test)
    train = [i for i in range(num_images) if i not in held_out]
    counts = sorted(requested | set(json_sets) | {c for c in NESTED_VIEW_COUNTS if c <= len(train)})
    view_sets: dict[str, list[int]] = {}
    previous: list[int] = []
    previous_name = "the empty set"
    for count in counts:
        if count > len(train):
            raise SplitError(f"asked for {count} training views, but of the scene's {num_images} images "
                             f"{len(test)} are held out for testing, leaving {len(train)} usable")
        if count in json_sets:
            path, chosen = json_sets[count]
            if view_rule == "nested" and not set(previous) <= set(chosen):
                raise SplitError(f"{path}: not a superset of {previous_name}; view sets must be nested")
            overlap = set(chosen) & held_out
            if overlap:
                raise SplitError(f"{path}: train_ids {sorted(overlap)[:5]} are test views")
            previous_name = path.name
        elif view_rule == "linspace":  # each set on its own: not nested
            chosen = linspace_views(train, count)
        else:
            chosen = grow_evenly(train, previous, count)
            previous_name = f"the {count}-view set"
        view_sets[view_set_key(count)] = chosen
        previous = chosen
    if any(c is None for c in view_counts):
        view_sets["all"] = list(train)
    return SceneSplit(test=test, train=train, view_sets=view_sets)


def split_scene(scene: Scene, source: SceneSourceConfig, view_counts: Sequence[int | None]) -> SceneSplit:
    """The split of a loaded scene: its ReconFusion files, the preset's test views or every
    ``source.test_every``-th image, and the view sets of ``source.view_rule``. Prepare and evaluation both call
    this."""
    from tracegs.data.colmap import test_indices_for

    return make_split(len(scene), view_counts, source.test_every, split_dir=scene.root,
                      test_indices=test_indices_for(source, scene), view_rule=source.view_rule)
