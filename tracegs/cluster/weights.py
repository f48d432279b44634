"""The released models the paper scale reads (supplement A.1-A.3: GSFixer's restorer on CogVideoX-5B-I2V, DINOv2 +
VGGT reference encoders, T5; BLIP-2 captions; VGG16 for LPIPS), as ``tracegs-weights`` (tracegs/cli/weights.py)
handles them: fetch them into the folders ``paths.weights_dir`` expects, record each file's bytes and SHA-256 in ``<weights_dir>/MANIFEST.json``, and verify a
tree against it without network.

Modes of ``tracegs-weights``:

- (no flag) fetch with huggingface_hub (the Hub's repositories) and torch.hub (torchvision's VGG16 file), then
  write the manifest;
- ``--dry-run``: the repositories, files and bytes a fetch would bring, listed by the Hub; offline (``--offline`` or
  the Hub unreachable) from the declared list below, each size marked declared or unknown;
- ``--check``: every file of the manifest present with its bytes and SHA-256 (``--sizes-only``: bytes alone,
  seconds instead of minutes for ~40 GB); the first mismatch is one line naming the file, exit 2;
- ``--record``: write the manifest of a tree fetched another way (copied from another cluster).

The repositories are those GSFixer's release downloads (``download/download_ckpt_hf.py``: flow666/GSFixer,
zai-org/CogVideoX-5b-I2V, facebook/VGGT-1B, facebook/dinov2-with-registers-large, Salesforce/blip2-opt-2.7b), each
narrowed to the files this code reads (CogVideoX's VAE, T5 and tokenizer: its transformer is GSFixer's; safetensors
only where a repository ships both formats).
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from tracegs.errors import InputFileError

MANIFEST = "MANIFEST.json"
CHUNK = 16 * 2**20


@dataclass(frozen=True)
class Release:
    """One released model: where it comes from and the folder (or file) under ``paths.weights_dir`` it fills."""

    name: str  # the name the GPU check reports it under
    target: str  # relative to paths.weights_dir
    repo: str | None = None  # a Hub model repository, fetched with huggingface_hub
    url: str | None = None  # a single file, fetched with torch.hub (its name's hash prefix checked)
    patterns: tuple[str, ...] | None = None  # the repository's files fetched (None: all of them)
    # Files known to be in the release with their bytes (None: size not declared here; the Hub lists it online).
    files: tuple[tuple[str, int | None], ...] = ()


RELEASES = (
    # GSFixer's release: its reference-guided CogVideoX transformer (config.json + weights). The file list is not
    # declared here: the Hub lists it.
    Release("gsfixer_transformer", "gsfixer", repo="flow666/GSFixer"),
    Release("cogvideox", "CogVideoX-5b-I2V", repo="zai-org/CogVideoX-5b-I2V",
            patterns=("vae/*", "text_encoder/*", "tokenizer/*"),
            files=(("vae/config.json", None), ("vae/diffusion_pytorch_model.safetensors", None),
                   ("text_encoder/config.json", None), ("text_encoder/model.safetensors.index.json", None),
                   ("tokenizer/spiece.model", None), ("tokenizer/tokenizer_config.json", None))),
    Release("dinov2", "dinov2-with-registers-large", repo="facebook/dinov2-with-registers-large",
            patterns=("*.json", "*.safetensors"), files=(("config.json", None), ("model.safetensors", None))),
    Release("vggt", "VGGT-1B", repo="facebook/VGGT-1B", patterns=("*.json", "*.safetensors"),
            files=(("config.json", None), ("model.safetensors", None))),
    Release("blip2_captioner", "blip2-opt-2.7b", repo="Salesforce/blip2-opt-2.7b",
            patterns=("*.json", "*.txt", "*.safetensors"),
            files=(("config.json", None), ("preprocessor_config.json", None),
                   ("model.safetensors.index.json", None))),
    # torchvision's VGG16 ImageNet file (VGG16_Weights.IMAGENET1K_V1: 527.8 MB in torchvision's weight table); its
    # name carries the first 8 hex digits of its SHA-256, checked on download.
    Release("vgg16_lpips", "vgg16-397923af.pth", url="https://download.pytorch.org/models/vgg16-397923af.pth",
            files=(("", 553433881),)),
)


def weight_paths(cfg) -> dict[str, str | None]:
    """Every released model the composed config reads, by name: its configured local path (None where unused)."""
    backbone, deploy, evaluation = cfg.backbone, cfg.deploy, cfg.evaluation
    return {"gsfixer_transformer": backbone.transformer.pretrained_path,
            "cogvideox_vae": backbone.codec.pretrained_path,
            "t5_text_encoder": backbone.text_encoder.pretrained_path,
            "t5_tokenizer": backbone.text_encoder.tokenizer_path,
            "dinov2": backbone.reference_encoder.dino_path,
            "vggt": backbone.reference_encoder.vggt_path,
            "blip2_captioner": deploy.captions.blip2_path,
            "vgg16_lpips": evaluation.lpips_weights}


def declared_listing(release: Release) -> list[dict]:
    """The files of ``release`` this module declares, with their bytes where declared."""
    return [{"path": str(Path(release.target, name)) if name else release.target, "bytes": size,
             "size": "declared" if size is not None else "unknown"} for name, size in release.files]


def hub_listing(release: Release) -> list[dict]:
    """The files of ``release`` the Hub lists now (matching its patterns), with their bytes."""
    from huggingface_hub import HfApi

    info = HfApi().model_info(release.repo, files_metadata=True)
    return [{"path": str(Path(release.target, item.rfilename)), "bytes": item.size, "size": "listed by the Hub"}
            for item in info.siblings
            if release.patterns is None or any(fnmatch.fnmatch(item.rfilename, p) for p in release.patterns)]


def dry_run(offline: bool) -> list[dict]:
    """What a fetch would bring, per release: source, target and files (listed online, else declared)."""
    plan = []
    for release in RELEASES:
        listing, listed = declared_listing(release), "declared"
        if release.repo is not None and not offline:
            try:
                listing, listed = hub_listing(release), "Hub"
            except Exception as error:  # noqa: BLE001 (no network, or the Hub refuses: the declared list stands)
                listed = f"declared (Hub unreachable: {type(error).__name__})"
        plan.append({"name": release.name, "source": release.repo or release.url, "target": release.target,
                     "patterns": list(release.patterns or ["*"]) if release.repo else None, "listed": listed,
                     "files": listing})
    return plan


def print_plan(plan: list[dict]) -> None:
    total, unknown = 0, 0
    for release in plan:
        patterns = f" [{', '.join(release['patterns'])}]" if release["patterns"] else ""
        print(f"{release['source']}{patterns} -> {release['target']} (files {release['listed']})")
        if not release["files"]:
            print("  (no files declared: the whole listing is the Hub's)")
        for item in release["files"]:
            size = "size unknown" if item["bytes"] is None else f"{item['bytes']:,} B ({item['size']})"
            print(f"  {item['path']}  {size}")
            total += item["bytes"] or 0
            unknown += item["bytes"] is None
    print(f"total: {total:,} B known; {unknown} file(s) of unknown size")


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(CHUNK):
            digest.update(block)
    return digest.hexdigest()


def release_files(weights_dir: Path, release: Release) -> list[Path]:
    """The files under a release's target (the file itself for a single-file release), huggingface_hub's own
    ``.cache`` bookkeeping left out."""
    target = weights_dir / release.target
    if target.is_file():
        return [target]
    return sorted(p for p in target.rglob("*") if p.is_file() and ".cache" not in p.relative_to(target).parts)


def record_manifest(weights_dir: Path) -> dict:
    """Hash every release's files into ``<weights_dir>/MANIFEST.json`` (written whole or not at all)."""
    files, releases = {}, {}
    for release in RELEASES:
        found = release_files(weights_dir, release)
        if not found:
            raise InputFileError(weights_dir / release.target, f"no files of {release.repo or release.url}",
                                 "fetch it (tracegs-weights) or copy it there, then record again")
        for name, _ in release.files:
            expected = weights_dir / release.target / name if name else weights_dir / release.target
            if not expected.is_file():
                raise InputFileError(expected, f"missing from {release.repo or release.url}",
                                     "fetch it again (tracegs-weights)")
        releases[release.name] = {"source": release.repo or release.url, "target": release.target}
        for path in found:
            files[str(path.relative_to(weights_dir))] = {"bytes": path.stat().st_size, "sha256": sha256(path)}
    manifest = {"releases": releases, "files": files}
    partial = weights_dir / f"{MANIFEST}.tmp"
    partial.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    partial.replace(weights_dir / MANIFEST)
    return manifest


def check_tree(weights_dir: Path, sizes_only: bool = False) -> dict:
    """Verify ``weights_dir`` against its manifest (no network); raise on the first file that differs."""
    manifest_path = weights_dir / MANIFEST
    try:
        manifest = json.loads(manifest_path.read_text())
        files = manifest["files"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputFileError(manifest_path, f"no readable manifest ({type(error).__name__})",
                             "fetch with tracegs-weights, or tracegs-weights --record a tree copied from elsewhere") \
            from error
    absent = [r.name for r in RELEASES if r.name not in manifest.get("releases", {})]
    if absent:
        raise InputFileError(manifest_path, f"records no {', '.join(absent)}", "fetch again (tracegs-weights)")
    for name, expected in sorted(files.items()):
        path = weights_dir / name
        if not path.is_file():
            raise InputFileError(path, "missing (listed in the manifest)", "fetch again (tracegs-weights)")
        size = path.stat().st_size
        if size != expected["bytes"]:
            raise InputFileError(path, f"{size} bytes, the manifest says {expected['bytes']}",
                                 "fetch again (tracegs-weights)")
        if not sizes_only and sha256(path) != expected["sha256"]:
            raise InputFileError(path, "SHA-256 differs from the manifest's", "fetch again (tracegs-weights)")
    return {"files": len(files), "bytes": sum(f["bytes"] for f in files.values()),
            "verified": "sizes" if sizes_only else "sha256"}


def fetch(weights_dir: Path) -> dict:
    """Download every release into its target, then record the manifest."""
    import torch
    from huggingface_hub import snapshot_download

    weights_dir.mkdir(parents=True, exist_ok=True)
    for release in RELEASES:
        print(f"fetching {release.repo or release.url} -> {weights_dir / release.target}", flush=True)
        if release.repo is not None:
            snapshot_download(repo_id=release.repo, local_dir=weights_dir / release.target,
                              allow_patterns=list(release.patterns) if release.patterns else None)
        elif not (weights_dir / release.target).is_file():
            prefix = Path(release.url).stem.rpartition("-")[2]
            partial = weights_dir / f"{release.target}.partial"
            torch.hub.download_url_to_file(release.url, str(partial), hash_prefix=prefix)
            partial.replace(weights_dir / release.target)
    return record_manifest(weights_dir)
