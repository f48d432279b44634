import dataclasses

import pytest
import torch
from tokenizers import Tokenizer, models, pre_tokenizers
from transformers import (
    Dinov2Config,
    Dinov2Model,
    Dinov2WithRegistersConfig,
    Dinov2WithRegistersModel,
    PreTrainedTokenizerFast,
    T5Config,
    T5EncoderModel,
)

from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import (
    QUALITY_SUFFIX,
    BackboneConfig,
    ReferenceEncoderConfig,
    ReferencePixels,
    TextEncoderConfig,
)
from tracegs.restorer.encoders import (
    Dinov2Encoder,
    EmbeddedReferenceEncoder,
    EmbeddedTextEncoder,
    T5TextEncoder,
    build_reference_encoder,
    reference_grid,
    reference_images,
    wrapped_bytes,
)
from tracegs.restorer.loading import MissingPackageError


def test_embedded_reference_tokens():
    encoder = EmbeddedReferenceEncoder(ReferenceEncoderConfig())
    refs = torch.rand(2, 2, 3, 48, 72)
    ref_2d, ref_3d = encoder(refs)
    assert ref_2d.shape == (2, 2 * 6 * 9, 192) and ref_3d.shape == (2, 108, 200)
    assert torch.equal(encoder(refs)[0], ref_2d)
    # 2D tokens are per view; 3D tokens depend on the pair jointly
    changed = refs.clone()
    changed[:, 1] = torch.rand(2, 3, 48, 72)
    new_2d, new_3d = encoder(changed)
    assert torch.equal(new_2d[:, :54], ref_2d[:, :54]) and not torch.equal(new_2d[:, 54:], ref_2d[:, 54:])
    assert not torch.equal(new_3d[:, :54], ref_3d[:, :54])
    with pytest.raises(ValueError, match=r"\(B, 2, 3, H, W\)"):
        encoder(torch.rand(2, 3, 3, 48, 72))


def test_embedded_text_encoder_prompt_null_and_determinism():
    cfg = TextEncoderConfig()
    encoder = EmbeddedTextEncoder(cfg)
    assert encoder.prompt("a wooden table.") == "a wooden table" + QUALITY_SUFFIX
    a = encoder.encode(["a wooden table", "a red car"])
    assert a.shape == (2, cfg.max_length, cfg.dim)
    assert torch.equal(a, EmbeddedTextEncoder(cfg).encode(["a wooden table", "a red car"]))
    assert not torch.allclose(a[0], a[1])
    assert a[0].abs().sum(dim=-1).min() > 0  # the suffix fills the remaining token slots
    null = encoder.null(3)
    assert null.shape == (3, cfg.max_length, cfg.dim) and not null.any()
    assert not torch.equal(encoder.encode([""])[0], null[0])  # dropout uses zeros, not the empty caption


def test_dinov2_with_registers_from_local_directory_keeps_the_patch_tokens(tmp_path):
    """GSFixer's inference: the preprocessed view, unnormalised, and ``last_hidden_state[:, 5:]``."""
    config = Dinov2WithRegistersConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=2,
                                       intermediate_size=32, patch_size=14, image_size=56, num_register_tokens=4)
    torch.manual_seed(0)
    Dinov2WithRegistersModel(config).save_pretrained(tmp_path / "dino")
    cfg = ReferenceEncoderConfig(dino_path=str(tmp_path / "dino"), image_size=56)
    encoder = Dinov2Encoder(cfg)
    views = torch.rand(3, 3, 48, 72)
    tokens = encoder(views)
    assert reference_grid(cfg, 48, 72) == (3, 4)  # 48 x 72 -> 42 x 56 pixels (aspect kept, multiple of 14)
    assert tokens.shape == (3, 3 * 4, 16) and encoder.dim == 16
    with torch.no_grad():
        full = encoder.model(pixel_values=reference_images(views, cfg)).last_hidden_state
    torch.testing.assert_close(tokens, full[:, 5:])
    assert not any(p.requires_grad for p in encoder.model.parameters())


def test_dinov2_without_registers_is_refused_in_one_line(tmp_path):
    config = Dinov2Config(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, intermediate_size=32,
                          patch_size=14, image_size=28)
    Dinov2Model(config).save_pretrained(tmp_path / "dino")
    with pytest.raises(ValueError, match="has 0 register tokens; GSFixer's DINOv2 has 4"):
        Dinov2Encoder(ReferenceEncoderConfig(dino_path=str(tmp_path / "dino"), image_size=28))


def test_uint8_wrap_is_gsfixers_cast_of_its_signed_frames():
    """gsfixer/cogvideo/inference.py l. 106-119: ``control = (frames - 0.5) * 2`` (torch), then
    ``(x * 255).astype(np.uint8)`` (numpy) and the encoders read the 8-bit image: dark pixels wrap."""
    import numpy as np

    frames = torch.cat([torch.rand(1, 3, 28, 42), torch.tensor([0.0, 0.25, 0.5]).view(1, 3, 1, 1).expand(1, 3, 28, 42)])
    released = torch.from_numpy((((frames - 0.5) * 2).numpy() * 255).astype(np.uint8)).float() / 255
    torch.testing.assert_close(wrapped_bytes(frames), released, atol=0, rtol=0)
    assert round(wrapped_bytes(torch.zeros(1)).item() * 255) == 1  # black -> -255 -> byte 1
    wrapped = ReferenceEncoderConfig(image_size=28, pixels=ReferencePixels.uint8_wrap)
    torch.testing.assert_close(reference_images(frames, wrapped),
                               reference_images(released, ReferenceEncoderConfig(image_size=28)))


@pytest.mark.parametrize(("size", "expected"), [((480, 720), (350, 518)), ((720, 480), (518, 518)),
                                                ((540, 960), (294, 518))])
def test_reference_images_follow_vggts_crop_preprocessing(size, expected):
    """VGGT's load_and_preprocess_images, mode "crop": width 518, height round(H * 518 / W / 14) * 14, then a
    centre crop to 518 rows; values stay in [0, 1]."""
    cfg = ReferenceEncoderConfig()
    views = torch.rand(2, 3, *size)
    out = reference_images(views, cfg)
    assert out.shape == (2, 3, *expected) and out.min() >= 0 and out.max() <= 1
    assert reference_grid(cfg, *size) == (expected[0] // 14, expected[1] // 14)
    if size == (720, 480):  # 777 / 14 = 55.5 rounds (half to even, as Python's round) to 56: 784 rows, middle 518
        full = torch.nn.functional.interpolate(views, size=(784, 518), mode="bicubic", antialias=True).clamp(0, 1)
        torch.testing.assert_close(out, full[..., 133:651, :])


def test_t5_from_local_directory(tmp_path):
    words = ["<pad>", "</s>", "<unk>", "a", "red", "car", "the", "video", "is", "of", "high", "quality"]
    tokenizer = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()
    PreTrainedTokenizerFast(
        tokenizer_object=tokenizer, pad_token="<pad>", eos_token="</s>", unk_token="<unk>"
    ).save_pretrained(tmp_path / "t5")
    config = T5Config(vocab_size=len(words), d_model=16, d_kv=4, num_heads=2, num_layers=1, d_ff=32)
    torch.manual_seed(0)
    T5EncoderModel(config).save_pretrained(tmp_path / "t5")
    cfg = TextEncoderConfig(kind="t5", dim=16, max_length=12, pretrained_path=str(tmp_path / "t5"))
    encoder = T5TextEncoder(cfg)
    emb = encoder.encode(["a red car", "the car"])
    assert emb.shape == (2, 12, 16) and not torch.allclose(emb[0], emb[1])
    assert not encoder.null(2).any()
    with pytest.raises(ValueError, match="d_model=16"):
        T5TextEncoder(dataclasses.replace(cfg, dim=32))


def test_vggt_missing_gives_install_hint():
    cfg = ReferenceEncoderConfig(kind="dinov2_vggt", dino_path="/nonexistent", vggt_path="/nonexistent")
    try:
        import vggt  # noqa: F401
    except ImportError:
        hint = "'vggt' package.*pip install git\\+https://github.com/facebookresearch/vggt"
        with pytest.raises(MissingPackageError, match=hint):
            build_reference_encoder(cfg)
    else:
        with pytest.raises(FileNotFoundError, match="reference_encoder.vggt_path"):
            build_reference_encoder(cfg)


def test_backbone_rejects_inconsistent_dimensions():
    cfg = BackboneConfig()
    cfg.codec.latent_channels = 16
    with pytest.raises(ValueError, match="transformer.latent_channels"):
        build_backbone(cfg)
    cfg = BackboneConfig()
    cfg.reference_encoder.patch_size = 4
    with pytest.raises(ValueError, match="transformer.ref_2d_dim"):
        build_backbone(cfg)
