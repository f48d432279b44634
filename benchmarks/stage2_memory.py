"""Peak memory of one Stage-2 step per memory mode, at the paper's shapes on a GPU, at the rehearsal's on a CPU.

Usage: ``.venv/bin/python benchmarks/stage2_memory.py [--scale auto|paper|rehearsal] [--rollout 10]``

One Stage-2 training step (supplement A.4: batch 2, N = 10 visited states resampled from M = 50, bf16 base under
``bf16-mixed``) of ``experiment=paper`` (CogVideoX-5B shapes, 49 x 480 x 720 clips: 13 x 60 x 90 latents,
2 x 25 x 37 reference tokens, 226 text tokens) or ``experiment=rehearsal`` (the same code paths at CPU sizes),
twice: unguided as the paper writes the rollout (``stage.guidance_scale`` = 1, the configured value) and under
deployment's guidance (``backbone.sampler.guidance_scale``, which earlier versions also used in Stage 2).
The student-activation figure is the memory of one visited state's student graph, (retain - stepwise) / (N - 1):
``retain`` keeps N graphs alive, ``stepwise`` one. Weights are random (a benchmark of memory, not of quality),
the Stage-1 adapter too.
``auto`` takes ``paper`` when CUDA is available.

- GPU: ``torch.cuda.max_memory_allocated`` over the step, per mode, in one process (reset between modes).
- CPU: each mode in a fresh process, the kernel's resident-set high-water mark over the step (see
  ``benchmarks/stage2.py``: an upper bound on live tensor bytes, allocator slack included).

Also printed: the bytes of every training-rank component at the paper's shapes, counted on the meta device
(no memory, no weights): the frozen bf16 transformer, each float32 adapter, the student's gradients and AdamW
state; and, for comparison, the frozen encoders a training rank no longer builds (the cache holds their outputs).
The last printed line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import lightning as L
from stage2 import _StepProbe, in_fresh_process, random_batch

MODES = ("retain", "stepwise")
MIB = 2**20


def compose_experiment(scale: str):
    """The training config of ``experiment=<scale>``, Stage 2, with no weights to read (random restorer)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from tracegs.cli.app import CONF_DIR
    from tracegs.config.schema import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={scale}", "stage=stage2",
                                                      "backbone.transformer.pretrained_path=null"])
    return (OmegaConf.to_object(cfg.backbone), cfg.trainer.precision, cfg.stage.guidance_scale,
            (cfg.experiment.frame_height, cfg.experiment.frame_width))


def paper_shaped_batch(backbone, batch_size: int, frame_size: tuple[int, int]) -> dict:
    from tracegs.restorer.encoders import reference_grid

    t = backbone.transformer
    frames = (t.sample_frames - 1) // t.temporal_compression_ratio + 1
    rows, cols = reference_grid(backbone.reference_encoder, *frame_size)
    return random_batch(t, frames, 2 * rows * cols, batch_size, seed=0)  # two views of patch-14 tokens


def random_base_transformer(backbone, device: str):
    """The frozen base of the measured step, random from seed 0 and built in bf16 directly (no 20 GB float32
    copy at 5B); the Stage-1 adapter is made on this same base, whose identity its file records."""
    import torch

    from tracegs.restorer.build import create_transformer

    torch.manual_seed(0)
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.bfloat16)
    try:
        return create_transformer(backbone.transformer, device).requires_grad_(False)
    finally:
        torch.set_default_dtype(previous)


def stage2_module(backbone, mode: str, rollout: int, adapter: Path, device: str, guidance: float):
    from tracegs.restorer.schedules import build_schedule
    from tracegs.restorer.speed import apply_switches
    from tracegs.training.config import OptimizerConfig
    from tracegs.training.stage2 import Stage2DistillationModule

    transformer = random_base_transformer(backbone, device)
    apply_switches(transformer, backbone)
    return Stage2DistillationModule(
        transformer, build_schedule(backbone.schedule), adapter, OptimizerConfig(lr=1e-5),
        rollout_steps=rollout, deploy_steps=backbone.schedule.deploy_steps, memory_mode=mode,
        lora=backbone.lora, guidance_scale=guidance)


def _step_peak_mib(scale: str, mode: str, rollout: int, batch_size: int, adapter: str, guidance: float) -> float:
    """Peak memory (MiB) of the second Stage-2 step (the first one allocates AdamW's state)."""
    import torch
    from torch.utils.data import DataLoader

    backbone, precision, _, frame_size = compose_experiment(scale)
    cuda = scale == "paper"
    device = "cuda" if cuda else "cpu"
    module = stage2_module(backbone, mode, rollout, Path(adapter), device, guidance)
    probe = _GpuProbe() if cuda else _StepProbe()
    trainer = L.Trainer(accelerator="gpu" if cuda else "cpu", devices=1, precision=precision, max_steps=2,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[probe])
    trainer.fit(module, train_dataloaders=DataLoader([paper_shaped_batch(backbone, batch_size, frame_size)], batch_size=None))
    if cuda:
        del module, trainer
        torch.cuda.empty_cache()
        return probe.peak_mib[-1]
    return probe.peaks_kib[-1] / 1024


class _GpuProbe(L.Callback):
    def __init__(self):
        super().__init__()
        self.peak_mib: list[float] = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        import torch

        torch.cuda.reset_peak_memory_stats()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        import torch

        self.peak_mib.append(torch.cuda.max_memory_allocated() / MIB)


def _worker(scale, mode, rollout, batch_size, adapter, guidance, queue) -> None:
    import torch

    torch.set_num_threads(1)
    queue.put(_step_peak_mib(scale, mode, rollout, batch_size, adapter, guidance))


def _cpu_peak_mib(scale: str, mode: str, rollout: int, batch_size: int, adapter: Path, guidance: float) -> float:
    """One fresh process per mode; tensors above 64 KiB are their own mappings, so RSS follows live tensors."""
    return in_fresh_process(_worker, (scale, mode, rollout, batch_size, str(adapter), guidance), mode,
                            mmap_threshold=True)


def make_random_adapter(backbone, path: Path, device: str) -> None:
    """A random Stage-1 adapter at the config's rank on the measured step's base (the file records that base's
    identity, which Stage 2 checks); the base is freed before anything is measured."""
    import torch

    from tracegs.restorer.adapters import adapter_parameters, add_adapter, save_adapter
    from tracegs.stages import Product

    model = random_base_transformer(backbone, device)
    add_adapter(model, "aligned", backbone.lora)
    torch.manual_seed(0)
    with torch.no_grad():
        for param in adapter_parameters(model, "aligned"):
            param.normal_(0.0, 0.02)
    save_adapter(model, "aligned", path, stage=Product.stage1)
    del model
    if device == "cuda":
        torch.cuda.empty_cache()


def encoder_bytes() -> dict[str, int]:
    """bf16 bytes of the frozen encoders at their published configurations (meta device): what a training rank
    used to load besides the transformer. VGGT is not on PyPI; its 1.26 B parameters are quoted from its card."""
    import torch
    from diffusers import AutoencoderKLCogVideoX
    from transformers import Dinov2WithRegistersConfig, Dinov2WithRegistersModel, T5Config, T5EncoderModel

    from tracegs.restorer.memory import module_bytes

    def size(model) -> int:
        return module_bytes(model.to(torch.bfloat16))

    with torch.device("meta"):
        t5 = T5EncoderModel(T5Config(vocab_size=32128, d_model=4096, d_kv=64, d_ff=10240, num_layers=24,
                                     num_heads=64, feed_forward_proj="gated-gelu"))
        dino = Dinov2WithRegistersModel(Dinov2WithRegistersConfig(
            hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, image_size=518, patch_size=14))
        vae = AutoencoderKLCogVideoX()
    return {"t5_xxl_encoder": size(t5), "dinov2_with_registers_large": size(dino), "cogvideox_vae": size(vae),
            "vggt_1b": int(1.26e9) * 2}


def main(argv: list[str] | None = None) -> dict:
    import torch

    from tracegs.restorer.memory import training_component_bytes

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", choices=("auto", "paper", "rehearsal"), default="auto")
    parser.add_argument("--rollout", type=int, default=10, help="N visited states per step")
    parser.add_argument("--batch", type=int, default=2)
    args = parser.parse_args(argv)
    scale = args.scale if args.scale != "auto" else ("paper" if torch.cuda.is_available() else "rehearsal")
    if scale == "paper" and not torch.cuda.is_available():
        sys.exit("--scale paper needs a CUDA GPU (use --scale rehearsal on a CPU)")
    if scale == "rehearsal" and not Path("/proc/self/clear_refs").exists():
        sys.exit("the CPU measurement needs Linux /proc/self/clear_refs to reset the peak resident set size")
    backbone, _, unguided, _ = compose_experiment(scale)
    guided = backbone.sampler.guidance_scale
    peaks: dict[float, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        adapter = Path(tmp) / "stage1_adapter.safetensors"
        make_random_adapter(backbone, adapter, "cuda" if scale == "paper" else "cpu")
        for guidance in (unguided, guided):
            peaks[guidance] = {
                mode: (_step_peak_mib(scale, mode, args.rollout, args.batch, str(adapter), guidance)
                       if scale == "paper" else _cpu_peak_mib(scale, mode, args.rollout, args.batch, adapter, guidance))
                for mode in MODES}
    activation = {g: (p["retain"] - p["stepwise"]) / max(args.rollout - 1, 1) for g, p in peaks.items()}
    paper_backbone = compose_experiment("paper")[0]
    components = training_component_bytes(paper_backbone)
    encoders = encoder_bytes()
    for guidance, label in ((unguided, "unguided (the paper)"), (guided, "deployment's guidance (before)")):
        print(f"Stage-2 step at {scale} shapes, batch {args.batch}, N={args.rollout}, guidance {guidance} {label}: "
              "peak " + ", ".join(f"{m} {v:.1f} MiB" for m, v in peaks[guidance].items())
              + f"; student activations per visited state {activation[guidance]:.1f} MiB")
    print("paper-shape bytes per training-rank component (meta device): "
          + ", ".join(f"{k} {v / MIB:.1f} MiB" for k, v in components.items() if k != "adapter_params"))
    print("encoders no longer built on training ranks (bf16): "
          + ", ".join(f"{k} {v / MIB:.1f} MiB" for k, v in encoders.items()))
    summary = {"scale": scale, "device": "cuda" if scale == "paper" else "cpu", "batch": args.batch,
               "rollout": args.rollout, "guidance": unguided, "guidance_before": guided,
               "peak_mib": {m: round(v, 2) for m, v in peaks[unguided].items()},
               "peak_mib_guidance_before": {m: round(v, 2) for m, v in peaks[guided].items()},
               "student_activation_mib_per_state": round(activation[unguided], 2),
               "student_activation_mib_per_state_guidance_before": round(activation[guided], 2),
               "paper_component_bytes": components, "paper_encoder_bytes_not_built": encoders}
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
