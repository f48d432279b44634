"""Train/test splits and nested sparse/dense view sets (paper Sec. 4.1 "Training Data").

TRACE-GS pairs a sparse view set V_s (K = 3, 6, 9) with a denser V_d (12, 18, all training views) and
requires V_s to be a subset of V_d. Mip-NeRF 360 / ReconFusion publish ``train_test_split_{n}.json``
(``train_ids`` / ``test_ids`` index the images sorted by name); they are honoured when present, as published:
nothing says a scene's 3-, 6- and 9-view files are nested, and evaluating a K-view set needs only that set and
the test views. Only training clips need V_s inside V_d (``require_sparse_in_dense``, called by prepare).
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

from tracegs.errors import ConfigError

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


def images_needed(views: int, test_every: int) -> int:
    """The fewest images whose every-``test_every``-th split (:func:`every_nth_test`) leaves ``views`` training
    views: how many images a capture without split files must have for a ``views``-view set."""
    count = views
    while count - len(every_nth_test(count, test_every)) < views:
        count += 1
    return count


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


def split_file(split_dir: Path, count: int) -> Path:
    """Where a scene folder lists its published ``count``-view set: ``train_test_split_{count}.json``."""
    return Path(split_dir) / f"train_test_split_{count}.json"


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
    verbatim for that view set, nested in the others or not (and its ``test_ids`` for the test split, which
    the scene's files must share: one test set serves all its view sets). ``test_indices`` overrides
    the every-``test_every`` rule (e.g. NeRFBusters' separate evaluation capture). The ladder
    ``NESTED_VIEW_COUNTS`` is always built too (the counts the scene has views for), so each set does not
    depend on which other counts the caller asked for.
    """
    requested = {c for c in view_counts if c is not None}
    json_sets: dict[int, tuple[Path, list[int]]] = {}
    json_test: list[int] | None = None
    if split_dir is not None:
        for count in sorted(requested | set(NESTED_VIEW_COUNTS)):
            path = split_file(split_dir, count)
            if path.is_file():
                train_ids, test_ids = read_split_json(path, num_images)
                if len(train_ids) != count:
                    raise SplitError(f"{path}: lists {len(train_ids)} train_ids, expected {count}")
                if json_test is not None and test_ids != json_test:
                    first = json_sets[min(json_sets)][0].name
                    raise SplitError(f"{path}: test_ids differ from {first}'s; one test set serves every view set "
                                     "of a scene, so give the scene's split files the same test_ids")
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
    for count in counts:
        if count > len(train):
            raise SplitError(f"asked for {count} training views, but of the scene's {num_images} images "
                             f"{len(test)} are held out for testing, leaving {len(train)} usable")
        if count in json_sets:
            path, chosen = json_sets[count]
            overlap = set(chosen) & held_out
            if overlap:
                raise SplitError(f"{path}: train_ids {sorted(overlap)[:5]} are test views")
        elif view_rule == "linspace":  # each set on its own: not nested
            chosen = linspace_views(train, count)
        else:  # grows the largest smaller set, a published one included
            chosen = grow_evenly(train, previous, count)
        view_sets[view_set_key(count)] = chosen
        previous = chosen
    if any(c is None for c in view_counts):
        view_sets["all"] = list(train)
    return SceneSplit(test=test, train=train, view_sets=view_sets)


def require_sparse_in_dense(split: SceneSplit, sparse: Sequence[int], dense: Sequence[int | None], split_dir: Path,
                            view_rule: str) -> None:
    """Refuse, naming what to change, a scene whose sparse set V_s is not inside a dense set V_d it is paired with.

    Training clips pair every sparse set with every dense set, and the method needs V_s inside V_d (paper Sec. 3:
    the dense reconstruction sees what the sparse one sees, and more). Evaluating a K-view set needs only that
    set, so ``make_split`` takes published sets as they are and prepare of training clips checks here. The
    culprit is a published split file (nothing makes a scene's 3-, 6- and 9-view files nested) or, with no file,
    the linspace rule, which picks each set on its own. All training views (``None``) hold every sparse set.
    """
    for count in sparse:
        for denser in (d for d in dense if d is not None):
            outside = sorted(set(split.views(count)) - set(split.views(denser)))
            if not outside:
                continue
            published = [p for p in (split_file(split_dir, count), split_file(split_dir, denser)) if p.is_file()]
            if not published:
                raise ConfigError("data.source.view_rule",
                                  f"{view_rule} picks each view set on its own, and scene {Path(split_dir).name}'s "
                                  f"{count}-view set has views {outside[:5]} outside its {denser}-view set; training "
                                  "clips need V_s inside V_d (paper Sec. 3): use nested")
            raise SplitError(f"{published[0]}: views {outside[:5]} of the {count}-view set are not in the "
                             f"{denser}-view set, and training clips need V_s inside V_d (paper Sec. 3); prepare "
                             "them with data.prepare.dense_views=[null] (all training views) or without the "
                             "scene's split files")


def split_scene(scene: Scene, source: SceneSourceConfig, view_counts: Sequence[int | None]) -> SceneSplit:
    """The split of a loaded scene: its ReconFusion files, the preset's test views or every
    ``source.test_every``-th image, and the view sets of ``source.view_rule``. Prepare and evaluation both call
    this."""
    from tracegs.data.colmap import test_indices_for

    return make_split(len(scene), view_counts, source.test_every, split_dir=scene.root,
                      test_indices=test_indices_for(source, scene), view_rule=source.view_rule)
