import math

import pytest
import torch
from diffusers import CogVideoXTransformer3DModel

from tracegs.restorer import adapters
from tracegs.restorer.build import (
    CheckpointMismatchError,
    create_transformer,
    load_transformer,
    transformer_kwargs,
)
from tracegs.restorer.config import TransformerConfig


def test_tiny_forward_backward_shapes(backbone, make_inputs):
    model = backbone.transformer
    model.requires_grad_(True)
    inputs = make_inputs()
    out = model(**inputs, return_retrieval=True)
    assert out.velocity.shape == inputs["noisy"].shape
    b, f, _, h, w = inputs["noisy"].shape
    p = model.config.patch_size
    assert out.retrieval.shape == (b, f * (h // p) * (w // p), 192)
    (out.velocity.square().mean() + out.retrieval.square().mean()).backward()
    for name in ("patch_embed.proj.weight", "projector_dino.proj.weight", "projector_vggt.proj.weight"):
        assert model.get_parameter(name).grad.abs().sum() > 0, name
    assert model.transformer_blocks[0].attn_cross.to_q.weight.grad.abs().sum() > 0
    assert model(**inputs).retrieval is None


def test_every_conditioning_input_reaches_the_velocity(backbone, make_inputs):
    model = backbone.transformer
    inputs = make_inputs()
    with torch.no_grad():
        base = model(**inputs).velocity
        for key in ("cond", "ref_2d", "ref_3d", "text", "timestep"):
            changed = dict(inputs, **{key: inputs[key] + 0.5})
            assert not torch.allclose(model(**changed).velocity, base, atol=1e-4), key


def test_retrieval_equals_independent_recomputation(backbone, make_inputs):
    model = backbone.transformer
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    with torch.no_grad():  # a non-zero LoRA so the recomputation must include phi (W^b of Eq. 7)
        for param in adapters.adapter_parameters(model, "student"):
            param.normal_(std=0.05)
    inputs = make_inputs()
    block = model.transformer_blocks[-1]
    captured = {}
    handle = block.norm_cross.register_forward_hook(
        lambda mod, args, out: captured.setdefault("queries_in", out)
    )
    with torch.no_grad():
        retrieval = model(**inputs, return_retrieval=True).retrieval
    handle.remove()

    attn, heads = block.attn_cross, model.config.num_attention_heads
    head_dim = model.config.attention_head_dim

    def effective(linear):  # W + (alpha / r) B A, read from the weights, not by calling the module
        delta = linear.lora_B["student"].weight @ linear.lora_A["student"].weight * linear.scaling["student"]
        return linear.base_layer.weight + delta, linear.base_layer.bias

    tokens = model.projector_dino.proj.weight @ inputs["ref_2d"].transpose(1, 2)
    tokens = tokens.transpose(1, 2) + model.projector_dino.proj.bias
    tokens = tokens + inputs["ref_3d"] @ model.projector_vggt.proj.weight.T + model.projector_vggt.proj.bias
    (wq, bq), (wk, bk), (wv, bv) = effective(attn.to_q), effective(attn.to_k), effective(attn.to_v)
    q = captured["queries_in"] @ wq.T + bq
    k, v = tokens @ wk.T + bk, tokens @ wv.T + bv
    per_head = []
    for h in range(heads):
        sl = slice(h * head_dim, (h + 1) * head_dim)
        weights = torch.softmax(q[..., sl] @ k[..., sl].transpose(1, 2) / math.sqrt(head_dim), dim=-1)
        per_head.append(weights @ v[..., sl])
    torch.testing.assert_close(retrieval, torch.cat(per_head, dim=-1), rtol=1e-4, atol=1e-5)


def test_text_length_must_match_config(backbone, make_inputs):
    inputs = make_inputs()
    inputs["text"] = inputs["text"][:, :5]
    with pytest.raises(ValueError, match="max_text_seq_length"):
        backbone.transformer(**inputs)


def test_paper_configuration_on_meta_device(paper_backbone):
    cfg = paper_backbone
    model = create_transformer(cfg.transformer, "meta")
    assert next(model.parameters()).is_meta
    assert len(model.transformer_blocks) == 42 and model.config.num_layers == 42
    attn = model.transformer_blocks[0].attn1
    assert attn.heads == 48 and attn.to_q.weight.shape == (3072, 3072)
    assert model.transformer_blocks[0].ff.net[2].weight.shape == (3072, 12288)
    assert model.transformer_blocks[0].attn_cross.to_k.weight.shape == (3072, 3072)
    adapters.add_adapter(model, "student", cfg.lora)
    adapters.clone_adapter(model, "student", "teacher", trainable=False)
    for name in ("student", "teacher"):
        assert sum(p.numel() for p in adapters.adapter_parameters(model, name)) == 66_060_288
    lora_layers = {n.split(".lora_")[0] for n, _ in model.named_parameters() if ".lora_A.student" in n}
    assert len(lora_layers) == 42 * 2 * 4

    # 49 x 480 x 720 -> 13 x 60 x 90 latents (8x spatial, 1 + (F - 1) / 4 frames) -> 17,550 video tokens
    latent = (1, 1 + (49 - 1) // 4, 16, 480 // 8, 720 // 8)
    assert latent[1:] == (13, 16, 60, 90)
    meta = torch.device("meta")
    out = model(
        noisy=torch.empty(latent, device=meta),
        cond=torch.empty(latent, device=meta),
        timestep=torch.tensor([999], device=meta),
        text=torch.empty(1, 226, 4096, device=meta),
        # 480 x 720 views at VGGT's 518-wide, aspect-kept size: 350 x 518 pixels, 25 x 37 patches of 14
        ref_2d=torch.empty(1, 2 * 25 * 37, 1024, device=meta),
        ref_3d=torch.empty(1, 2 * 25 * 37, 2048, device=meta),
        return_retrieval=True,
    )
    assert out.velocity.shape == latent
    assert out.retrieval.shape == (1, 17_550, 3072)


def test_load_transformer_round_trip(tmp_path, backbone, make_inputs):
    cfg = TransformerConfig(pretrained_path=str(tmp_path / "restorer"))
    backbone.transformer.save_pretrained(cfg.pretrained_path)
    loaded = load_transformer(cfg)
    inputs = make_inputs()
    with torch.no_grad():
        torch.testing.assert_close(loaded(**inputs).velocity, backbone.transformer(**inputs).velocity)


def test_load_transformer_lists_missing_keys(tmp_path):
    cfg = TransformerConfig(pretrained_path=str(tmp_path / "plain_cogvideox"))
    # A plain CogVideoX checkpoint of the same shape has no reference cross-attention / projections.
    kwargs = {
        k: v
        for k, v in transformer_kwargs(cfg).items()
        if k not in ("ref_2d_dim", "ref_3d_dim", "reference_norms", "timestep_scale", "prediction", "clean_min_time",
                     "sigma_data", "noise_scale")
    }
    CogVideoXTransformer3DModel(**kwargs).save_pretrained(cfg.pretrained_path)
    first_missing = r"model weight 'projector_dino.proj.bias' is not in the folder \(0 unused, 24 missing"
    with pytest.raises(CheckpointMismatchError, match=first_missing):
        load_transformer(cfg)
    with pytest.raises(CheckpointMismatchError, match="num_layers"):
        load_transformer(TransformerConfig(num_layers=3, pretrained_path=cfg.pretrained_path))
    # a checkpoint that does not say what it predicts is a velocity model
    with pytest.raises(CheckpointMismatchError, match="'prediction': \\('velocity', 'residual'\\)"):
        load_transformer(TransformerConfig(prediction="residual", pretrained_path=cfg.pretrained_path))
    with pytest.raises(FileNotFoundError, match="transformer.pretrained_path"):
        load_transformer(TransformerConfig(pretrained_path=str(tmp_path / "absent")))


def test_bf16_base_accepts_float32_inputs(backbone, make_inputs):
    model, inputs = backbone.transformer, make_inputs(batch=1, frames=2)
    with torch.no_grad():
        reference = model(**inputs, return_retrieval=True)
        model.to(torch.bfloat16)
        out = model(**inputs, return_retrieval=True)
    assert out.velocity.dtype == torch.float32 and out.retrieval.dtype == torch.float32
    assert (out.velocity - reference.velocity).abs().mean() < 0.05 * reference.velocity.abs().mean()


@pytest.mark.parametrize("prediction", ["clean", "residual"])
def test_x0_predictions_return_the_rectified_flow_velocity_of_their_x0(tmp_path, backbone, make_inputs, prediction):
    """The head's output is x0 (clean) or x0 - cond (residual); the model returns v = (z_t - x0) / max(t, t_min),
    so an Euler step to t = 0 lands on that x0. Weights saved as one prediction do not load as another."""
    as_velocity = backbone.transformer
    as_x0 = create_transformer(TransformerConfig(prediction=prediction))
    as_x0.load_state_dict(as_velocity.state_dict())
    as_velocity.save_pretrained(tmp_path / "weights")
    with pytest.raises(CheckpointMismatchError, match=f"'prediction': \\('velocity', '{prediction}'\\)"):
        load_transformer(TransformerConfig(pretrained_path=str(tmp_path / "weights"), prediction=prediction))
    inputs = make_inputs()
    inputs["timestep"] = torch.tensor([0.7, 0.01])  # the second sits below clean_min_time = 0.05
    with torch.no_grad():
        head = as_velocity(**inputs).velocity  # the same head output, read as x0 or x0 - cond
        velocity = as_x0(**inputs).velocity
    x0 = head + inputs["cond"] if prediction == "residual" else head
    denominator = torch.tensor([0.7, 0.05]).reshape(2, 1, 1, 1, 1)
    torch.testing.assert_close(velocity, (inputs["noisy"] - x0) / denominator)
    torch.testing.assert_close(inputs["noisy"][:1] - 0.7 * velocity[:1], x0[:1])
    with pytest.raises(ValueError, match="prediction='noise'"):
        create_transformer(TransformerConfig(prediction="noise"))


def test_fresh_residual_restorer_returns_its_input_rendering(make_inputs):
    model = create_transformer(TransformerConfig(prediction="residual"))
    inputs = make_inputs()
    with torch.no_grad():
        velocity = model(**inputs).velocity
    t = inputs["timestep"].clamp_min(0.05).reshape(-1, 1, 1, 1, 1)
    torch.testing.assert_close(inputs["noisy"] - t * velocity, inputs["cond"])  # x0 = R before training


def _randomised(model):
    """The model with a non-zero output head: any network output, not the zero-initialised one."""
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        model.proj_out.weight.copy_(torch.randn(model.proj_out.weight.shape, generator=g))
        model.proj_out.bias.copy_(torch.randn(model.proj_out.bias.shape, generator=g))
    return model


@pytest.mark.parametrize(("sigma_data", "noise_scale"), [(0.2, 1.0), (1.0, 1.0), (0.17, 0.17)])
def test_preconditioned_clean_prediction_tends_to_the_state_at_low_noise(make_inputs, sigma_data, noise_scale):
    """EDM's c_skip -> 1 and c_out -> 0 as t -> 0: x0_hat = z_t - t v -> z_t whatever the network outputs, and
    the velocity stays finite at t = 0 (no division by t)."""
    model = _randomised(create_transformer(TransformerConfig(prediction="preconditioned", sigma_data=sigma_data,
                                                             noise_scale=noise_scale)))
    inputs = make_inputs()
    gaps = []
    with torch.no_grad():
        for t in (0.1, 1e-2, 1e-3, 0.0):
            inputs["timestep"] = torch.full((2,), t)
            velocity = model(**inputs).velocity
            assert torch.isfinite(velocity).all()
            gaps.append(float((inputs["noisy"] - t * velocity - inputs["noisy"]).abs().max()))
    assert gaps[0] > gaps[1] > gaps[2] > gaps[3] == 0.0
    assert gaps[2] < 0.15 * gaps[1]  # |x0_hat - z_t| = t |v| with v bounded: linear in t near the clean end


@pytest.mark.parametrize("noise", [1.0, 0.25])
def test_preconditioned_velocity_is_that_of_edms_clean_prediction(make_inputs, noise):
    """v = (z_t - x0_hat) / t with x0_hat = R + c_skip s + c_out F(c_in s), s = z_t - (1 - t) R (Karras et al.
    2022, Table 1; noise end sigma_n: z_t = (1 - t) x0 + t sigma_n eps), written out here from the network
    output F read through a velocity-head twin."""
    sigma = 0.3
    precond = _randomised(create_transformer(TransformerConfig(prediction="preconditioned", sigma_data=sigma,
                                                               noise_scale=noise)))
    head = create_transformer(TransformerConfig())
    head.load_state_dict(precond.state_dict())
    inputs = make_inputs()
    t = torch.tensor([0.7, 0.2]).reshape(2, 1, 1, 1, 1)
    inputs["timestep"] = t.flatten()
    shifted = inputs["noisy"] - (1 - t) * inputs["cond"]
    variance = (1 - t) ** 2 * sigma**2 + t**2 * noise**2
    with torch.no_grad():
        velocity = precond(**inputs).velocity
        network = head(**{**inputs, "noisy": shifted / variance.sqrt()}).velocity
    x0 = inputs["cond"] + (1 - t) * sigma**2 / variance * shifted + t * noise * sigma / variance.sqrt() * network
    torch.testing.assert_close(velocity, (inputs["noisy"] - x0) / t, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(("sigma_data", "noise_scale"), [(0.17, 1.0), (0.3, 0.5)])
def test_edm_loss_weight_counts_the_network_outputs_error_alike_at_every_t(make_inputs, sigma_data, noise_scale):
    """EDM's lambda = 1 / c_out^2 in velocity units: two network outputs F1, F2 at the same state give velocities
    whose weighted squared difference is sigma_data^2 |F1 - F2|^2 at every t (1 at t = 1, sigma_d^2 / sigma_n^2 at 0)."""
    config = TransformerConfig(prediction="preconditioned", sigma_data=sigma_data, noise_scale=noise_scale)
    first, second = create_transformer(config), _randomised(create_transformer(config))
    twin = create_transformer(TransformerConfig())
    inputs = make_inputs()
    for t in (1.0, 0.6, 0.1, 0.01):
        inputs["timestep"] = torch.full((2,), t)
        weight = second.loss_weight(inputs["timestep"]).reshape(2, 1, 1, 1, 1)
        shifted = inputs["noisy"] - (1 - t) * inputs["cond"]
        with torch.no_grad():
            gap = second(**inputs).velocity - first(**inputs).velocity  # first: the zero-initialised head, F = 0
            twin.load_state_dict(second.state_dict())
            output = twin(**{**inputs, "noisy": shifted / ((1 - t) ** 2 * sigma_data**2 + t**2 * noise_scale**2) ** 0.5}).velocity
        torch.testing.assert_close(weight * gap**2, sigma_data**2 * output**2, rtol=1e-3, atol=1e-5)
    assert float(second.loss_weight(torch.ones(1))) == pytest.approx(1.0)
    assert float(second.loss_weight(torch.zeros(1))) == pytest.approx(sigma_data**2 / noise_scale**2)
    with pytest.raises(ValueError, match="prediction='preconditioned'"):
        create_transformer(TransformerConfig(prediction="residual")).loss_weight(torch.ones(1))


def test_fresh_preconditioned_restorer_predicts_its_rendering_from_pure_noise(make_inputs):
    model = create_transformer(TransformerConfig(prediction="preconditioned", sigma_data=0.2))
    inputs = make_inputs()
    inputs["timestep"] = torch.ones(2)
    with torch.no_grad():
        velocity = model(**inputs).velocity
    torch.testing.assert_close(inputs["noisy"] - velocity, inputs["cond"])  # x0_hat = R at t = 1
