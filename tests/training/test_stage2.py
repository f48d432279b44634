"""Stage 2: optimiser ownership, frozen teacher, on/off-policy queries, memory modes, exact resume."""

from __future__ import annotations

import pytest
import torch
from support.training import TINY_LORA, fit_steps, make_batch, make_schedule, make_transformer

from tracegs.restorer.adapters import active_adapter
from tracegs.restorer.sampler import sample, using_adapter
from tracegs.training.config import OptimizerConfig
from tracegs.training.stage2 import STUDENT, TEACHER, Stage2DistillationModule

N, M = 3, 8


def make_module(adapter_path, **overrides) -> Stage2DistillationModule:
    optimizer = overrides.pop("optimizer", OptimizerConfig(lr=1e-2, warmup_steps=2, grad_clip=None))
    kwargs = dict(rollout_steps=N, deploy_steps=M, lambda_ret=0.15, on_policy=True, memory_mode="stepwise", seed=3)
    kwargs.update(overrides)
    return Stage2DistillationModule(make_transformer(), make_schedule(), adapter_path, optimizer, **kwargs)


def named_adapter(module, name):
    return {n: p.detach().clone() for n, p in module.transformer.named_parameters() if f".{name}." in n}


def record_queries(module):
    """Forward hook recording every restorer evaluation: role, inputs, grad mode and outputs."""
    calls = []

    def hook(model, args, kwargs, output):
        named = dict(zip(("noisy", "cond", "timestep", "text"), args)) | kwargs
        noisy, cond, timestep = named["noisy"], named["cond"], named["timestep"]
        calls.append(
            {
                "role": active_adapter(model),
                "noisy": noisy.detach().clone(),
                "cond": cond.detach().clone(),
                "t": timestep.detach().clone(),
                "text": named["text"].detach().clone(),
                "grad": torch.is_grad_enabled(),
                "retrieval": kwargs.get("return_retrieval", False),
                "velocity": output.velocity.detach().clone(),
            }
        )

    handle = module.transformer.register_forward_hook(hook, with_kwargs=True)
    return calls, handle


def test_only_student_weights_in_optimiser(stage1_adapter):
    module = make_module(stage1_adapter)
    optimizer = module.configure_optimizers()["optimizer"]
    in_optimiser = {id(p) for group in optimizer.param_groups for p in group["params"]}
    student = {id(p) for n, p in module.transformer.named_parameters() if f".{STUDENT}." in n}
    # 2 blocks x 2 attentions x 4 projections x (A, B)
    assert in_optimiser == student and len(student) == 2 * 2 * len(TINY_LORA.target_modules) * 2


def test_teacher_frozen_and_bit_identical_student_moves(stage1_adapter):
    module = make_module(stage1_adapter)
    teacher_before = named_adapter(module, TEACHER)
    student_before = named_adapter(module, STUDENT)
    base_before = {n: p.detach().clone() for n, p in module.transformer.named_parameters() if "lora_" not in n}
    # the clone starts from the Stage-1 weights: student == teacher tensor by tensor
    for name, value in student_before.items():
        assert torch.equal(value, teacher_before[name.replace(f".{STUDENT}.", f".{TEACHER}.")])
    fit_steps(module, make_batch(), steps=3)
    for name, param in module.transformer.named_parameters():
        if f".{TEACHER}." in name:
            assert param.grad is None and not param.requires_grad
            assert torch.equal(param.detach(), teacher_before[name])
        elif "lora_" not in name:
            assert param.grad is None and torch.equal(param.detach(), base_before[name])
    changed = [not torch.equal(p.detach(), student_before[n]) for n, p in module.transformer.named_parameters()
               if f".{STUDENT}." in n]
    assert all(changed)


def test_teacher_queried_at_exactly_the_student_states(stage1_adapter):
    module = make_module(stage1_adapter)
    calls, handle = record_queries(module)
    batch = make_batch()
    fit_steps(module, batch, steps=2)
    handle.remove()
    schedule = make_schedule()
    full_grid = schedule.timesteps(M)
    assert len(calls) == 2 * 2 * N  # per step: N teacher + N student evaluations, no teacher rollout
    for step in range(2):
        pairs = calls[step * 2 * N:(step + 1) * 2 * N]
        teacher, student = pairs[0::2], pairs[1::2]
        assert [c["role"] for c in teacher] == [TEACHER] * N and [c["role"] for c in student] == [STUDENT] * N
        times = torch.stack([c["t"].reshape(-1)[0] for c in student])
        assert times[0] == full_grid[0] and all(times[:-1] > times[1:])
        assert all(bool((full_grid == t).any()) for t in times)
        for i in range(N):
            assert torch.equal(teacher[i]["noisy"], student[i]["noisy"])
            assert torch.equal(teacher[i]["t"], student[i]["t"])
            assert not teacher[i]["grad"] and student[i]["grad"]
            assert torch.equal(student[i]["cond"], batch["student_cond"])
            assert torch.equal(teacher[i]["cond"], batch["teacher_cond"])
            assert teacher[i]["retrieval"] and student[i]["retrieval"]
        # on-policy: each next state is the solver step with the *student's* velocity (Eq. 4)
        for i in range(N - 1):
            t, t_next = times[i], times[i + 1]
            expected = schedule.step(student[i]["noisy"], student[i]["velocity"], t, t_next)
            torch.testing.assert_close(student[i + 1]["noisy"], expected)
            teacher_step = schedule.step(student[i]["noisy"], teacher[i]["velocity"], t, t_next)
            assert not torch.allclose(student[i + 1]["noisy"], teacher_step)


def test_off_policy_queries_independently_forward_noised_states(stage1_adapter):
    module = make_module(stage1_adapter, on_policy=False)
    calls, handle = record_queries(module)
    batch = make_batch()
    fit_steps(module, batch, steps=1)
    handle.remove()
    schedule = make_schedule()
    teacher, student = calls[0::2], calls[1::2]
    target = batch["target"]
    noises = []
    for i in range(N):
        assert torch.equal(teacher[i]["noisy"], student[i]["noisy"])
        t = student[i]["t"].reshape(-1)[0]
        # the schedules are linear in (x0, eps): recover the noise that forward-noised the pseudo-target
        clean_part = schedule.add_noise(target, torch.zeros_like(target), t)
        noise_scale = schedule.add_noise(torch.zeros_like(target), torch.ones_like(target), t)
        noise = (student[i]["noisy"] - clean_part) / noise_scale
        assert abs(noise.std().item() - 1.0) < 0.25 and abs(noise.mean().item()) < 0.25
        noises.append(noise)
        if i + 1 < N:
            rollout = schedule.step(student[i]["noisy"], student[i]["velocity"], t, student[i + 1]["t"].reshape(-1)[0])
            assert not torch.allclose(student[i + 1]["noisy"], rollout, atol=1e-3)
    for i in range(N):
        for j in range(i + 1, N):
            assert not torch.allclose(noises[i], noises[j], atol=1e-2)  # independent draws


def test_lambda_ret_zero_skips_retrieval_readout(stage1_adapter):
    module = make_module(stage1_adapter, lambda_ret=0.0)
    calls, handle = record_queries(module)
    fit_steps(module, make_batch(), steps=1)
    handle.remove()
    assert calls and not any(c["retrieval"] for c in calls)


def student_grads(module):
    return torch.cat([p.grad.reshape(-1) for p in module.trainable_parameters()])


def test_retain_and_stepwise_give_the_same_gradients(stage1_adapter):
    grads = {}
    for mode in ("retain", "stepwise"):
        module = make_module(stage1_adapter, memory_mode=mode, rollout_steps=4)
        fit_steps(module, make_batch(), steps=1)
        grads[mode] = student_grads(module)
    assert grads["retain"].norm() > 0
    rel = (grads["retain"] - grads["stepwise"]).norm() / grads["retain"].norm()
    assert rel <= 1e-5, rel


def test_interrupted_and_resumed_equals_uninterrupted(stage1_adapter, tmp_path):
    batch = make_batch()
    optimizer = OptimizerConfig(lr=1e-2, warmup_steps=3, grad_clip=0.5)
    full = make_module(stage1_adapter, optimizer=optimizer)
    fit_steps(full, batch, steps=5)

    first = make_module(stage1_adapter, optimizer=optimizer)
    trainer = fit_steps(first, batch, steps=2)
    checkpoint = tmp_path / "k2.ckpt"
    trainer.save_checkpoint(checkpoint)
    stored = torch.load(checkpoint, weights_only=True)["state_dict"]
    assert stored and all(f".{STUDENT}." in key for key in stored)  # trainable weights only

    resumed = make_module(stage1_adapter, optimizer=optimizer)
    fit_steps(resumed, batch, steps=5, ckpt_path=checkpoint)
    for (name, a), b in zip(full.transformer.named_parameters(), resumed.transformer.parameters()):
        assert torch.equal(a, b), name


@pytest.mark.parametrize(("guidance", "temperature"), [(1.0, 1.0), (4.0, 1.0), (1.0, 0.0)])
@pytest.mark.parametrize("rollout_steps", [N, M])
def test_rollout_visits_the_deployment_samplers_states(stage1_adapter, guidance, temperature, rollout_steps):
    """Same noise, grid, guidance, sampling temperature and adapter: the Stage-2 rollout is the deployment
    sampler's trajectory, and the teacher is queried there under the same guidance rule."""
    module = make_module(stage1_adapter, guidance_scale=guidance, rollout_steps=rollout_steps,
                         temperature=temperature)
    batch = make_batch()
    batch_size = batch["target"].shape[0]

    def deployed(grid, generator, scale=guidance):
        with using_adapter(module.transformer, STUDENT):
            return sample(module.transformer, module.schedule, batch["student_cond"], batch["ref_2d"], batch["ref_3d"],
                          batch["text"], M, scale, generator, temperature=temperature, return_states=True,
                          grid=grid)[1]

    generator = module.step_generator()  # the first training step's generator: grid draw, then the noise
    grid = module.training_grid(generator)
    if rollout_steps == M:
        assert torch.equal(grid, module.schedule.timesteps(M))  # N = M: the full deployment schedule
    expected = deployed(grid, generator)
    generator = module.step_generator()
    rolled = module.rollout(batch, module.training_grid(generator), generator)
    assert len(rolled) == len(expected) == rollout_steps + 1
    assert all(torch.equal(a, b) for a, b in zip(rolled, expected))
    if guidance != 1.0:  # an unguided rollout would leave the deployed trajectory after its first step
        generator = module.step_generator()
        unguided = deployed(module.training_grid(generator), generator, scale=1.0)
        assert not torch.allclose(unguided[1], expected[1], atol=1e-4)

    # the training step itself (Lightning, losses, backward) queries both roles at exactly those states
    calls, handle = record_queries(module)
    fit_steps(module, batch, steps=1)
    handle.remove()
    teacher, student = calls[0::2], calls[1::2]
    assert len(student) == rollout_steps
    doubled = 1 if guidance == 1.0 else 2  # guidance: one doubled batch, conditional then unconditional
    for i, (t_call, s_call) in enumerate(zip(teacher, student)):
        assert t_call["role"] == TEACHER and s_call["role"] == STUDENT
        for call in (t_call, s_call):
            assert call["noisy"].shape[0] == doubled * batch_size
            assert all(torch.equal(half, expected[i]) for half in call["noisy"].chunk(doubled))
            assert torch.equal(call["text"][:batch_size], batch["text"])
            if doubled == 2:
                assert not call["text"][batch_size:].any()  # the all-zero unconditional text


def test_paper_stage2_rollout_is_unguided_ten_student_and_ten_teacher_forwards(stage1_adapter):
    """Supplement: per rollout, N gradient-tracked student forwards u_i = v(z_{t'_i}, t'_i, R_s) and N no-gradient
    teacher forwards, at N = 10 (experiment=paper); guidance is deployment's, not training's."""
    from types import SimpleNamespace

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from tracegs.cli.app import CONF_DIR
    from tracegs.config.schema import register_configs
    from tracegs.training.run import build_module

    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = OmegaConf.to_object(compose(config_name="train", overrides=[
            "experiment=paper", "stage=stage2", f"stage.init_adapter={stage1_adapter}",
            f"backbone.lora.rank={TINY_LORA.rank}", f"backbone.lora.alpha={TINY_LORA.alpha}"]))
    assert cfg.stage.rollout_steps == 10 and cfg.backbone.sampler.guidance_scale == 6.0
    module = build_module(cfg, SimpleNamespace(transformer=make_transformer(), schedule=make_schedule()))
    assert module.guidance_scale == 1.0
    batch = make_batch()
    calls, handle = record_queries(module)
    fit_steps(module, batch, steps=1)
    handle.remove()
    students = [c for c in calls if c["role"] == STUDENT]
    teachers = [c for c in calls if c["role"] == TEACHER]
    assert len(calls) == 20 and len(students) == 10 and len(teachers) == 10
    assert all(c["grad"] for c in students) and not any(c["grad"] for c in teachers)
    # unguided: one conditional batch per forward, the clip's own text (no all-zero unconditional half)
    assert all(c["noisy"].shape[0] == batch["target"].shape[0] for c in calls)
    assert all(torch.equal(c["text"], batch["text"]) for c in calls)


def test_clean_space_trajectory_term_weighs_each_state_by_t_squared(stage1_adapter):
    """loss.trajectory_space=clean compares the clean predictions the two velocities imply at the state: for
    rectified flow x0 = z - t v, so the term is t^2 times the velocity-space term of Eq. 6, state by state."""
    batch = make_batch()
    velocity, clean = (make_module(stage1_adapter, lambda_ret=0.0, trajectory_space=space) for space in
                       ("velocity", "clean"))
    clean.load_state_dict(velocity.state_dict())
    state = torch.randn_like(batch["target"].float())
    for t_value in (0.9, 0.2):
        t = torch.full((state.shape[0],), t_value)
        in_velocity = velocity.state_loss(batch, state, t)[0]["traj"]
        in_clean = clean.state_loss(batch, state, t)[0]["traj"]
        assert in_velocity > 0
        torch.testing.assert_close(in_clean, t_value**2 * in_velocity, rtol=1e-4, atol=1e-8)
    with pytest.raises(ValueError, match="loss.trajectory_space"):
        make_module(stage1_adapter, trajectory_space="noise")


def test_pseudo_target_trajectory_term_compares_the_students_clean_prediction_with_the_pseudo_target(
        stage1_adapter):
    """loss.trajectory_target=pseudo_target (the oracle teacher of the embedded scale, whose pseudo-target is the
    ground truth): at each visited state the student is compared with the clip's pseudo-target, not the teacher."""
    batch = make_batch()
    oracle = make_module(stage1_adapter, lambda_ret=0.0, trajectory_space="clean", trajectory_target="pseudo_target")
    taught = make_module(stage1_adapter, lambda_ret=0.0, trajectory_space="clean")
    taught.load_state_dict(oracle.state_dict())
    state = torch.randn_like(batch["target"].float())
    t = torch.full((state.shape[0],), 0.4)
    terms, student_velocity = oracle.state_loss(batch, state, t)
    expected = torch.nn.functional.mse_loss(oracle.schedule.predict_clean(state, student_velocity, t),
                                            batch["target"].float())
    torch.testing.assert_close(terms["traj"], expected, rtol=1e-4, atol=1e-8)
    assert not torch.allclose(taught.state_loss(batch, state, t)[0]["traj"], expected)
    with pytest.raises(ValueError, match="loss.trajectory_target"):
        make_module(stage1_adapter, trajectory_target="teacher_views")
