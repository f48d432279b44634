import pytest
import torch

from tracegs.restorer import adapters
from tracegs.restorer.sampler import RestorationPipeline, partial_start, sample


def _count_forwards(model):
    calls = []
    handle = model.register_forward_hook(
        lambda mod, args, kwargs, out: calls.append(kwargs), with_kwargs=True
    )
    return calls, handle


def _inputs(backbone, make_inputs):
    inputs = make_inputs(batch=1, frames=2)
    return dict(cond=inputs["cond"], ref_2d=inputs["ref_2d"], ref_3d=inputs["ref_3d"], text=inputs["text"])


def test_sampler_is_deterministic_per_seed(backbone, make_inputs):
    inputs = _inputs(backbone, make_inputs)
    run = lambda seed: sample(  # noqa: E731
        backbone.transformer,
        backbone.schedule,
        **inputs,
        steps=4,
        guidance_scale=1.0,
        generator=torch.Generator().manual_seed(seed),
    )
    first, again, other = run(7), run(7), run(8)
    assert torch.equal(first, again)
    assert not torch.allclose(first, other)


def test_temperature_scales_the_first_state_and_zero_makes_the_restorer_deterministic(backbone, make_inputs):
    """Every trajectory starts at the noise end of tau * eps: tau = 1 is the Gaussian prior, tau = 0 its centre,
    so the restoration no longer depends on the seed."""
    inputs = _inputs(backbone, make_inputs)

    def run(seed, temperature):
        return sample(backbone.transformer, backbone.schedule, **inputs, steps=4, guidance_scale=1.0,
                      generator=torch.Generator().manual_seed(seed), temperature=temperature, return_states=True)[1]

    prior = run(7, 1.0)[0]
    assert torch.equal(run(7, 0.5)[0], 0.5 * prior)
    cold, other_seed = run(7, 0.0), run(8, 0.0)
    assert torch.count_nonzero(cold[0]) == 0
    assert all(torch.equal(a, b) for a, b in zip(cold, other_seed))
    assert not torch.allclose(run(7, 1.0)[-1], run(8, 1.0)[-1])


def test_partial_start_noises_the_start_to_the_kept_steps_first_time(backbone):
    """SDEdit's start: strength s keeps the last int(s x M) steps of the grid and noises the clean start to the
    first of them, with the draw the full trajectory would start from."""
    grid = backbone.schedule.timesteps(10)
    start, noise = torch.rand(2, 3, 4, 4, 4), torch.randn(2, 3, 4, 4, 4)
    z, rest = partial_start(backbone.schedule, grid, start, noise, 0.3)
    assert torch.equal(rest, grid[7:])
    assert torch.equal(z, backbone.schedule.add_noise(start, noise, grid[7].expand(2)))
    assert torch.equal(partial_start(backbone.schedule, grid, start, noise, 0.01)[1], grid[-2:])  # one step at least


def test_strength_runs_the_last_steps_from_the_condition_and_one_is_deployment(backbone, make_inputs):
    """A pseudo-target at strength s < 1 evaluates the restorer int(s x M) times, starting from the condition's
    own latent; strength 1 is exactly the restoration from noise."""
    inputs = _inputs(backbone, make_inputs)
    run = lambda strength: sample(backbone.transformer, backbone.schedule, **inputs, steps=4,  # noqa: E731
                                  guidance_scale=1.0, generator=torch.Generator().manual_seed(3), strength=strength)
    calls, handle = _count_forwards(backbone.transformer)
    try:
        half, full = run(0.5), run(1.0)
    finally:
        handle.remove()
    assert len(calls) == 2 + 4
    assert torch.equal(full, sample(backbone.transformer, backbone.schedule, **inputs, steps=4, guidance_scale=1.0,
                                    generator=torch.Generator().manual_seed(3)))
    # The partial start is nearer its condition than the restoration from noise.
    assert (half - inputs["cond"]).norm() < (full - inputs["cond"]).norm()


def test_guidance_one_skips_unconditional_pass(backbone, make_inputs):
    inputs = _inputs(backbone, make_inputs)
    calls, handle = _count_forwards(backbone.transformer)
    plain, states = sample(
        backbone.transformer,
        backbone.schedule,
        **inputs,
        steps=3,
        guidance_scale=1.0,
        generator=torch.Generator().manual_seed(0),
        return_states=True,
    )
    assert len(calls) == 3 and all(c["noisy"].shape[0] == 1 for c in calls)
    assert len(states) == 4 and torch.equal(states[-1], plain)

    calls.clear()
    guided = sample(
        backbone.transformer,
        backbone.schedule,
        **inputs,
        steps=3,
        guidance_scale=3.0,
        generator=torch.Generator().manual_seed(0),
    )
    handle.remove()
    assert len(calls) == 3 and all(c["noisy"].shape[0] == 2 for c in calls)
    text = calls[0]["text"]
    assert torch.equal(text[0], inputs["text"][0]) and not text[1].any()  # all-zero unconditional text
    assert not torch.allclose(guided, plain)


def test_guidance_combines_conditional_and_unconditional(backbone, make_inputs):
    inputs = _inputs(backbone, make_inputs)
    model, schedule = backbone.transformer, backbone.schedule
    grid = schedule.timesteps(1)
    z = torch.randn(inputs["cond"].shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        v_c = model(z, inputs["cond"], grid[:1], inputs["text"], inputs["ref_2d"], inputs["ref_3d"]).velocity
        null = torch.zeros_like(inputs["text"])
        v_u = model(z, inputs["cond"], grid[:1], null, inputs["ref_2d"], inputs["ref_3d"]).velocity
    expected = schedule.step(z, v_u + 2.5 * (v_c - v_u), grid[:1], grid[1:])
    got = sample(
        model, schedule, **inputs, steps=1, guidance_scale=2.5, generator=torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5)


def test_pipeline_restores_clips_with_and_without_adapter(backbone):
    frames, refs = torch.rand(1, 3, 3, 48, 72), torch.rand(1, 2, 3, 48, 72)
    base = RestorationPipeline(backbone).restore(frames, refs, ["a room"], seed=0, steps=2)
    assert base.shape == frames.shape and 0 <= base.min() and base.max() <= 1
    model = backbone.transformer
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    with torch.no_grad():
        for p in adapters.adapter_parameters(model, "student"):
            p.normal_(std=0.05)
    pipeline = RestorationPipeline(backbone, "student")
    restored = pipeline.restore(frames, refs, ["a room"], seed=0, steps=2)
    assert not torch.allclose(restored, base)
    # adapter None means the bare base model even when adapters are loaded
    torch.testing.assert_close(
        RestorationPipeline(backbone).restore(frames, refs, ["a room"], seed=0, steps=2), base
    )
    assert torch.equal(pipeline.restore(frames, refs, ["a room"], seed=0, steps=2), restored)
    with pytest.raises(KeyError, match="teacher"):
        RestorationPipeline(backbone, "teacher")
    with pytest.raises(ValueError, match="captions"):
        pipeline.restore(frames, refs, ["a", "b"], seed=0)


def test_guidance_runs_its_unconditional_branch_on_the_negative_prompt(backbone, make_inputs):
    """With ``text_encoder.negative_prompt`` set (paper scale: GSFixer's, gsfixer/cogvideo/inference.py l. 320-325),
    the pipeline's unconditional branch is that prompt's encoding (no quality suffix), not the all-zero
    embedding; without one it stays all-zero (the embedded scale)."""
    inputs = make_inputs(batch=2, frames=2)
    latents = (inputs["cond"], inputs["ref_2d"], inputs["ref_3d"], inputs["text"])
    calls, handle = _count_forwards(backbone.transformer)
    zero = RestorationPipeline(backbone).restore_latents(*latents, seed=0, steps=1, guidance_scale=6.0)
    assert not calls[0]["text"][2:].any()
    backbone.cfg.text_encoder.negative_prompt = "Distortion. Watermark present in each frame."
    calls.clear()
    negative = RestorationPipeline(backbone).restore_latents(*latents, seed=0, steps=1, guidance_scale=6.0)
    handle.remove()
    encoded = backbone.text_encoder.encode_prompts(["Distortion. Watermark present in each frame."])[0]
    unconditional = calls[0]["text"][2:]
    assert torch.equal(unconditional, torch.stack([encoded, encoded]))
    assert not torch.equal(encoded, backbone.text_encoder.encode(["Distortion. Watermark present in each frame."])[0])
    assert not torch.allclose(zero, negative)
