"""Names of the tensors in a paired-clip cache shard and of the cache's manifest (supplement A.4).

One safetensors shard per clip holds, for every rendered condition (a student R_s at a snapshot, or a
dense R_d), its codec latent and its uint8 frames, plus the target's latent and frames, the two reference
frames and the frozen reference / text encodings. ``prepare`` writes these names; the datamodule and the
held-out evaluations (``eval.clips``, ``eval.privileged``) read them, so they live here once.
"""

from __future__ import annotations

from tracegs.data.splits import view_set_key

MANIFEST = "manifest.json"

TARGET = "target"  # the pseudo-target clip (ground truth, restorer output or R_d: data.prepare.pseudo_target)
REFERENCE = "ref"  # the two reference frames at the clip ends
GROUND_TRUTH = "gt"  # the true frames, where the scene is known (synthetic benchmark)

REF_2D = "ref_2d"  # 2D reference tokens (DINOv2 features, main paper Sec. 3.2)
REF_3D = "ref_3d"  # 3D reference tokens (VGGT features, main paper Sec. 3.2)
TEXT = "text"  # caption embedding (T5)
POSES = "poses"  # world-to-camera matrices of the clip's frames
INTRINSICS = "intrinsics"  # camera matrices of the clip's frames


def student_prefix(views: int | None) -> str:
    """The part of a student condition's key before its snapshot: every ``s{K}_it*`` of ``K`` views."""
    return f"s{view_set_key(views)}_it"


def condition_key(views: int | None, snapshot: int | None = None) -> str:
    """Cache key of a rendered condition: ``s{K}_it{snapshot}`` (student) or ``d{V}`` (final snapshot)."""
    return f"{student_prefix(views)}{snapshot}" if snapshot is not None else f"d{view_set_key(views)}"


def latent(name: str) -> str:
    """Key of the codec latent of a condition or of ``TARGET``."""
    return f"latent/{name}"


def frames(name: str) -> str:
    """Key of the uint8 frames of a condition, ``TARGET``, ``REFERENCE`` or ``GROUND_TRUTH``."""
    return f"frames/{name}"
