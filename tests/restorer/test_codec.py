import pytest
import torch
import torch.nn.functional as F
from diffusers import AutoencoderKLCogVideoX
from skimage import data

from tracegs.restorer.codec import CogVideoXCodec, EmbeddedCodec
from tracegs.restorer.config import CodecConfig


def _photo(name: str) -> torch.Tensor:
    image = getattr(data, name)()
    x = torch.tensor(image, dtype=torch.float32) / 255.0
    x = x[..., None].expand(*x.shape, 3) if x.dim() == 2 else x[..., :3]
    return F.interpolate(x.permute(2, 0, 1)[None], size=(48, 72), mode="area")[0]


def test_embedded_codec_is_near_lossless_on_textured_images():
    frames = torch.stack([_photo(n) for n in ("astronaut", "coffee", "chelsea", "rocket", "brick")])[None]
    codec = EmbeddedCodec(CodecConfig())
    latents = codec.encode(frames)
    assert latents.shape == (1, 5, 24, 12, 18) and codec.latent_frames(5) == 5 and codec.spatial_factor == 4
    mse = (codec.decode(latents) - frames).square().mean(dim=(0, 2, 3, 4))
    psnr = -10 * torch.log10(mse)
    assert psnr.mean() > 38.0 and psnr.min() > 33.0, psnr
    # channels are roughly balanced (no detail channel vanishes under unit noise)
    std = latents.std(dim=(0, 1, 3, 4))
    assert std.max() / std.min() < 40


def test_embedded_codec_keeps_all_information_at_full_rank():
    codec = EmbeddedCodec(CodecConfig(latent_channels=48))
    frames = torch.rand(2, 3, 3, 8, 12)
    torch.testing.assert_close(codec.decode(codec.encode(frames)), frames, atol=1e-5, rtol=0)


def test_embedded_codec_rejects_bad_sizes():
    codec = EmbeddedCodec(CodecConfig())
    with pytest.raises(ValueError, match="divisible by 4"):
        codec.encode(torch.rand(1, 2, 3, 10, 12))
    with pytest.raises(ValueError, match="codec.latent_channels"):
        EmbeddedCodec(CodecConfig(latent_channels=49))


def test_cogvideox_vae_from_local_directory(tmp_path):
    # Same layout as CogVideoX's VAE (4 levels -> 8x spatial, 4x temporal), tiny widths.
    vae = AutoencoderKLCogVideoX(
        block_out_channels=(8, 8, 8, 8),
        latent_channels=4,
        layers_per_block=1,
        norm_num_groups=4,
        temporal_compression_ratio=4,
        sample_height=32,
        sample_width=32,
    )
    vae.save_pretrained(tmp_path / "vae")
    codec = CogVideoXCodec(CodecConfig(kind="cogvideox", pretrained_path=str(tmp_path / "vae"), tiling=False))
    assert codec.spatial_factor == 8 and codec.latent_frames(49) == 13 and codec.latent_frames(9) == 3
    frames = torch.rand(1, 9, 3, 32, 48)
    latents = codec.encode(frames)
    assert latents.shape == (1, 3, 4, 4, 6)
    decoded = codec.decode(latents)
    assert decoded.shape == frames.shape and decoded.min() >= 0 and decoded.max() <= 1
    with pytest.raises(ValueError, match="8k \\+ 1"):
        codec.encode(torch.rand(1, 5, 3, 32, 48))
    with pytest.raises(FileNotFoundError, match="codec.pretrained_path"):
        CogVideoXCodec(CodecConfig(kind="cogvideox", pretrained_path=str(tmp_path / "absent")))
