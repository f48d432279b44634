"""The transformer's execution switches (tracegs.restorer.speed, adapters.set_lora_compute) at the embedded size on
the CPU: each computes what the model computes without it (exactly, or within bf16's rounding for bf16 LoRA), and
each demonstrably acts (blocks recomputed, blocks compiled, kernels recorded, factors multiplied in bf16)."""

from __future__ import annotations

import pytest
import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

from tracegs.errors import ConfigError
from tracegs.restorer import adapters, speed
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig, LoraConfig, TransformerConfig

# bf16 keeps 8 significant bits (relative rounding 2^-8 = 0.39% per operation): the adapters' contribution computed
# in bf16 is allowed 2% of its size (about five roundings); measured 0.46% for outputs, 0.56% for gradients.
BF16_SHARE = 0.02


@pytest.fixture
def student(backbone, make_inputs):
    """(the embedded transformer in train mode with a random trainable adapter, its inputs, a forward + backward
    returning the outputs and the adapter's gradients)."""
    model, inputs = backbone.transformer, make_inputs(batch=1, frames=2)
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    with torch.no_grad():
        for param in adapters.adapter_parameters(model, "student"):
            param.normal_(std=0.05)
    model.train()

    def run(autocast: bool = False):
        for param in model.parameters():
            param.grad = None
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            out = model(**inputs, return_retrieval=True)
            (out.velocity.float().square().mean() + out.retrieval.float().square().mean()).backward()
        grads = [p.grad.clone() for p in adapters.adapter_parameters(model, "student")]
        return out.velocity.detach(), out.retrieval.detach(), grads

    return model, inputs, run


def assert_same(first, second) -> None:
    (velocity, retrieval, grads), (velocity2, retrieval2, grads2) = first, second
    assert torch.equal(velocity, velocity2) and torch.equal(retrieval, retrieval2)
    assert len(grads) == len(grads2) and all(torch.equal(a, b) for a, b in zip(grads, grads2))


@pytest.mark.parametrize(("share", "wrapped"), [(0.5, 1), (1.0, 2)])
def test_checkpointing_a_share_of_the_blocks_recomputes_them_and_changes_nothing(student, share, wrapped):
    model, _, run = student
    plain = run()
    calls = [0] * len(model.transformer_blocks)
    for index, block in enumerate(model.transformer_blocks):
        block.register_forward_pre_hook(lambda module, args, index=index: calls.__setitem__(index, calls[index] + 1))
    assert speed.checkpoint_blocks(model, share) == wrapped
    assert_same(run(), plain)
    # a wrapped block runs its forward again in backward; the others once
    assert calls == [2] * wrapped + [1] * (len(calls) - wrapped)
    assert speed.checkpoint_blocks(model, 0.0) == 0 and not model.gradient_checkpointing


def test_compiled_blocks_give_the_same_outputs_and_gradients(student):
    model, _, run = student
    plain = run()
    graphs = []

    def counting_eager(graph, example_inputs):  # torch.compile's "eager" backend, counting what it is handed
        graphs.append(graph)
        return graph.forward

    torch._dynamo.reset()
    speed.compile_blocks(model, counting_eager)
    with speed.AttentionKernels() as recorder:  # the first training step's kernel check, around compiled blocks
        assert_same(run(), plain)
    assert graphs  # dynamo traced the blocks; the backend ran what it traced
    assert recorder.counts["flash"] == 2 * len(model.transformer_blocks)
    speed.checkpoint_blocks(model, 1.0)  # compiled blocks under checkpointing: still the same
    assert_same(run(), plain)


def test_the_attention_kernels_are_recorded_and_an_unfused_one_is_refused_when_required(backbone, make_inputs):
    model, inputs = backbone.transformer, make_inputs(batch=1, frames=2)
    with torch.no_grad(), speed.AttentionKernels() as recorder:
        model(**inputs)
    blocks = len(model.transformer_blocks)
    # PyTorch's fused CPU kernel takes float32 without a mask: each block's self- and reference attention
    assert dict(recorder.counts) == {"flash": 2 * blocks}
    assert recorder.summary() == f"attention (SDPA) kernels: flash x{2 * blocks} (fused)"
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), speed.AttentionKernels() as unfused:
        model(**inputs)
    assert dict(unfused.counts) == {"math": 2 * blocks} and "NOT all fused" in unfused.summary()
    with pytest.raises(ConfigError, match=r"^config field 'backbone.transformer.require_fused_attention': "
                                          r"attention would run on PyTorch's math kernel on cpu \(float32, head dim 32\)"):
        with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), speed.AttentionKernels(require_fused=True) as refusing:
            model(**inputs)
    assert dict(refusing.counts) == {"math": 1}  # refused at the first call, before it ran


def test_bf16_lora_keeps_float32_masters_and_computes_within_bf16_rounding(student):
    model, inputs, run = student
    velocity, retrieval, grads = run()
    names = list(model.state_dict())
    adapters.set_lora_compute(model, True)
    assert list(model.state_dict()) == names  # what is saved and loaded is the same
    velocity16, retrieval16, grads16 = run()
    assert all(p.dtype == torch.float32 for p in adapters.adapter_parameters(model, "student"))
    assert all(g.dtype == torch.float32 for g in grads16)
    assert not torch.equal(velocity16, velocity)  # the products are bf16's
    model.disable_adapters()
    with torch.no_grad():
        base = model(**inputs).velocity
    model.enable_adapters()
    contribution = (velocity - base).abs().max()
    assert (velocity16 - velocity).abs().max() <= BF16_SHARE * contribution
    assert (retrieval16 - retrieval).abs().max() <= BF16_SHARE * retrieval.abs().max()
    for grad16, grad in zip(grads16, grads):
        assert (grad16 - grad).norm() <= BF16_SHARE * grad.norm()
    # an adapter added afterwards (Stage 2's clone of the student) computes in bf16 too
    adapters.clone_adapter(model, "student", "teacher", trainable=False)
    teacher = [m for n, m in model.named_modules() if n.endswith((".lora_A.teacher", ".lora_B.teacher"))]
    assert teacher and all(type(m) is adapters.Bf16Factor for m in teacher)


def test_bf16_lora_under_bf16_autocast_is_exactly_what_peft_computes(student):
    """trainer.precision=bf16-mixed: peft's float32 copy of each input is cast back to bf16 by autocast anyway."""
    model, _, run = student
    autocast = run(autocast=True)
    adapters.set_lora_compute(model, True)
    assert_same(run(autocast=True), autocast)


def test_build_backbone_applies_the_configured_switches():
    torch.manual_seed(0)
    cfg = BackboneConfig(transformer=TransformerConfig(activation_checkpointing=0.5, compile_blocks=True,
                                                       compile_backend="eager"),
                         lora=LoraConfig(compute_bf16=True))
    model = build_backbone(cfg).transformer
    assert model.gradient_checkpointing
    assert all(block._compiled_call_impl is not None for block in model.transformer_blocks)
    adapters.add_adapter(model, "aligned", cfg.lora)
    assert {type(m) for n, m in model.named_modules() if ".lora_B.aligned" in n} == {adapters.Bf16Factor}


def test_an_unknown_compile_backend_is_refused_in_one_line(backbone):
    with pytest.raises(ConfigError, match=r"^config field 'backbone.transformer.compile_backend': 'nonesuch' is not a "
                                          r"torch.compile backend here \(have .*inductor"):
        speed.compile_blocks(backbone.transformer, "nonesuch")
    assert all(block._compiled_call_impl is None for block in backbone.transformer.transformer_blocks)
