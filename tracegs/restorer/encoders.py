"""Frozen conditioning encoders (supplement A.2): reference tokens and text tokens.

Reference encoders return ``(ref_2d (B, R, D2), ref_3d (B, R, D3))`` for the two reference views, tokens of
both views concatenated along R (Eq. supp-ref-tokens); the transformer projects and adds them (Proj_2D +
Proj_3D, Eq. supp-ref-fusion). Text encoders embed ``caption + quality suffix`` and supply the all-zero
embedding used for caption dropout and the unconditional branch of classifier-free guidance.
"""

from __future__ import annotations

import contextlib
import functools
import json
import re
import zlib
from collections.abc import Iterator
from pathlib import Path

import torch
import torch.nn.functional as F

from tracegs.restorer.config import ReferenceEncoderConfig, ReferencePixels, TextEncoderConfig
from tracegs.restorer.loading import MissingPackageError, require_local_dir, torch_dtype

VGGT_INSTALL_HINT = (
    "reference_encoder.kind=dinov2_vggt needs the 'vggt' package, which is not on PyPI: install it with "
    "`pip install git+https://github.com/facebookresearch/vggt` (or set reference_encoder.kind=embedded)"
)


@contextlib.contextmanager
def on_device(model: torch.nn.Module, device: torch.device | str, offload: bool) -> Iterator[None]:
    """Run a frozen encoder on ``device``. With ``offload`` (``backbone.offload_encoders``) the encoder lives on
    the CPU and visits ``device`` only for this call, then is released there (moved back, cache emptied), so
    the transformer denoises without it beside it. On a CPU ``device`` nothing moves."""
    if encoder_placement(device, offload)[1] is None:
        yield
        return
    model.to(device)
    try:
        yield
    finally:
        model.to("cpu")
        if torch.cuda.is_available():
            torch.cuda.empty_cache()


def encoder_placement(device: torch.device | str, offload: bool) -> tuple[str, str | None]:
    """(home, visits) of a frozen encoder run on ``device``: where its weights live between calls, and the
    device they move to only while encoding (None: they never move)."""
    if offload and torch.device(device).type != "cpu":
        return "cpu", str(device)
    return str(device), None


def _home(device: torch.device | str, offload: bool) -> str:
    return encoder_placement(device, offload)[0]


def _check_reference_images(ref_images: torch.Tensor) -> None:
    if ref_images.dim() != 5 or ref_images.shape[1] != 2 or ref_images.shape[2] != 3:
        raise ValueError(f"reference images must be (B, 2, 3, H, W) in [0, 1], got {tuple(ref_images.shape)}")


class EmbeddedReferenceEncoder:
    """Weight-free reference tokens for the CPU default, one token per ``p x p`` pixel patch of each view.

    - 2D tokens (stand-in for DINOv2, per view): the patch's centred pixels, so the restorer can copy
      observed appearance.
    - 3D tokens (stand-in for VGGT, joint over the pair): the patch minus the co-located patch of the other
      reference view (a crude parallax / disocclusion cue) plus a sin-cos code of the patch position.
    """

    position_features = 8

    def __init__(self, cfg: ReferenceEncoderConfig):
        self.cfg = cfg
        self.dim_2d = 3 * cfg.patch_size**2
        self.dim_3d = self.dim_2d + self.position_features

    def to(self, device: torch.device | str) -> EmbeddedReferenceEncoder:
        return self

    @torch.no_grad()
    def __call__(self, ref_images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_reference_images(ref_images)
        b, v, _, h, w = ref_images.shape
        p = self.cfg.patch_size
        if h % p or w % p:
            raise ValueError(
                f"reference image size {h}x{w} must be divisible by reference_encoder.patch_size={p}"
            )
        x = ref_images.float() * 2.0 - 1.0
        patches = (
            x.reshape(b, v, 3, h // p, p, w // p, p).permute(0, 1, 3, 5, 2, 4, 6).reshape(b, v, -1, 3 * p * p)
        )
        other = patches.flip(1)  # view 1 <-> view 2
        ys, xs = torch.meshgrid(
            torch.linspace(-1.0, 1.0, h // p), torch.linspace(-1.0, 1.0, w // p), indexing="ij"
        )
        angles = torch.stack([ys, xs], dim=-1).reshape(-1, 2, 1) * torch.tensor([1.0, 2.0]) * torch.pi / 2
        position = torch.cat([angles.sin(), angles.cos()], dim=-1).reshape(1, 1, -1, self.position_features)
        ref_2d = patches.reshape(b, -1, self.dim_2d)
        ref_3d = torch.cat([patches - other, position.to(x).expand(b, v, -1, -1)], dim=-1).reshape(
            b, -1, self.dim_3d
        )
        return ref_2d, ref_3d


REFERENCE_PATCH = 14  # DINOv2's and VGGT's patch size
# GSFixer drops the first five DINOv2 tokens (CLS + four registers): the with-registers ViT-L/14.
DINO_PREFIX_TOKENS = 5


def reference_grid(cfg: ReferenceEncoderConfig, height: int, width: int) -> tuple[int, int]:
    """Patch rows and columns of a ``height x width`` view after ``reference_images`` (VGGT's "crop" rule)."""
    size = cfg.image_size
    rows = round(height * (size / width) / REFERENCE_PATCH)
    return min(rows, size // REFERENCE_PATCH), size // REFERENCE_PATCH


def wrapped_bytes(images: torch.Tensor) -> torch.Tensor:
    """[0, 1] frames as GSFixer's release hands them to the reference encoders (gsfixer/cogvideo/inference.py
    l. 106-119): ``(frames - 0.5) * 2``, then ``(x * 255).astype(np.uint8)``, whose cast truncates toward zero and
    wraps negatives modulo 256 (-0.5 -> 129), read back as bytes / 255."""
    signed = (images.float() - 0.5) * 2
    return (signed * 255).trunc().to(torch.int64).remainder(256).float() / 255


def reference_images(images: torch.Tensor, cfg: ReferenceEncoderConfig) -> torch.Tensor:
    """(N, 3, H, W) in [0, 1] -> what GSFixer feeds both DINOv2 and VGGT: with ``pixels=uint8_wrap`` its wrapped
    bytes (``wrapped_bytes``), then VGGT's ``load_and_preprocess_images``
    ("crop"): width ``image_size`` (518), height scaled with the aspect ratio to a multiple of 14, bicubic,
    centre-cropped to ``image_size`` if taller; values stay in [0, 1] (VGGT normalises inside its aggregator,
    and GSFixer gives DINOv2 the same unnormalised tensor). Written for tensors because our frames are tensors;
    torch's antialiased bicubic is its PIL-compatible filter (no 8-bit rounding in between)."""
    if cfg.pixels == ReferencePixels.uint8_wrap:
        images = wrapped_bytes(images)
    size = cfg.image_size
    height = round(images.shape[-2] * (size / images.shape[-1]) / REFERENCE_PATCH) * REFERENCE_PATCH
    x = F.interpolate(images.float(), size=(height, size), mode="bicubic", align_corners=False, antialias=True)
    x = x.clamp(0.0, 1.0)
    if height > size:
        top = (height - size) // 2
        x = x[..., top:top + size, :]
    return x


class Dinov2Encoder:
    """DINOv2 with registers through transformers from a local directory; per-view patch tokens.

    As GSFixer's inference: ``last_hidden_state[:, 5:]`` (CLS and the four registers dropped) of the
    preprocessed views, so the tokens line up one-to-one with VGGT's patch tokens and can be added.
    """

    def __init__(self, cfg: ReferenceEncoderConfig, device: torch.device | str = "cpu", offload: bool = False):
        from transformers import AutoModel

        path = require_local_dir(cfg.dino_path, "reference_encoder.dino_path")
        dtype = torch_dtype(cfg.dtype, "reference_encoder.dtype")
        self.model = AutoModel.from_pretrained(path, torch_dtype=dtype).to(_home(device, offload))
        registers = getattr(self.model.config, "num_register_tokens", 0)
        if 1 + registers != DINO_PREFIX_TOKENS:
            raise ValueError(
                f"reference_encoder.dino_path={str(path)!r} has {registers} register tokens; GSFixer's DINOv2 has "
                f"{DINO_PREFIX_TOKENS - 1} (dinov2-with-registers-large)"
            )
        self.model.eval().requires_grad_(False)
        self.cfg, self.device, self.offload = cfg, device, offload
        self.dim = int(self.model.config.hidden_size)

    def to(self, device: torch.device | str) -> Dinov2Encoder:
        self.device = device
        self.model.to(_home(device, self.offload))
        return self

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """images (N, 3, H, W) in [0, 1] -> (N, tokens, D2)."""
        with on_device(self.model, self.device, self.offload):
            pixels = reference_images(images, self.cfg).to(self.device, self.model.dtype)
            out = self.model(pixel_values=pixels).last_hidden_state
        return out[:, DINO_PREFIX_TOKENS:].float()


class VggtEncoder:
    """VGGT aggregator tokens of the reference pair, processed jointly (needs the ``vggt`` package).

    As GSFixer's inference: ``output_list[-1]`` (frame and global attention of the last layer, concatenated)
    from ``patch_start_idx`` on (the camera token and registers dropped).
    """

    def __init__(self, cfg: ReferenceEncoderConfig, device: torch.device | str = "cpu", offload: bool = False):
        try:
            from vggt.models.vggt import VGGT
        except ImportError as err:
            raise MissingPackageError(VGGT_INSTALL_HINT) from err
        path = require_local_dir(cfg.vggt_path, "reference_encoder.vggt_path")
        # VGGT's from_pretrained (huggingface_hub's mixin) loads float32; the cast follows.
        dtype = torch_dtype(cfg.dtype, "reference_encoder.dtype")
        self.model = VGGT.from_pretrained(str(path)).to(_home(device, offload), dtype)
        self.model.eval().requires_grad_(False)
        self.cfg, self.device, self.offload = cfg, device, offload
        # The aggregator concatenates frame- and global-attention tokens: 2 x embed_dim features. VGGT's hub
        # config.json records embed_dim; without one the model is VGGT's default (1024, VGGT-1B).
        config = path / "config.json"
        embed_dim = json.loads(config.read_text()).get("embed_dim", 1024) if config.is_file() else 1024
        self.dim = 2 * int(embed_dim)

    def to(self, device: torch.device | str) -> VggtEncoder:
        self.device = device
        self.model.to(_home(device, self.offload))
        return self

    @torch.no_grad()
    def __call__(self, ref_images: torch.Tensor) -> torch.Tensor:
        """ref_images (B, 2, 3, H, W) in [0, 1] -> (B, 2, tokens, D3) from the last aggregator layer."""
        b, v = ref_images.shape[:2]
        x = reference_images(ref_images.flatten(0, 1), self.cfg)
        with on_device(self.model, self.device, self.offload):
            pixels = x.view(b, v, *x.shape[1:]).to(self.device, next(self.model.parameters()).dtype)
            tokens, patch_start = self.model.aggregator(pixels)
        return tokens[-1][:, :, patch_start:].float()


class PretrainedReferenceEncoder:
    """DINOv2 per view + VGGT on the pair, on the same patch grid so the token sets can be added."""

    def __init__(self, cfg: ReferenceEncoderConfig, device: torch.device | str = "cpu", offload: bool = False):
        self.vggt = VggtEncoder(cfg, device, offload)  # first: fail fast with the install hint
        self.dino = Dinov2Encoder(cfg, device, offload)
        # Both checked against transformer.ref_2d_dim / ref_3d_dim when the backbone is built.
        self.dim_2d = self.dino.dim
        self.dim_3d = self.vggt.dim

    def to(self, device: torch.device | str) -> PretrainedReferenceEncoder:
        self.vggt.to(device)
        self.dino.to(device)
        return self

    @torch.no_grad()
    def __call__(self, ref_images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _check_reference_images(ref_images)
        b, v = ref_images.shape[:2]
        ref_2d = self.dino(ref_images.flatten(0, 1)).view(b, v, -1, self.dino.dim)
        ref_3d = self.vggt(ref_images)
        if ref_2d.shape[2] != ref_3d.shape[2]:
            raise ValueError(f"DINOv2 gives {ref_2d.shape[2]} tokens per view but VGGT {ref_3d.shape[2]}")
        return ref_2d.flatten(1, 2), ref_3d.flatten(1, 2)


def build_reference_encoder(cfg: ReferenceEncoderConfig, device: torch.device | str = "cpu", offload: bool = False):
    """``offload``: weights live on the CPU and visit ``device`` only while encoding (``on_device``)."""
    if cfg.kind == "embedded":
        return EmbeddedReferenceEncoder(cfg)
    if cfg.kind == "dinov2_vggt":
        return PretrainedReferenceEncoder(cfg, device, offload)
    raise ValueError(f"reference_encoder.kind must be 'embedded' or 'dinov2_vggt', got {cfg.kind!r}")


class TextEncoder:
    """Shared prompt construction and null embedding; subclasses map prompts to (B, L, D) tokens."""

    def __init__(self, cfg: TextEncoderConfig):
        self.cfg = cfg

    def prompt(self, caption: str) -> str:
        """Supplement A.2: the caption followed by the fixed quality suffix."""
        return caption.strip().rstrip(".") + self.cfg.quality_suffix

    def null(self, batch: int, device: torch.device | str = "cpu") -> torch.Tensor:
        """All-zero embedding (caption dropout / unconditional CFG branch), not the encoding of ''."""
        return torch.zeros(batch, self.cfg.max_length, self.cfg.dim, device=device)

    def to(self, device: torch.device | str) -> TextEncoder:
        return self

    def encode(self, captions: list[str]) -> torch.Tensor:
        """Captions -> (B, L, D): each caption's prompt (``prompt``) encoded."""
        return self.encode_prompts([self.prompt(c) for c in captions])

    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        """Prompts as they are (no quality suffix) -> (B, L, D)."""
        raise NotImplementedError

    @functools.cached_property
    def negative_embedding(self) -> torch.Tensor | None:
        """(1, L, D): the encoding of ``cfg.negative_prompt``, guided sampling's unconditional branch, encoded once
        per encoder (every restored clip reuses it); None = no prompt (the all-zero embedding)."""
        prompt = self.cfg.negative_prompt
        return None if prompt is None else self.encode_prompts([prompt])


class EmbeddedTextEncoder(TextEncoder):
    """Deterministic hashed-word embeddings: each lower-cased word gets a fixed Gaussian vector seeded by
    CRC32(word) and ``cfg.seed`` (no vocabulary, no weights), truncated / zero-padded to ``max_length``."""

    @torch.no_grad()
    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        out = torch.zeros(len(prompts), self.cfg.max_length, self.cfg.dim)
        for row, prompt in enumerate(prompts):
            words = re.findall(r"[a-z0-9]+", prompt.lower())[: self.cfg.max_length]
            for col, word in enumerate(words):
                generator = torch.Generator().manual_seed(zlib.crc32(word.encode()) + (self.cfg.seed << 32))
                out[row, col] = torch.randn(self.cfg.dim, generator=generator)
        return out


def tokenizer_dir(cfg: TextEncoderConfig, encoder_dir: Path) -> Path:
    """``text_encoder.tokenizer_path``, else CogVideoX's layout: ``tokenizer/`` beside ``text_encoder/``, or the
    encoder's own folder when it holds the tokenizer files (a plain T5 checkpoint)."""
    if cfg.tokenizer_path is not None:
        return require_local_dir(cfg.tokenizer_path, "text_encoder.tokenizer_path")
    sibling = encoder_dir.parent / "tokenizer"
    return sibling if sibling.is_dir() else encoder_dir


class T5TextEncoder(TextEncoder):
    """T5 encoder + tokenizer from a local directory, padded to ``max_length`` like CogVideoX's pipelines."""

    def __init__(self, cfg: TextEncoderConfig, device: torch.device | str = "cpu", offload: bool = False):
        from transformers import AutoTokenizer, T5EncoderModel

        super().__init__(cfg)
        path = require_local_dir(cfg.pretrained_path, "text_encoder.pretrained_path")
        self.tokenizer = AutoTokenizer.from_pretrained(tokenizer_dir(cfg, path))
        dtype = torch_dtype(cfg.dtype, "text_encoder.dtype")
        self.model = T5EncoderModel.from_pretrained(path, torch_dtype=dtype).to(_home(device, offload))
        self.model.eval().requires_grad_(False)
        self.device, self.offload = device, offload
        if self.model.config.d_model != cfg.dim:
            raise ValueError(
                f"text_encoder.dim={cfg.dim} but the T5 at {path} has d_model={self.model.config.d_model}"
            )

    def to(self, device: torch.device | str) -> T5TextEncoder:
        self.device = device
        self.model.to(_home(device, self.offload))
        return self

    @torch.no_grad()
    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        ids = self.tokenizer(
            prompts,
            padding="max_length",
            max_length=self.cfg.max_length,
            truncation=True,
            add_special_tokens=True,
            return_tensors="pt",
        ).input_ids.to(self.device)
        with on_device(self.model, self.device, self.offload):
            return self.model(ids).last_hidden_state.float()


def build_text_encoder(cfg: TextEncoderConfig, device: torch.device | str = "cpu", offload: bool = False
                       ) -> TextEncoder:
    """``offload``: weights live on the CPU and visit ``device`` only while encoding (``on_device``)."""
    if cfg.kind == "embedded":
        return EmbeddedTextEncoder(cfg)
    if cfg.kind == "t5":
        return T5TextEncoder(cfg, device, offload)
    raise ValueError(f"text_encoder.kind must be 'embedded' or 't5', got {cfg.kind!r}")
