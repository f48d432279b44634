"""Names of the files and tensors of a paired-clip cache and of its manifest (supplement A.4).

Per scene (``<cache>/<scene>/``):

- ``clip_NNN.safetensors``, one per clip: the codec latent of every condition the clip holds (its student
  view count K's snapshots R_s, the teacher conditions R_d, the pseudo-target), the clip's camera poses and,
  only with ``data.prepare.store_frames``, uint8 frames of those conditions, the target, the two reference
  frames and ground truth. Its metadata names K, the reference views and the caption.
- ``refs/view_VVVV.safetensors``: the 2D reference tokens of one reference view (DINOv2 encodes each view
  alone, so a view's tokens are the same in every pair it belongs to).
- ``refs/pair_AAAA_BBBB.safetensors``: the 3D reference tokens of one ordered reference pair (VGGT attends
  across the two views, so its tokens are the pair's, not each view's).
- ``text/<digest>.safetensors``: the text embedding of one distinct caption.

Clips index the scene files instead of each holding a copy. ``prepare`` writes these names; the datamodule
and the held-out evaluations (``eval.clips``, ``eval.privileged``) read them, so they live here once.
"""

from __future__ import annotations

import hashlib

from tracegs.data.splits import view_set_key

MANIFEST = "manifest.json"
# Layout version of the manifest: 2 = one student view count per clip, latents only by default, reference
# tokens and text embeddings in per-scene files.
CACHE_VERSION = 2

TARGET = "target"  # the pseudo-target clip (ground truth, restorer output or R_d: data.prepare.pseudo_target)
REFERENCE = "ref"  # the two reference frames at the clip ends
GROUND_TRUTH = "gt"  # the true frames, where the scene is known (synthetic benchmark)

REF_2D = "ref_2d"  # 2D reference tokens (DINOv2 features, main paper Sec. 3.2), in a view file
REF_3D = "ref_3d"  # 3D reference tokens (VGGT features, main paper Sec. 3.2), in a pair file
TEXT = "text"  # caption embedding (T5), in a text file
POSES = "poses"  # world-to-camera matrices of the clip's frames
INTRINSICS = "intrinsics"  # camera matrices of the clip's frames

# Clip metadata naming what the clip indexes.
META_VIEWS = "student_views"  # the clip's student view count K
META_REFS = "refs"  # JSON [a, b]: image indices of the two reference views
META_TEXT = "text_file"  # the text file of the clip's caption, relative to the scene folder
# A held-out clip through captured cameras (tracegs/data/held_out.py): JSON, the captured image index of each
# frame, ends included (a padded clip repeats some), and the capture-order rule the clip was built with.
META_CAPTURED_IMAGES = "captured_images"
META_CAPTURE_ORDER = "capture_order"


def student_prefix(views: int | None) -> str:
    """The part of a student condition's key before its snapshot: every ``s{K}_it*`` of ``K`` views."""
    return f"s{view_set_key(views)}_it"


def condition_key(views: int | None, snapshot: int | None = None) -> str:
    """Cache key of a rendered condition: ``s{K}_it{snapshot}`` (student) or ``d{V}`` (final snapshot)."""
    return f"{student_prefix(views)}{snapshot}" if snapshot is not None else f"d{view_set_key(views)}"


def student_order(name: str) -> tuple[int, int]:
    """(K, snapshot) of a student condition key ``s{K}_it{snapshot}``: the order conditions are listed in."""
    views, _, snapshot = name[1:].partition("_it")
    return int(views), int(snapshot)


def latent(name: str) -> str:
    """Key of the codec latent of a condition or of ``TARGET``."""
    return f"latent/{name}"


def frames(name: str) -> str:
    """Key of the uint8 frames of a condition, ``TARGET``, ``REFERENCE`` or ``GROUND_TRUTH``."""
    return f"frames/{name}"


def clip_file(index: int) -> str:
    return f"clip_{index:03d}.safetensors"


def view_tokens_file(view: int) -> str:
    """The file (relative to the scene folder) of one reference view's 2D tokens."""
    return f"refs/view_{view:04d}.safetensors"


def pair_tokens_file(first: int, second: int) -> str:
    """The file (relative to the scene folder) of one ordered reference pair's 3D tokens."""
    return f"refs/pair_{first:04d}_{second:04d}.safetensors"


def text_file(caption: str) -> str:
    """The file (relative to the scene folder) of one caption's embedding, named by a digest of the caption."""
    return f"text/{hashlib.sha256(caption.encode()).hexdigest()[:16]}.safetensors"
