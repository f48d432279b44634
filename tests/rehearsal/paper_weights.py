"""The README's ``weights/`` tree written with each library's ``save_pretrained``: tiny, random-initialised.

Every component has the class and folder layout of the paper-scale download (GSFixer's transformer in its
released diffusers layout, CogVideoX-5b-I2V's ``vae/``, ``text_encoder/`` and ``tokenizer/``, DINOv2), only its
widths come from the rehearsal's backbone config, so the production loaders read them unchanged. VGGT is
not installable from the package index; ``VggtDouble`` stands in for it with its aggregator's interface.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import torch
from support.gsfixer_layout import write_gsfixer_folder
from support.vgg16_layout import write_vgg16_weights

from tracegs.restorer.config import BackboneConfig

VAE_BLOCKS = 4  # the CogVideoX VAE's four resolution levels: spatial factor 8, as at paper scale
VGGT_REGISTER_TOKENS = 4  # VGGT's aggregator puts a camera token and four registers before the patches


def write_transformer(cfg: BackboneConfig, weights: Path) -> None:
    """GSFixer's released restorer at the rehearsal's widths: the frozen base, variant A and the pseudo-target
    generator alike. Written from GSFixer's key list (tests/support/gsfixer_layout.py), not from our model, so a drift
    of our module names from the released layout fails the rehearsal's loads."""
    write_gsfixer_folder(weights / "gsfixer" / "transformer", cfg.transformer)


def write_vae(cfg: BackboneConfig, weights: Path) -> None:
    from diffusers import AutoencoderKLCogVideoX

    vae = AutoencoderKLCogVideoX(
        down_block_types=("CogVideoXDownBlock3D",) * VAE_BLOCKS,
        up_block_types=("CogVideoXUpBlock3D",) * VAE_BLOCKS,
        block_out_channels=(8,) * VAE_BLOCKS,
        latent_channels=cfg.codec.latent_channels,
        layers_per_block=1,
        norm_num_groups=4,
        temporal_compression_ratio=cfg.transformer.temporal_compression_ratio,
    )
    vae.save_pretrained(weights / "CogVideoX-5b-I2V" / "vae")


def write_t5(cfg: BackboneConfig, weights: Path) -> None:
    """T5 encoder in ``text_encoder/`` and a sentencepiece T5 tokenizer in ``tokenizer/`` (CogVideoX layout)."""
    import sentencepiece
    from transformers import T5Config, T5EncoderModel, T5Tokenizer

    root = weights / "CogVideoX-5b-I2V"
    corpus = [cfg.text_encoder.quality_suffix, "a photo of a scene", "a garden with a table and a bicycle"] * 10
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(corpus), model_writer=model, vocab_size=64, model_type="unigram",
        pad_id=0, eos_id=1, unk_id=2, bos_id=-1, hard_vocab_limit=False, minloglevel=2,
    )
    (root / "tokenizer").mkdir(parents=True, exist_ok=True)
    spiece = root / "tokenizer" / "spiece.model"
    spiece.write_bytes(model.getvalue())
    pieces = sentencepiece.SentencePieceProcessor(model_file=str(spiece))
    vocab = [(pieces.id_to_piece(i), pieces.get_score(i)) for i in range(pieces.get_piece_size())]
    tokenizer = T5Tokenizer(vocab=vocab, extra_ids=0, unk_id=pieces.unk_id())
    tokenizer.save_pretrained(root / "tokenizer")
    dim = cfg.text_encoder.dim
    config = T5Config(vocab_size=len(tokenizer), d_model=dim, d_kv=dim // 2, d_ff=2 * dim, num_layers=1,
                      num_heads=2)
    T5EncoderModel(config).save_pretrained(root / "text_encoder")


def write_dinov2(cfg: BackboneConfig, weights: Path) -> None:
    from transformers import Dinov2WithRegistersConfig, Dinov2WithRegistersModel

    config = Dinov2WithRegistersConfig(hidden_size=cfg.transformer.ref_2d_dim, num_hidden_layers=1,
                                       num_attention_heads=2, intermediate_size=2 * cfg.transformer.ref_2d_dim,
                                       patch_size=14, image_size=cfg.reference_encoder.image_size,
                                       num_register_tokens=4)
    Dinov2WithRegistersModel(config).save_pretrained(weights / "dinov2-with-registers-large")


def write_vggt_config(cfg: BackboneConfig, weights: Path) -> None:
    """What the double reads from ``VGGT-1B/`` (the real folder holds the VGGT checkpoint)."""
    folder = weights / "VGGT-1B"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.json").write_text(json.dumps({"embed_dim": cfg.transformer.ref_3d_dim // 2, "patch_size": 14}))


def write_weights(cfg: BackboneConfig, weights: Path) -> Path:
    write_transformer(cfg, weights)
    write_vae(cfg, weights)
    write_t5(cfg, weights)
    write_dinov2(cfg, weights)
    write_vggt_config(cfg, weights)
    write_vgg16_weights(weights / "vgg16-397923af.pth")  # LPIPS, which the paper's tables require
    return weights


class VggtAggregatorDouble(torch.nn.Module):
    """VGGT's aggregator interface: ``(B, S, 3, H, W)`` -> (list of per-layer tokens ``(B, S, 5 + P, 2C)``,
    patch_start_idx = 5); tokens are a fixed random projection of each 14 x 14 patch, frame and pair mixed."""

    def __init__(self, embed_dim: int, patch_size: int):
        super().__init__()
        generator = torch.Generator().manual_seed(0)
        self.patch_size = patch_size
        self.frame = torch.nn.Parameter(torch.randn(3 * patch_size**2, embed_dim, generator=generator) * 0.05)
        self.special = torch.nn.Parameter(torch.randn(1 + VGGT_REGISTER_TOKENS, 2 * embed_dim, generator=generator))

    def forward(self, images: torch.Tensor) -> tuple[list[torch.Tensor], int]:
        b, s, c, h, w = images.shape
        p = self.patch_size
        patches = images.reshape(b, s, c, h // p, p, w // p, p).permute(0, 1, 3, 5, 2, 4, 6).flatten(4).flatten(2, 3)
        frame = patches @ self.frame
        pair = frame.mean(dim=1, keepdim=True).expand_as(frame)  # global attention mixes the views
        tokens = torch.cat([frame, pair], dim=-1)
        special = self.special.expand(b, s, -1, -1)
        return [torch.cat([special, tokens], dim=2)], 1 + VGGT_REGISTER_TOKENS


class VggtDouble(torch.nn.Module):
    """Stands in for ``vggt.models.vggt.VGGT`` (``from_pretrained`` + ``aggregator``) in tests only."""

    def __init__(self, embed_dim: int, patch_size: int):
        super().__init__()
        self.aggregator = VggtAggregatorDouble(embed_dim, patch_size)

    @classmethod
    def from_pretrained(cls, path: str) -> VggtDouble:
        config = json.loads((Path(path) / "config.json").read_text())
        return cls(config["embed_dim"], config["patch_size"])


def install_vggt_double(monkeypatch) -> None:
    """Make ``from vggt.models.vggt import VGGT`` resolve to the double for this test."""
    import sys
    import types

    package, models, module = (types.ModuleType(n) for n in ("vggt", "vggt.models", "vggt.models.vggt"))
    module.VGGT = VggtDouble
    package.models, models.vggt = models, module
    for name, mod in (("vggt", package), ("vggt.models", models), ("vggt.models.vggt", module)):
        monkeypatch.setitem(sys.modules, name, mod)


def write_vggt_double_package(folder: Path) -> Path:
    """A ``vggt`` package under ``folder`` whose ``vggt.models.vggt.VGGT`` is the double, for console scripts
    run as subprocesses (put ``folder`` on their PYTHONPATH); returns ``folder``."""
    module = folder / "vggt" / "models"
    module.mkdir(parents=True, exist_ok=True)
    (folder / "vggt" / "__init__.py").write_text("")
    (module / "__init__.py").write_text("")
    (module / "vggt.py").write_text(
        # paper_weights imports the layout tables of tests/ (gsfixer_layout, vgg16_layout): both folders on the path
        f"import sys\nsys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(__file__).parents[1])!r}]\n"
        "from paper_weights import VggtDouble as VGGT  # noqa: E402,F401\n")
    return folder
