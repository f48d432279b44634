"""Baseline (variant A) and Stage 1: what is trained, what both roles see, and the A -> Stage 1 hand-over."""

from __future__ import annotations

import torch
from support.training import TINY_LORA, fit_steps, make_batch, make_schedule, make_transformer

from tracegs.restorer.adapters import load_adapter
from tracegs.training.baseline import BaselineRestorerModule
from tracegs.training.config import OptimizerConfig
from tracegs.training.losses import warm_loss
from tracegs.training.stage1 import Stage1AlignmentModule


def evaluate(transformer, batch, t=0.6):
    g = torch.Generator().manual_seed(5)
    noisy = torch.randn(batch["target"].shape, generator=g)
    timestep = torch.full((noisy.shape[0],), t)
    with torch.no_grad():
        return transformer(noisy, batch["student_cond"], timestep, batch["text"], batch["ref_2d"],
                           batch["ref_3d"]).velocity


def test_baseline_trains_every_transformer_weight_and_fits_a_batch():
    module = BaselineRestorerModule(make_transformer(), make_schedule(), OptimizerConfig(lr=3e-3), seed=0)
    assert {id(p) for p in module.configure_optimizers()["optimizer"].param_groups[0]["params"]} == {
        id(p) for p in module.transformer.parameters()
    }
    batch = make_batch()
    schedule = make_schedule()

    def denoising_error():
        g = torch.Generator().manual_seed(9)
        target = batch["target"]
        noise = torch.randn(target.shape, generator=g)
        t = torch.tensor([0.3, 0.7])
        with torch.no_grad():
            v = module.transformer(schedule.add_noise(target, noise, t), batch["student_cond"], t, batch["text"],
                                   batch["ref_2d"], batch["ref_3d"]).velocity
        return torch.mean((v - schedule.velocity_target(target, noise, t)) ** 2).item()

    before = denoising_error()
    fit_steps(module, batch, steps=30)
    assert denoising_error() < 0.7 * before


def test_stage1_starts_equal_to_base_and_trains_only_the_shared_adapter(tmp_path):
    base = make_transformer()
    batch = make_batch()
    reference = evaluate(base, batch)
    module = Stage1AlignmentModule(make_transformer(), make_schedule(), TINY_LORA, OptimizerConfig(lr=1e-2))
    # zero-initialised B: before Stage 1 the adapted model equals the base restorer (variant A) exactly
    assert torch.equal(evaluate(module.transformer, batch), reference)
    params = module.configure_optimizers()["optimizer"].param_groups[0]["params"]
    assert params and all(".lora_" in n and ".aligned." in n for n, p in module.transformer.named_parameters()
                          if any(p is q for q in params))
    base_before = {n: p.clone() for n, p in module.transformer.named_parameters() if "lora_" not in n}
    fit_steps(module, batch, steps=3)
    for name, param in module.transformer.named_parameters():
        if "lora_" not in name:
            assert torch.equal(param, base_before[name]) and param.grad is None
    assert not torch.equal(evaluate(module.transformer, batch), reference)
    # the saved adapter reproduces the trained model on a fresh copy of the base
    path = tmp_path / "aligned.safetensors"
    module.export(path)
    fresh = make_transformer()
    load_adapter(fresh, "aligned", path, trainable=False)
    assert torch.equal(evaluate(fresh, batch), evaluate(module.transformer, batch))


def test_stage1_roles_share_state_noise_and_time_with_online_teacher_target():
    module = Stage1AlignmentModule(make_transformer(), make_schedule(), TINY_LORA, OptimizerConfig(lr=1e-2))
    batch = make_batch()
    seen = []

    def hook(model, args, kwargs, output):
        seen.append((args[0].detach().clone(), args[1].detach().clone(), args[2].detach().clone(), output.velocity))

    handle = module.transformer.register_forward_hook(hook, with_kwargs=True)
    logged = []
    module.log_dict = lambda values, **kw: logged.append({k: float(v) for k, v in values.items()})
    fit_steps(module, batch, steps=2)
    handle.remove()
    schedule = make_schedule()
    assert len(seen) == 2  # one forward of the doubled batch per step: both roles, online v_T
    for step, (noisy, cond, t, velocity) in enumerate(seen):
        z_s, z_t = noisy.chunk(2)
        assert torch.equal(z_s, z_t)
        assert torch.equal(t[:2], t[2:])
        assert torch.equal(cond[:2], batch["student_cond"]) and torch.equal(cond[2:], batch["teacher_cond"])
        # z_t is the pseudo-target forward-noised with one shared noise sample
        noise = (z_s - schedule.add_noise(batch["target"], torch.zeros_like(z_s), t[:2])) / t[:2].view(-1, 1, 1, 1, 1)
        v_s, v_t = velocity.detach().chunk(2)
        expected = warm_loss(v_s, v_t, schedule.velocity_target(batch["target"], noise, t[:2]), 1.0)
        for name in ("fm_student", "fm_teacher", "align", "loss"):
            assert abs(logged[step][f"train/{name}"] - expected[name].item()) < 1e-4 * (1 + expected[name].item())
