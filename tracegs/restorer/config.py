"""Hyperparameters of the restorer (supplement A.1-A.3). Defaults are the embedded CPU scale.

Plain dataclasses only (no torch import) so the Hydra schema can compose them cheaply.
The CogVideoX-5B-I2V + GSFixer values of the paper live in one place: ``conf/backbone/cogvideox5b.yaml``.
"""

from __future__ import annotations

from dataclasses import dataclass

from tracegs.modes import Mode
from tracegs.products import BASELINE, PREPARE, STAGE1, STAGE2, execution, reads
from tracegs.ranges import FINITE, SEED, at_least, each, positive, within

# Supplement A.2, "Text tokens": appended to every BLIP-2 caption before T5 encoding.
QUALITY_SUFFIX = (
    ". The video is of high quality, and the view is very clear. High quality, masterpiece, best quality, "
    "highres, ultra-detailed, fantastic."
)


class Prediction(Mode):
    """What the transformer's output head predicts (tracegs.restorer.transformer)."""

    velocity = "velocity"  # v, as CogVideoX
    clean = "clean"  # x0; the model returns v = (z_t - x0) / max(t, clean_min_time) (rectified flow only)
    residual = "residual"  # x0 as the condition plus a predicted residual (rectified flow only)
    # EDM's preconditioning centred on the condition: x0 = R + c_skip s + c_out F(c_in s), s = z_t - (1 - t) R
    # (rectified flow only; transformer.Preconditioning)
    preconditioned = "preconditioned"


class CodecKind(Mode):
    embedded = "embedded"  # fixed orthonormal block transform (CPU scale)
    cogvideox = "cogvideox"  # AutoencoderKLCogVideoX from a local diffusers folder


class ReferenceEncoderKind(Mode):
    embedded = "embedded"  # pixel-patch tokens (CPU scale)
    dinov2_vggt = "dinov2_vggt"  # DINOv2 (transformers) + VGGT (its own package), main paper Sec. 3.2


class ReferencePixels(Mode):
    """What DINOv2 and VGGT see of the two reference frames, before their resize (encoders.reference_images)."""

    clean = "clean"  # the frames as they are, in [0, 1]
    # GSFixer's release (gsfixer/cogvideo/inference.py l. 106-119): the frames, mapped to [-1, 1], are cast with
    # ``(x * 255).astype(np.uint8)``, so every pixel below 0.5 wraps modulo 256 (dark turns bright) before the
    # encoders read the 8-bit image back. Its published numbers were made so; its training code is unreleased.
    uint8_wrap = "uint8_wrap"


class TextEncoderKind(Mode):
    embedded = "embedded"  # deterministic hashed-token embeddings (CPU scale)
    t5 = "t5"  # the T5 encoder of CogVideoX (local folder)


class LossWeighting(Mode):
    """How the training states' squared velocity errors are weighted (``schedule.train_loss_weighting``)."""

    uniform = "uniform"  # the paper's plain L_fm (Eq. 1)
    edm = "edm"  # EDM's 1 / c_out^2 in velocity units (transformer.Preconditioning.loss_weight)


class ScheduleKind(Mode):
    rectified_flow = "rectified_flow"  # tiny backbone
    vpred_ddim = "vpred_ddim"  # CogVideoX: v-prediction DDPM training, DDIM deployment


@dataclass
class TransformerConfig:
    """Reference-guided CogVideoX DiT (supplement A.1). Field names follow diffusers' config keys."""

    num_layers: int = reads(PREPARE, BASELINE, default=2, range=at_least(1))
    num_attention_heads: int = reads(PREPARE, BASELINE, default=6, range=at_least(1))
    attention_head_dim: int = reads(PREPARE, BASELINE, default=32, range=at_least(1))
    # Per-token output is patch^2 x latent_channels = 96 = width / 2: a wider output than ~half the width
    # leaves the velocity head rank-limited and noise cannot be removed.
    # The patch embedding sees 2x this: noisy + condition latent (Eq. supp-render-cond).
    latent_channels: int = reads(PREPARE, BASELINE, default=24, range=at_least(1))
    text_embed_dim: int = reads(PREPARE, BASELINE, default=64, range=at_least(1))
    max_text_seq_length: int = reads(PREPARE, BASELINE, default=8, range=at_least(1))
    time_embed_dim: int = reads(PREPARE, BASELINE, default=128, range=at_least(1))
    patch_size: int = reads(PREPARE, BASELINE, default=2, range=at_least(1))
    # Latent grid the positional embeddings are precomputed for (other sizes are recomputed per call).
    # Pixel frames, diffusers convention: latent frames = (F - 1) / ratio + 1
    sample_frames: int = reads(PREPARE, BASELINE, default=9, range=at_least(1))
    sample_height: int = reads(PREPARE, BASELINE, default=12, range=at_least(1))
    sample_width: int = reads(PREPARE, BASELINE, default=18, range=at_least(1))
    temporal_compression_ratio: int = reads(PREPARE, BASELINE, default=1, range=at_least(1))
    use_rotary_positional_embeddings: bool = reads(PREPARE, BASELINE, default=False)
    use_learned_positional_embeddings: bool = reads(PREPARE, BASELINE, default=False)
    attention_bias: bool = reads(PREPARE, BASELINE, default=True)
    # width of Enc_DINO tokens (embedded: 8x8x3 pixel patches)
    ref_2d_dim: int = reads(PREPARE, BASELINE, default=192, range=at_least(1))
    # Width of Enc_VGGT tokens (embedded: 8x8x3 cross-view difference + 8 position)
    ref_3d_dim: int = reads(PREPARE, BASELINE, default=200, range=at_least(1))
    # GSFixer's LayerNorms on the reference path: per-head q/k in ``attn_cross`` and after each projector. Its
    # released weights hold them (paper scale: true); the embedded restorer was tuned without them.
    reference_norms: bool = reads(PREPARE, BASELINE, default=False)
    # The model embeds ``timestep * timestep_scale``: rectified-flow t in [0, 1] -> 0..1000 like CogVideoX's
    # integer DDPM steps (scale 1). Callers always pass the schedule's native t.
    timestep_scale: float = reads(PREPARE, BASELINE, default=1000.0, range=positive())
    # "velocity" (the output head predicts v, as CogVideoX) or "clean" (it predicts x0 and the model returns
    # v = (z_t - x0) / max(t, clean_min_time); rectified flow only). See transformer.velocity_from_clean.
    prediction: Prediction = reads(PREPARE, BASELINE, default=Prediction.velocity)
    clean_min_time: float = reads(PREPARE, BASELINE, default=0.05, range=within(0, 1, low_open=True))
    # prediction=preconditioned: the standard deviation of the residual x0 - R in latent units, EDM's sigma_data.
    sigma_data: float = reads(PREPARE, BASELINE, default=1.0, range=positive())
    # prediction=preconditioned: the schedule's noise end sigma_n (schedule.noise_scale; the two must agree).
    noise_scale: float = reads(PREPARE, BASELINE, default=1.0, range=positive())
    # Local folder holding config.json and the weights (build.load_transformer), or whose transformer/ holds them.
    pretrained_path: str | None = reads(PREPARE, BASELINE, default=None)
    # Exact key names of stored tensors the class has no place for: skipped and logged (each) instead of refusing
    # the folder, which any other unused stored tensor does. The paper scale lists none. Never loaded, they leave
    # the model as it is.
    skip_stored_keys: list[str] = execution(factory=list)
    # Frozen base weights; paper scale "bfloat16" (LoRA factors stay float32: adapters.py)
    dtype: str = reads(PREPARE, BASELINE, default="float32")
    # Execution switches (tracegs.restorer.speed): each computes the same function (tests/restorer/test_speed.py:
    # equal outputs and gradients), so none changes a product, and tuning them to a card keeps every product
    # already made. The share of blocks whose activations are recomputed in backward instead of kept (0: none,
    # 1: every block, which fits a 5B student on any card; the H200 ran Stage 2 at 36 of its 141 GiB so).
    activation_checkpointing: float = execution(default=0.0, range=within(0, 1))
    # torch.compile of each block (regional compilation); compile_backend: torch.compile's backend ("inductor"
    # generates kernels; "eager" only traces, the CPU tests' exact check).
    compile_blocks: bool = execution(default=False)
    compile_backend: str = execution(default="inductor")
    # Refuse, at the first training step's first attention call, to run attention on PyTorch's unfused math
    # kernel (it materialises every attention matrix); off: the kernel in use is logged either way.
    require_fused_attention: bool = execution(default=False)


@dataclass
class LoraConfig:
    """LoRA on both attentions of every block (supplement Table of insertion points, Eq. supp-lora)."""

    rank: int = reads(STAGE1, default=8, range=at_least(1))
    alpha: int = reads(STAGE1, default=8, range=at_least(1))
    dropout: float = reads(STAGE1, default=0.0, range=within(0, 1, high_open=True))
    target_modules: list[str] = reads(STAGE1, factory=lambda: ["to_q", "to_k", "to_v", "to_out.0"])
    attention_modules: list[str] = reads(STAGE1, factory=lambda: ["attn1", "attn_cross"])
    # Compute the adapters' products in bfloat16 while their factors (and AdamW's state) stay float32 masters
    # (tracegs.restorer.adapters.set_lora_compute): under bf16 autocast (trainer.precision=bf16-mixed, the
    # sampler's autocast_bf16) the same numbers without peft's float32 copy of every adapted input; elsewhere
    # bf16's rounding, which changes the products (hence read by Stage 1 and everything after it).
    compute_bf16: bool = reads(STAGE1, default=False)


@dataclass
class CodecConfig:
    """``embedded``: fixed orthonormal block transform; ``cogvideox``: AutoencoderKLCogVideoX (local dir)."""

    kind: CodecKind = reads(PREPARE, BASELINE, default=CodecKind.embedded)
    block_size: int = reads(PREPARE, BASELINE, default=4, range=at_least(1))
    # 40.4 dB mean round trip on scikit-image photos at 48x72 (16 -> 35.0 dB)
    latent_channels: int = reads(PREPARE, BASELINE, default=24, range=at_least(1))
    pretrained_path: str | None = reads(PREPARE, BASELINE, default=None)
    # Decode the VAE in tiles to bound memory at 480x720 (diffusers' enable_tiling).
    tiling: bool = reads(PREPARE, BASELINE, default=True)


@dataclass
class ReferenceEncoderConfig:
    """``embedded``: pixel-patch tokens; ``dinov2_vggt``: DINOv2 (transformers) + VGGT (its own package)."""

    kind: ReferenceEncoderKind = reads(PREPARE, BASELINE, default=ReferenceEncoderKind.embedded)
    patch_size: int = reads(PREPARE, BASELINE, default=8, range=at_least(1))
    dino_path: str | None = reads(PREPARE, BASELINE, default=None)
    vggt_path: str | None = reads(PREPARE, BASELINE, default=None)
    # GSFixer (the paper is silent): DINOv2 and VGGT both see VGGT's preprocessing, width 518 with the aspect
    # ratio kept (480 x 720 -> 350 x 518, 25 x 37 patches of 14), unnormalised [0, 1] (encoders.reference_images)
    image_size: int = reads(PREPARE, BASELINE, default=518, range=at_least(1))
    # dinov2_vggt only (the embedded stand-in reads pixels of its own): clean frames, or GSFixer's wrapped bytes.
    pixels: ReferencePixels = reads(PREPARE, BASELINE, default=ReferencePixels.clean)
    # Weights of DINOv2 and VGGT (frozen, inference only); paper scale "bfloat16". Tokens leave as float32.
    dtype: str = reads(PREPARE, BASELINE, default="float32")


@dataclass
class TextEncoderConfig:
    """``embedded``: deterministic hashed-token embeddings; ``t5``: T5 encoder (local dir)."""

    kind: TextEncoderKind = reads(PREPARE, BASELINE, default=TextEncoderKind.embedded)
    dim: int = reads(PREPARE, BASELINE, default=64, range=at_least(1))
    max_length: int = reads(PREPARE, BASELINE, default=8, range=at_least(1))
    pretrained_path: str | None = reads(PREPARE, BASELINE, default=None)
    # The T5 tokenizer's directory; None = CogVideoX's layout, ``tokenizer/`` beside ``pretrained_path``
    # (``text_encoder/``), or ``pretrained_path`` itself if there is no such folder (a plain T5 checkpoint).
    tokenizer_path: str | None = reads(PREPARE, BASELINE, default=None)
    quality_suffix: str = reads(PREPARE, BASELINE, default=QUALITY_SUFFIX)
    # The unconditional branch of guided sampling (deployment, variant A, pseudo-targets): None = the all-zero
    # embedding caption dropout trains (supplement A.2); a prompt = its encoding, without the quality suffix.
    # Paper scale: GSFixer's negative prompt (conf/backbone/cogvideox5b.yaml).
    negative_prompt: str | None = reads(PREPARE, BASELINE, default=None)
    seed: int = reads(PREPARE, BASELINE, default=0, range=SEED)
    # T5 weights (frozen, inference only); paper scale "bfloat16". Embeddings leave as float32.
    dtype: str = reads(PREPARE, BASELINE, default="float32")


@dataclass
class ScheduleConfig:
    """``rectified_flow`` (tiny backbone) or ``vpred_ddim`` (CogVideoX v-prediction DDPM + DDIM)."""

    kind: ScheduleKind = reads(PREPARE, BASELINE, default=ScheduleKind.rectified_flow)
    num_train_timesteps: int = reads(PREPARE, BASELINE, default=1000, range=at_least(1))
    # The deployment grid, and the training-time density below, are read where they are used: a restoration
    # (a restorer-made cache, Stage 2's rollout, deployment) samples on the grid and never draws training times.
    deploy_steps: int = reads(PREPARE, STAGE2, default=20, range=at_least(1))  # M
    # rectified_flow: training times of forward-noised states (baseline L_fm, Stage 1) are drawn with density
    # proportional to t^p, p >= 0 (0 = uniform). A large p trains mostly at high noise, where the restorer reads
    # the clip from its condition; conf/backbone/tiny.yaml records the measured choice.
    train_time_power: float = reads(BASELINE, default=0.0, range=at_least(0))
    # rectified_flow: with a value, training times are logit-normal instead, t = sigmoid(m + s n), n ~ N(0, 1)
    # (Esser et al. 2024, Sec. 3.1): [m, s]. Takes the place of train_time_power.
    train_time_logit_normal: list[float] | None = reads(PREPARE, BASELINE, default=None, range=each(FINITE))
    # rectified_flow: the share of training times drawn uniformly on [0, 1] instead (a mixture with the density
    # above): a density concentrated near t = 1, where the first prediction is made, still trains the low-noise
    # states the last reverse steps visit.
    train_time_uniform_share: float = reads(BASELINE, default=0.0, range=within(0, 1))
    # rectified_flow with transformer.prediction=preconditioned: "edm" weights each training state's squared
    # velocity error by EDM's lambda = 1 / c_out^2 (Karras et al. 2022, Table 1) written in velocity units, so the
    # network output's error counts alike at every t (transformer.Preconditioning.loss_weight); "uniform" (the
    # paper's plain L_fm) weights the velocity error alike, which counts the output's error near t = 1, where the
    # first prediction is made, 1 / sigma_data^2 times less than near t = 0.
    train_loss_weighting: LossWeighting = reads(BASELINE, default=LossWeighting.uniform)
    # rectified_flow: the noise end of the path, z_1 = noise_scale eps (1: the standard path). Near the size of the
    # residual x0 - R, the states carry what the restorer is unsure of through the whole trajectory.
    noise_scale: float = reads(PREPARE, BASELINE, default=1.0, range=positive())
    # rectified_flow: the deployment grid (and so Stage 2's resampled grids, drawn from it) puts its M + 1 points
    # at equal steps of t^(q + 1), q >= 0; q = 0 is the uniform grid. With q = p every solver step spans an equal
    # share of the training times, so the solver stays where the training times are (with p = 12 and q = 0
    # the last state before the clean end is t = 0.05, which t^12 draws with probability 0.05^13; with q = 12
    # it is 0.79).
    deploy_time_power: float = reads(PREPARE, STAGE2, default=0.0, range=at_least(0))
    # CogVideoX-5B scheduler values (used by vpred_ddim only).
    beta_start: float = reads(PREPARE, BASELINE, default=0.00085,
                              range=within(0, 1, low_open=True, high_open=True))
    beta_end: float = reads(PREPARE, BASELINE, default=0.012,
                            range=within(0, 1, low_open=True, high_open=True))
    beta_schedule: str = reads(PREPARE, BASELINE, default="scaled_linear")
    snr_shift_scale: float = reads(PREPARE, BASELINE, default=1.0, range=positive())
    rescale_betas_zero_snr: bool = reads(PREPARE, BASELINE, default=True)


@dataclass
class SamplerConfig:
    """Deployment sampling (Alg. 1, Restore).

    ``guidance_scale``: classifier-free guidance of deployment. 1 = no guidance (one restorer evaluation per
    state); any other value costs a second, unconditional evaluation per state. The paper states no value;
    CogVideoX's and GSFixer's pipelines use 6. Stage 2's rollout has its own setting (``stage.guidance_scale``).
    """

    # A and Stage 1 never sample (reads(PREPARE, STAGE2) on BackboneConfig.sampler); a cache's pseudo-targets have
    # their own guidance (data.prepare.pseudo_target_guidance) and a seed derived from each clip.
    guidance_scale: float = reads(STAGE2, default=1.0, range=at_least(0))
    seed: int = reads(STAGE2, default=0, range=SEED)
    # Sampling temperature tau: every reverse trajectory (deployment, pseudo-target restorations, the Stage-2
    # rollout, the trajectory diagnostics) starts at the schedule's noise end of tau * eps. The paper samples
    # from the Gaussian prior itself (tau = 1, its DDIM from noise). tau < 1 narrows the samples towards the
    # restorer's posterior mean, which PSNR rewards; tau = 0 starts every trajectory at the noise end's centre
    # (a deterministic restorer; forward-noised training states are never that quiet, so the student's states
    # are its own). conf/backbone/tiny_diffusion.yaml records the measured choice.
    temperature: float = reads(PREPARE, STAGE2, default=1.0, range=within(0, 1))
    autocast_bf16: bool = reads(PREPARE, STAGE2, default=True)  # only takes effect on CUDA


# A paired-clip cache is made with (supplement A.4) the backbone fields prepare reads: the codec's latents and the
# frozen reference and text encoders' outputs and, when its pseudo-targets are restorations (data.prepare.
# pseudo_target=restorer), what makes a restoration: the transformer, the deployment schedule and the sampler,
# less the fields that leave a restoration's bytes as they are. Never the adapters (the generator has none), nor
# where the encoders live (backbone.offload_encoders).
RESTORATION_SECTIONS = ("transformer", "schedule", "sampler")


def sections_not_in_cache(pseudo_target) -> tuple[str, ...]:
    """The backbone sections prepare reads that a paired-clip cache with these pseudo-targets is not made with."""
    return () if str(pseudo_target) == "restorer" else RESTORATION_SECTIONS


@dataclass
class BackboneConfig:
    name: str = reads(PREPARE, BASELINE, default="tiny")
    transformer: TransformerConfig = reads(PREPARE, BASELINE, factory=TransformerConfig)
    # A trains the whole transformer: no adapter.
    lora: LoraConfig = reads(STAGE1, factory=LoraConfig)
    codec: CodecConfig = reads(PREPARE, BASELINE, factory=CodecConfig)
    reference_encoder: ReferenceEncoderConfig = reads(PREPARE, BASELINE, factory=ReferenceEncoderConfig)
    text_encoder: TextEncoderConfig = reads(PREPARE, BASELINE, factory=TextEncoderConfig)
    schedule: ScheduleConfig = reads(PREPARE, BASELINE, factory=ScheduleConfig)
    sampler: SamplerConfig = reads(PREPARE, STAGE2, factory=SamplerConfig)
    # Keep the text and reference encoders on the CPU and move them to the accelerator only while they encode a
    # batch of clips (sampler.RestorationPipeline): the transformer denoises without T5 / DINOv2 / VGGT beside it.
    offload_encoders: bool = reads(BASELINE, default=False)
