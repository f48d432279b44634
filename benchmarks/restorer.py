"""Embedded restorer figures: codec round-trip PSNR, tiny transformer size and CPU timings.

Run: ``.venv/bin/python benchmarks/restorer.py``. The last printed line is a JSON object with keys
``codec_psnr_db`` (PSNR of the pooled MSE over scikit-image photos at 48x72), ``codec_psnr_min_db``, ``params``,
``lora_params``, ``tokens_per_clip``, ``fwd_bwd_s`` (batch of 2 clips), ``fwd_nograd_s``, ``restore_s``
(one clip, M deployment steps).
"""

from __future__ import annotations

import json
import time

import torch
import torch.nn.functional as F
from skimage import data

from tracegs.restorer import adapters
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline

PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "brick", "immunohistochemistry", "retina", "cat")


def photo(name: str, height: int, width: int) -> torch.Tensor:
    image = torch.tensor(getattr(data, name)(), dtype=torch.float32) / 255.0
    image = image[..., None].expand(*image.shape, 3) if image.dim() == 2 else image[..., :3]
    return F.interpolate(image.permute(2, 0, 1)[None], size=(height, width), mode="area")[0]


def best_time(fn, repeats: int = 5) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    torch.manual_seed(0)
    cfg = BackboneConfig()
    backbone = build_backbone(cfg)
    model = backbone.transformer
    frames = torch.stack([photo(n, 48, 72) for n in PHOTOS])[None]
    decoded = backbone.codec.decode(backbone.codec.encode(frames))
    mse = (decoded - frames).square().mean(dim=(0, 2, 3, 4))
    psnr = -10 * torch.log10(mse)
    for name, value in zip(PHOTOS, psnr.tolist()):
        print(f"codec PSNR {name:>22s}: {value:.1f} dB")

    adapters.add_adapter(model, "student", cfg.lora)
    t = cfg.transformer
    clip = torch.rand(2, 9, 3, 48, 72)
    latents = backbone.codec.encode(clip)
    ref_2d, ref_3d = backbone.reference_encoder(torch.rand(2, 2, 3, 48, 72))
    text = backbone.text_encoder.encode(["a synthetic room", "a textured object"])
    timestep = backbone.schedule.sample_train_t(2)
    tokens = latents.shape[1] * (latents.shape[3] // t.patch_size) * (latents.shape[4] // t.patch_size)

    def forward_backward() -> None:
        out = model(latents, latents, timestep, text, ref_2d, ref_3d, return_retrieval=True)
        (out.velocity.square().mean() + out.retrieval.square().mean()).backward()

    def forward_nograd() -> None:
        with torch.no_grad():
            model(latents, latents, timestep, text, ref_2d, ref_3d)

    pipeline = RestorationPipeline(backbone, "student")
    figures = {
        "codec_psnr_db": round(float(-10 * torch.log10(mse.mean())), 2),
        "codec_psnr_min_db": round(float(psnr.min()), 2),
        "params": sum(p.numel() for n, p in model.named_parameters() if ".lora_" not in n),
        "lora_params": sum(p.numel() for p in adapters.adapter_parameters(model, "student")),
        "tokens_per_clip": tokens,
        "fwd_bwd_s": round(best_time(forward_backward), 4),
        "fwd_nograd_s": round(best_time(forward_nograd), 4),
        "restore_s": round(
            best_time(lambda: pipeline.restore(clip[:1], torch.rand(1, 2, 3, 48, 72), ["a room"], seed=0), 2),
            3,
        ),
        "threads": torch.get_num_threads(),
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
