"""The first minutes on a GPU: one unattended check that times and loads the paper scale (10-15 min on one H200).

Usage: ``launch/gpu_check.sh [--out DIR] [--scale auto|paper|rehearsal] [--fit-iterations 1000]
[--speed-rollout 2] [--sections restorer,vae,...]``

Sections, each measured on its own (a section that fails records its one-line error and the others still run: the
minutes on a GPU are few, one failure must not cost the rest):
- ``device``: GPU name, memory, torch and CUDA versions;
- ``restorer``: the paper's restorer at its real shapes with random weights (nothing is read: a benchmark of time
  and memory, not of quality), built in bf16 with fp32 LoRA adapters of the paper's rank on the supplement's
  targets: seconds and peak memory of one guided deployment step (``backbone.sampler.guidance_scale``: two
  forwards) and one unguided rollout step (one forward, no gradient);
- ``vae``: the VAE's encode and decode of one clip (49 x 480 x 720);
- ``weights``: every released model the paper scale reads under ``paths.weights_dir`` (GSFixer, CogVideoX's VAE, T5
  and tokenizer, DINOv2, VGGT, BLIP-2, VGG16 for LPIPS), present or missing, and the tree checked against the
  manifest ``tracegs-weights`` wrote (file sizes); when the restorer's are all present,
  they are loaded through the pipeline's own loaders and one clip is restored (seconds);
- ``rasterizer``: one 3DGS fit of a procedural scene (embedded resolution) at the paper's fit settings
  (``conf/splat/paper.yaml``) with every iteration-based schedule scaled to ``--fit-iterations``, once on the GPU
  (gsplat) and once with the compiled CPU backend, same scene and seed: iterations per second of each, and the
  PSNR of each fit on the scene's held-out views (the two should agree within 0.2 dB);
- ``stage2``: two Stage-2 training iterations at the paper's batch (N student forwards with gradient and gradient
  checkpointing as configured, N teacher forwards without, the optimiser step), each timed as it ends: the
  second is the figure (the first allocates AdamW's state). Minutes each at 5B;
- ``speed``: the same Stage-2 iteration (the same code, at ``--speed-rollout`` visited states: the seconds per
  visited state are what the estimate reads) under each of the transformer's execution switches
  (``SPEED_SETTINGS``: fewer blocks checkpointed, compiled blocks, bf16 LoRA products, all of them) and as
  configured, each under its own key with its seconds and peak memory, or its one-line error (out of memory, a
  compiler that fails) while the others still run; ``attention_kernels``: the SDPA kernels of the configured run's
  first iteration; ``best``: the fastest setting. About 10 minutes at the paper's shapes by estimate (six fresh 5B
  bases, two iterations each): run it alone (``--sections speed``);
- ``demo``: the embedded demo end to end (``tracegs-demo``, the framework's single-GPU debug run) on the device,
  ``trainer=gpu`` with gsplat fitting and rendering (``demo_overrides``), in a child process: seconds, exit code,
  each step's seconds from its ``run.json``, or its one-line error. Last: tens of minutes on a CPU.

Sections run in the order above. On a fresh GPU machine gsplat compiles its CUDA kernels at first use (minutes): a
child process builds them on the CPU from the start while the transformer is timed on the GPU, and the rasterizer
section waits for it. ``--sections`` runs some of them (``device`` always runs). ``<out>/gpu_check.json`` is
rewritten after every figure (a run stopped at its time limit keeps what it measured) and merged with the figures
already there from the same scale (a rerun of one section replaces that section's figures alone).

Writes ``<out>/gpu_check.json`` and ``<out>/gpu_check.log`` (and ``rasterizer_build.log`` on a GPU); ``benchmarks/paper_gpu_hours.py --measured
<out>/gpu_check.json`` replaces its assumed seconds with these. Without a CUDA device (``--scale auto``) it prints
"no GPU: nothing measured" and exits 0; ``--scale rehearsal`` runs every section on the CPU at the rehearsal's
tiny shapes (``experiment=rehearsal``: what the test suite does, the demo's section aside: it composes that one's
command line; the whole demo takes tens of minutes on two cores). The last printed line is the JSON object.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage2_memory import (  # noqa: E402
    make_random_adapter,
    paper_shaped_batch,
    random_base_transformer,
    stage2_module,
)

from tracegs.cluster.weights import check_tree, weight_paths  # noqa: E402
from tracegs.data.colmap import load_scene, test_indices_for  # noqa: E402
from tracegs.data.config import SceneSourceConfig, SyntheticConfig  # noqa: E402
from tracegs.data.splits import every_nth_test  # noqa: E402
from tracegs.data.synthetic import generate_scene, scene_name  # noqa: E402
from tracegs.errors import TraceGSError, one_line  # noqa: E402
from tracegs.eval.clips import mean_psnr  # noqa: E402
from tracegs.splat.config import GaussianFitConfig  # noqa: E402
from tracegs.splat.fit import View, fit_gaussians  # noqa: E402
from tracegs.splat.gaussians import GaussianModel  # noqa: E402
from tracegs.splat.render import fit_device, render_views  # noqa: E402

log = logging.getLogger("gpu_check")
MIB = 2**20
SCENE_SEED = 0  # the embedded benchmark's first training scene


def compose(scale: str, overrides: tuple[str, ...] = ()):
    """The Stage-2 training config of ``experiment=<scale>`` (paper, or rehearsal at CPU sizes); it holds the
    deployment, evaluation and data settings too."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from tracegs.config.schema import register_configs
    from tracegs.location import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return hydra_compose(config_name="train", overrides=[f"experiment={scale}", "stage=stage2", *overrides])


class Clock:
    """Seconds and peak accelerator memory of a call; CUDA work is synchronised so the time is the kernels'."""

    def __init__(self, device: torch.device):
        self.device = device

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def measure(self, work: Callable[[], object], repeats: int = 1, warm_up: bool = True) -> dict:
        """Median seconds over ``repeats`` calls after one untimed warm-up call (``warm_up``: kernels chosen,
        memory pooled); peak MiB over the timed calls (CUDA only: CPU tensors have no allocator statistics,
        None there)."""
        if warm_up:
            work()
            self._sync()
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            work()
            self._sync()
            seconds.append(time.perf_counter() - start)
        peak = torch.cuda.max_memory_allocated(self.device) / MIB if self.device.type == "cuda" else None
        return {"seconds": statistics.median(seconds), "peak_mib": peak}


def device_facts(device: torch.device) -> dict:
    facts = {"device": str(device), "torch": torch.__version__, "cuda": torch.version.cuda}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        facts.update(name=props.name, memory_gib=round(props.total_memory / 2**30, 1),
                     capability=f"{props.major}.{props.minor}")
    else:
        facts["name"] = "cpu"
    return facts


def shortened(fit: GaussianFitConfig, iterations: int) -> GaussianFitConfig:
    """``fit`` with every iteration-based schedule scaled to ``iterations`` (the fractions of the paper's 30k stay)."""
    def scaled(value: int) -> int:
        return max(1, round(value * iterations / fit.iterations))

    d = fit.densification
    return replace(fit, iterations=iterations, snapshot_iters=[iterations],
                   sh_degree_interval=scaled(fit.sh_degree_interval),
                   densification=replace(d, refine_start_iter=scaled(d.refine_start_iter),
                                         refine_stop_iter=scaled(d.refine_stop_iter),
                                         refine_every=scaled(d.refine_every), reset_every=scaled(d.reset_every)))


def fit_and_score(fit: GaussianFitConfig, views: list[View], held_out: list[View], init: GaussianModel) -> dict:
    """Iterations per second of one fit, and its PSNR on the held-out views (rendered with the fit's backend)."""
    device = fit_device(fit)
    start = time.perf_counter()
    model = fit_gaussians(views, fit, init)[fit.iterations].to(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    rendered = render_views(model, [v.camera for v in held_out], fit.background, fit.sh_degree, fit.backend)
    truth = torch.stack([v.image for v in held_out]).to(rendered.device)
    return {"backend": str(fit.backend), "iterations": fit.iterations, "seconds": seconds,
            "iterations_per_s": fit.iterations / seconds, "psnr_held_out": mean_psnr(rendered.cpu(), truth.cpu())}


def rasterizer_section(fit: GaussianFitConfig, backends: tuple[str, str], iterations: int,
                       work_dir: Path) -> Iterator[tuple[str, object]]:
    """The same shortened fit with ``backends`` (accelerator's, then the CPU reference): speed and PSNR gap, each
    fit's figures yielded as soon as it ends."""
    synthetic = SyntheticConfig(root=str(work_dir / "synthetic"))
    generate_scene(SCENE_SEED, synthetic, Path(synthetic.root))
    source = SceneSourceConfig(root=synthetic.root, preset="synthetic")
    scene = load_scene(source, scene_name(SCENE_SEED))
    test = set(test_indices_for(source, scene) or every_nth_test(len(scene.cameras), source.test_every))
    indices = [i for i in range(len(scene.cameras)) if i not in test]
    training = [View(image=scene.load_image(i), camera=scene.cameras[i]) for i in indices]
    held_out = [View(image=scene.load_image(i), camera=scene.cameras[i]) for i in sorted(test)]
    init = GaussianModel.from_points(*scene.points_seen_by(indices, fit.init_min_views))  # as prepare starts a fit
    fits = []
    for backend in backends:
        fits.append(fit_and_score(replace(shortened(fit, iterations), backend=backend), training, held_out, init))
        yield "fits", fits
    yield "psnr_gap_db", fits[0]["psnr_held_out"] - fits[1]["psnr_held_out"]
    yield "speedup", fits[0]["iterations_per_s"] / fits[1]["iterations_per_s"]


def random_backbone(cfg):
    """``cfg``'s backbone settings with no weights to read: every section times random weights."""
    from omegaconf import OmegaConf

    backbone = OmegaConf.to_object(cfg.backbone)
    backbone.transformer.pretrained_path = None
    return backbone


def stage2_batch(cfg, backbone, device: torch.device) -> dict:
    """A random Stage-2 batch at ``cfg``'s batch size and shapes, on ``device``."""
    frame_size = (cfg.experiment.frame_height, cfg.experiment.frame_width)
    return {key: value.to(device)
            for key, value in paper_shaped_batch(backbone, cfg.experiment.batch_size, frame_size).items()}


def restorer_section(cfg, device: torch.device, clock: Clock) -> Iterator[tuple[str, object]]:
    """Time and memory of the restorer's forwards at ``cfg``'s shapes, random weights, each figure yielded as soon
    as it is measured (the Stage-2 iteration is its own section: minutes at 5B)."""
    from tracegs.restorer.adapters import add_adapter
    from tracegs.restorer.sampler import guided_prediction

    backbone = random_backbone(cfg)
    kind = device.type
    yield "deploy_guidance_scale", backbone.sampler.guidance_scale
    frame_size = (cfg.experiment.frame_height, cfg.experiment.frame_width)
    start = time.perf_counter()
    # The forwards are timed on a base with a freshly added adapter of the configured rank (active, as in every
    # forward of a trained student): no adapter file to write and verify before the first figure.
    transformer = random_base_transformer(backbone, kind)
    add_adapter(transformer, "aligned", backbone.lora)
    yield "build_seconds", time.perf_counter() - start
    dtype = next(transformer.parameters()).dtype
    one = {key: value.to(device, dtype) for key, value in paper_shaped_batch(backbone, 1, frame_size).items()}
    t = torch.full((1,), 0.5, device=device)

    def evaluation(guidance: float) -> Callable[[], object]:
        def run():
            with torch.no_grad(), torch.autocast(kind, dtype=dtype, enabled=dtype != torch.float32):
                return guided_prediction(transformer, one["target"], one["student_cond"], t, one["text"],
                                         one["ref_2d"], one["ref_3d"], guidance)
        return run

    yield "deploy_step", clock.measure(evaluation(backbone.sampler.guidance_scale), repeats=3)
    yield "rollout_step", clock.measure(evaluation(1.0), repeats=3)


def stage2_section(cfg, device: torch.device, work_dir: Path, publish: Callable[[str, object], None]) -> dict:
    """Set-up seconds and the first two Stage-2 training iterations at ``cfg``'s shapes (minutes each at 5B), each
    figure published as soon as it is measured: ``iteration`` is the last one finished (the second, once the
    first has allocated AdamW's state), ``iterations`` all of them."""
    backbone = random_backbone(cfg)
    publish("batch_size", cfg.experiment.batch_size)
    publish("rollout_steps", cfg.stage.rollout_steps)
    batch = stage2_batch(cfg, backbone, device)
    start = time.perf_counter()
    adapter = work_dir / "stage1_adapter"
    make_random_adapter(backbone, adapter, device.type)
    module = stage2_module(backbone, cfg.stage.memory_mode, cfg.stage.rollout_steps, adapter, device.type,
                           cfg.stage.guidance_scale)
    publish("setup_seconds", time.perf_counter() - start)
    iterations: list[dict] = []

    def finished(figures: dict) -> None:
        iterations.append(figures)
        publish("iterations", list(iterations))
        publish("iteration", figures)

    train_two_iterations(module, batch, cfg.trainer.precision, device, finished)
    return {}


# The speed section's settings: the overrides of the composed config each one times, under its key in the JSON.
# The paper scale checkpoints every block (36 of the H200's 141 GiB): the first two keep more activations.
SPEED_SETTINGS: dict[str, tuple[str, ...]] = {
    "as_configured": (),
    "activation_checkpointing_0.5": ("backbone.transformer.activation_checkpointing=0.5",),
    "activation_checkpointing_0": ("backbone.transformer.activation_checkpointing=0",),
    "compile_blocks": ("backbone.transformer.compile_blocks=true",),
    "lora_compute_bf16": ("backbone.lora.compute_bf16=true",),
    "all": ("backbone.transformer.activation_checkpointing=0.5", "backbone.transformer.compile_blocks=true",
            "backbone.lora.compute_bf16=true"),
}


def speed_section(scale: str, overrides: tuple[str, ...], device: torch.device, work_dir: Path, rollout: int,
                  publish: Callable[[str, object], None]) -> dict:
    """One Stage-2 iteration (the second of two: the first allocates AdamW's state and compiles) at ``rollout``
    visited states under each of ``SPEED_SETTINGS``, each published as soon as it is measured, a failing one as its
    one-line error; then the fastest (``best``)."""
    from tracegs.training.attention import AttentionKernelCheck

    cfg = compose(scale, overrides)
    backbone = random_backbone(cfg)
    publish("batch_size", cfg.experiment.batch_size)
    publish("rollout_steps", rollout)
    batch = stage2_batch(cfg, backbone, device)
    adapter = work_dir / "speed_adapter"
    make_random_adapter(backbone, adapter, device.type)  # one base (seed 0) and adapter for every setting
    timed: dict[str, float] = {}
    for name, setting in SPEED_SETTINGS.items():
        switched = random_backbone(compose(scale, (*overrides, *setting)))
        iterations: list[dict] = []
        kernels = AttentionKernelCheck(require_fused=False)
        try:
            module = stage2_module(switched, cfg.stage.memory_mode, rollout, adapter, device.type,
                                   cfg.stage.guidance_scale)
            train_two_iterations(module, batch, cfg.trainer.precision, device, iterations.append, [kernels])
            figures = {**iterations[-1], "first_seconds": iterations[0]["seconds"]}
            timed[name] = figures["seconds"]
        except Exception as error:  # noqa: BLE001 (out of memory or a compiler failure: the other settings still run)
            log.error("speed %s failed: %s", name, traceback.format_exc())
            figures = {"error": one_line(f"{type(error).__name__}: {error}")}
        finally:
            module = None  # the next setting measures its own peak: Lightning's trainer and module hold each other
            gc.collect()
            if device.type == "cuda":
                torch.cuda.empty_cache()
        publish(name, figures)
        if name == "as_configured" and kernels.kernels is not None:
            publish("attention_kernels", kernels.kernels)
    return {"best": min(timed, key=timed.get) if timed else None}


def train_two_iterations(module, batch: dict, precision: str, device: torch.device,
                         finished: Callable[[dict], None], callbacks: Iterable = ()) -> None:
    """Two Lightning training iterations on ``batch``; ``finished`` gets the seconds and peak memory of each as it
    ends. ``callbacks`` join the timing one."""
    import lightning as L
    from torch.utils.data import DataLoader

    class Probe(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
                torch.cuda.reset_peak_memory_stats(device)
            self.start = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            cuda = device.type == "cuda"
            if cuda:
                torch.cuda.synchronize(device)
            finished({"seconds": time.perf_counter() - self.start,
                      "peak_mib": torch.cuda.max_memory_allocated(device) / MIB if cuda else None})

    trainer = L.Trainer(accelerator="gpu" if device.type == "cuda" else "cpu", devices=1, precision=precision,
                        max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[Probe(), *callbacks])
    trainer.fit(module, train_dataloaders=DataLoader([batch], batch_size=None))


def vae_section(cfg, device: torch.device, clock: Clock) -> Iterator[tuple[str, object]]:
    """The VAE's encode and decode of one clip: the weights folder's architecture when its config is present,
    else diffusers' ``AutoencoderKLCogVideoX`` defaults (CogVideoX's published architecture); random weights."""
    from diffusers import AutoencoderKLCogVideoX
    from omegaconf import OmegaConf

    from tracegs.restorer.codec import CogVideoXCodec

    codec_cfg = OmegaConf.to_object(cfg.backbone.codec)
    frames, frame_size = cfg.experiment.frames_per_clip, (cfg.experiment.frame_height, cfg.experiment.frame_width)
    folder = Path(codec_cfg.pretrained_path or "")
    config = AutoencoderKLCogVideoX.load_config(folder) if (folder / "config.json").is_file() else {}
    torch.manual_seed(0)
    with torch.device(device):
        vae = AutoencoderKLCogVideoX.from_config(config).to(torch.bfloat16)
    codec = CogVideoXCodec(codec_cfg, device, vae=vae)
    clip = torch.rand(1, frames, 3, *frame_size, device=device)
    yield "vae_clip", [frames, *frame_size]
    latents = codec.encode(clip)
    yield "vae_encode", clock.measure(lambda: codec.encode(clip))
    yield "vae_decode", clock.measure(lambda: codec.decode(latents))


def weights_section(cfg, device: torch.device, clock: Clock) -> dict:
    """Which released models are on disk; with the restorer's all present, load them and restore one clip."""
    from omegaconf import OmegaConf

    from tracegs.restorer.build import build_backbone
    from tracegs.restorer.sampler import RestorationPipeline

    paths = weight_paths(cfg)
    present = {name: path is not None and Path(path).exists() for name, path in paths.items()}
    missing = sorted(name for name, path in paths.items() if path is not None and not present[name])
    figures: dict = {"paths": paths, "missing": missing}
    try:  # bytes only: hashing ~40 GB would take minutes of the lease (tracegs-weights --check hashes them)
        figures["manifest"] = check_tree(Path(cfg.paths.weights_dir), sizes_only=True)
    except TraceGSError as error:
        figures["manifest"] = {"error": str(error)}
    restorer = ("gsfixer_transformer", "cogvideox_vae", "t5_text_encoder", "t5_tokenizer", "dinov2", "vggt")
    if any(name in missing for name in restorer):
        log.info("weights missing under %s: %s (nothing loaded)", cfg.paths.weights_dir, ", ".join(missing))
        return figures
    start = time.perf_counter()
    backbone = build_backbone(OmegaConf.to_object(cfg.backbone), device=device)
    figures["load_seconds"] = time.perf_counter() - start
    height, width = cfg.experiment.frame_height, cfg.experiment.frame_width
    frames = torch.rand(1, cfg.experiment.frames_per_clip, 3, height, width)
    references = torch.rand(1, 2, 3, height, width)
    pipeline = RestorationPipeline(backbone)
    # One restoration (M guided steps) is minutes at the paper's shapes: timed once, cold, as deployment meets it.
    figures["restore_clip"] = clock.measure(
        lambda: pipeline.restore(frames, references, ["a photo of a scene"], seed=0), warm_up=False)
    return figures


def section(name: str, work: Callable[[Callable[[str, object], None]], dict | Iterable[tuple[str, object]]],
            record: dict, checkpoint: Callable[[], None] = lambda: None) -> None:
    """Run one section into ``record[name]``: its figures (a dict, pairs yielded as they are measured, or pairs
    handed to the ``publish`` callable it is given; each logged and passed to ``checkpoint`` at once, so a run
    stopped mid-section keeps them), or its error in one line (the traceback goes to the log) beside the figures
    measured before it."""
    log.info("%s ...", name)
    start = time.perf_counter()
    figures = record[name] = {}

    def publish(key: str, value: object) -> None:
        figures[key] = value
        log.info("%s.%s: %s", name, key, json.dumps(value, default=str))
        checkpoint()

    try:
        result = work(publish)
        for key, value in result.items() if isinstance(result, dict) else result:
            publish(key, value)
    except Exception as error:  # noqa: BLE001 (an unattended run records every failure and goes on)
        log.error("%s failed: %s", name, traceback.format_exc())
        figures["error"] = f"{type(error).__name__}: {error}".splitlines()[0]
    if torch.cuda.is_available():
        torch.cuda.empty_cache()  # what a section built is gone: the next one measures its own peak
    figures["section_seconds"] = round(time.perf_counter() - start, 2)
    log.info("%s: %s", name, json.dumps(figures, default=str))


def demo_overrides(device: torch.device, root: Path) -> list[str]:
    """The ``tracegs-demo`` command line of the demo section: the embedded default on one GPU (``trainer=gpu``) with
    gsplat's rasterizer (the embedded fit's ``auto`` would take it too; named, a machine without it is refused
    before any work), or on the CPU as the demo runs by default."""
    on_gpu = ["trainer=gpu", "data.prepare.fit.backend=gsplat"] if device.type == "cuda" else ["trainer=cpu"]
    return [*on_gpu, f"paths.root_dir={root}"]


def demo_section(device: torch.device, work_dir: Path, publish: Callable[[str, object], None]) -> dict:
    """The embedded demo end to end on ``device`` in a child process (its own CUDA context and Hydra run), timed."""
    root = work_dir / "demo"
    root.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "tracegs.cli.demo", *demo_overrides(device, root)]
    publish("command", " ".join(["tracegs-demo", *command[3:]]))
    start = time.perf_counter()
    with open(work_dir / "demo.log", "w") as output:
        done = subprocess.run(command, cwd=root, stdout=output, stderr=subprocess.PIPE, text=True)
    figures: dict = {"seconds": time.perf_counter() - start, "exit_code": done.returncode}
    if done.returncode != 0:
        figures["error"] = one_line(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "no message")
    records = sorted(root.rglob("run.json"))
    if records:  # the demo's own record: each step's seconds, the machine, the commit
        figures["run"] = json.loads(records[0].read_text())
    return figures


SECTIONS = ("device", "restorer", "vae", "weights", "rasterizer", "stage2", "speed", "demo")


def previous_record(target: Path, scale: str) -> dict:
    """The figures an earlier run left in ``target`` at the same ``scale`` (none from another scale or no file)."""
    try:
        record = json.loads(target.read_text())
    except (OSError, ValueError):
        return {"scale": scale}
    return record if isinstance(record, dict) and record.get("scale") == scale else {"scale": scale}


def write_record(record: dict, target: Path) -> None:
    partial = target.with_suffix(".json.tmp")
    partial.write_text(json.dumps(record, indent=2, default=str) + "\n")
    partial.replace(target)


# Both rasterizers the rasterizer section compares, built at first use: gsplat's CUDA kernels and the compiled CPU
# backend.
BUILD_RASTERIZERS = ("from gsplat.cuda._backend import _C; "
                     "from tracegs.splat.rasterize_compiled import library; library()")


def build_rasterizers_aside(out: Path) -> subprocess.Popen:
    """The rasterizers compile at first use (gsplat's kernels: minutes on a fresh machine): built in a child process
    on the CPU while the transformer is timed on the GPU, so the rasterizer section does not spend the lease
    waiting."""
    log.info("the rasterizers build aside (%s)", out / "rasterizer_build.log")
    with open(out / "rasterizer_build.log", "a") as build_log:
        return subprocess.Popen([sys.executable, "-c", BUILD_RASTERIZERS], stdout=build_log,
                                stderr=subprocess.STDOUT)


def run_check(scale: str, out: Path, fit_iterations: int, overrides: tuple[str, ...] = (),
              sections: tuple[str, ...] = SECTIONS, speed_rollout: int = 2) -> dict:
    """``sections`` at ``scale`` on CUDA (paper) or the CPU (rehearsal), merged into ``out``/gpu_check.json, which
    is rewritten after each section."""
    from omegaconf import OmegaConf

    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "gpu_check.log", mode="a")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        device = torch.device("cuda" if scale == "paper" else "cpu")
        cfg = compose(scale, overrides)
        clock = Clock(device)
        fit = OmegaConf.to_object(cfg.data.prepare.fit)
        backends = ("gsplat", "compiled") if device.type == "cuda" else ("torch", "compiled")
        target = out / "gpu_check.json"
        record = previous_record(target, scale)
        with tempfile.TemporaryDirectory() as scratch:
            work = {"device": lambda publish: device_facts(device),
                    "restorer": lambda publish: restorer_section(cfg, device, clock),
                    "vae": lambda publish: vae_section(cfg, device, clock),
                    "weights": lambda publish: weights_section(cfg, device, clock),
                    "rasterizer": lambda publish: rasterizer_section(fit, backends, fit_iterations, Path(scratch)),
                    "stage2": lambda publish: stage2_section(cfg, device, Path(scratch), publish),
                    "speed": lambda publish: speed_section(scale, overrides, device, Path(scratch), speed_rollout,
                                                           publish),
                    "demo": lambda publish: demo_section(device, Path(scratch), publish)}
            compiling = build_rasterizers_aside(out) if device.type == "cuda" and "rasterizer" in sections else None
            for name in SECTIONS:
                if name == "rasterizer" and compiling is not None:
                    compiling.wait()  # gsplat clears a build lock it finds: two builds at once would clash
                if name == "device" or name in sections:
                    section(name, work[name], record, lambda: write_record(record, target))
                    write_record(record, target)
        return record
    finally:
        log.removeHandler(handler)
        handler.close()


def main(argv: list[str] | None = None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/gpu_check")
    parser.add_argument("--scale", choices=("auto", "paper", "rehearsal"), default="auto")
    parser.add_argument("--fit-iterations", type=int, default=1000,
                        help="the paper's 30k-iteration fit, every schedule scaled to this many iterations")
    parser.add_argument("--speed-rollout", type=int, default=2,
                        help="visited states per Stage-2 iteration of the speed section (the paper's N = 10 in the "
                             "stage2 section)")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated, of {', '.join(SECTIONS)} (device always runs)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the composed config (e.g. paths.root_dir=...)")
    args = parser.parse_args(argv)
    sections = tuple(name.strip() for name in args.sections.split(",") if name.strip())
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        parser.error(f"--sections: unknown {', '.join(unknown)} (known: {', '.join(SECTIONS)})")
    if args.speed_rollout < 1:
        parser.error(f"--speed-rollout: {args.speed_rollout} visited states, at least 1 needed")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.scale == "auto" and not torch.cuda.is_available():
        print("no GPU: nothing measured")
        return None
    scale = "paper" if args.scale == "auto" else args.scale
    if scale == "paper" and not torch.cuda.is_available():
        sys.exit("--scale paper needs a CUDA device (--scale rehearsal runs the same sections on the CPU)")
    record = run_check(scale, Path(args.out), args.fit_iterations, tuple(args.overrides), sections, args.speed_rollout)
    print(json.dumps(record, default=str))
    return record


if __name__ == "__main__":
    main()
