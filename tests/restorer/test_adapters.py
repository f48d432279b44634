import pytest
import torch

from tracegs.errors import InputFileError
from tracegs.io import read_safetensors, save_safetensors_atomic
from tracegs.restorer import adapters


def _randomise(model, name):
    with torch.no_grad():
        for param in adapters.adapter_parameters(model, name):
            param.normal_(std=0.05)


def test_new_adapter_is_identity_and_targets_both_attentions(backbone, make_inputs):
    model, inputs = backbone.transformer, make_inputs()
    with torch.no_grad():
        before = model(**inputs).velocity
        adapters.add_adapter(model, "stage1", backbone.cfg.lora)
        torch.testing.assert_close(model(**inputs).velocity, before)  # B = 0 at init
    wrapped = {n.rsplit(".lora_", 1)[0] for n, _ in model.named_parameters() if ".lora_A.stage1" in n}
    expected = {
        f"transformer_blocks.{i}.{attn}.{proj}"
        for i in range(backbone.cfg.transformer.num_layers)
        for attn in ("attn1", "attn_cross")
        for proj in ("to_q", "to_k", "to_v", "to_out.0")
    }
    assert wrapped == expected
    assert all(not p.requires_grad for n, p in model.named_parameters() if ".lora_" not in n)
    config = model.peft_config["stage1"]
    assert (config.r, config.lora_alpha, config.lora_dropout) == (8, 8, 0.0)


def test_teacher_student_clone_and_student_only_training(backbone, make_inputs):
    model, inputs = backbone.transformer, make_inputs()
    adapters.add_adapter(model, "stage1", backbone.cfg.lora)
    _randomise(model, "stage1")
    adapters.clone_adapter(model, "stage1", "teacher", trainable=False)
    adapters.clone_adapter(model, "stage1", "student", trainable=True)

    with torch.no_grad():
        model.disable_adapters()
        base = model(**inputs).velocity
        model.enable_adapters()
        outputs = {}
        for name in ("teacher", "student"):
            adapters.activate(model, name)
            outputs[name] = model(**inputs, return_retrieval=True)
    assert not torch.allclose(outputs["teacher"].velocity, base, atol=1e-4)  # the adapters matter
    torch.testing.assert_close(outputs["teacher"].velocity, outputs["student"].velocity, rtol=0, atol=0)
    torch.testing.assert_close(outputs["teacher"].retrieval, outputs["student"].retrieval, rtol=0, atol=0)

    # peft's set_adapter would flip these; activate keeps the recorded roles
    adapters.activate(model, "teacher")
    assert not any(p.requires_grad for p in adapters.adapter_parameters(model, "teacher"))
    assert all(p.requires_grad for p in adapters.adapter_parameters(model, "student"))

    snapshot = {n: p.detach().clone() for n, p in model.named_parameters()}
    optimiser = torch.optim.SGD(adapters.adapter_parameters(model, "student"), lr=0.5)
    with torch.no_grad():
        teacher_out = model(**inputs, return_retrieval=True)  # teacher forward, as in Stage 2
    adapters.activate(model, "student")
    student_out = model(**inputs, return_retrieval=True)
    loss = (
        student_out.velocity - teacher_out.velocity - 1.0
    ).square().mean() + student_out.retrieval.square().mean()
    loss.backward()
    optimiser.step()

    changed = {n for n, p in model.named_parameters() if not torch.equal(p, snapshot[n])}
    assert changed and all(".student." in n for n in changed)
    for name, param in model.named_parameters():
        if ".student." not in name:
            assert param.grad is None, name


def test_saved_adapter_loads_back_identically(tmp_path, backbone, make_inputs):
    model, inputs = backbone.transformer, make_inputs()
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    _randomise(model, "student")
    path = tmp_path / "student.safetensors"
    adapters.save_adapter(model, "student", path)
    with torch.no_grad():
        expected = model(**inputs).velocity

    model.delete_adapters("student")
    adapters.load_adapter(model, "restored", path, trainable=False)
    adapters.activate(model, "restored")
    with torch.no_grad():
        torch.testing.assert_close(model(**inputs).velocity, expected, rtol=0, atol=0)
    assert not any(p.requires_grad for p in adapters.adapter_parameters(model, "restored"))

    # diffusers' own loader reads the same file (peft keys + adapter config in the metadata)
    model.load_lora_adapter(str(path), prefix=None, adapter_name="via_diffusers")
    adapters.activate(model, "via_diffusers")
    with torch.no_grad():
        torch.testing.assert_close(model(**inputs).velocity, expected, rtol=0, atol=0)


def test_load_adapter_rejects_mismatched_file(tmp_path, backbone):
    model = backbone.transformer
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    path = tmp_path / "student.safetensors"
    adapters.save_adapter(model, "student", path)
    other = type(backbone.cfg.lora)(rank=8, alpha=8, attention_modules=["attn1"])
    adapters.add_adapter(model, "self_attn_only", other)
    with pytest.raises(adapters.AdapterFileError, match=r"unexpected \[.transformer_blocks.0.attn_cross"):
        adapters.load_adapter(model, "self_attn_only", path, trainable=True)
    with pytest.raises(InputFileError, match="absent.safetensors: no such file"):
        adapters.load_adapter(model, "x", tmp_path / "absent.safetensors", trainable=True)


def test_adapters_on_a_bf16_base_are_fp32_saved_and_loaded_as_fp32(tmp_path, backbone):
    model = backbone.transformer.to(torch.bfloat16)
    adapters.add_adapter(model, "student", backbone.cfg.lora)
    adapters.clone_adapter(model, "student", "teacher", trainable=False)
    for name in ("student", "teacher"):
        assert {p.dtype for p in adapters.adapter_parameters(model, name)} == {torch.float32}
    _randomise(model, "student")
    with torch.no_grad():  # values bf16 cannot hold: a downcast anywhere on the way would change them
        for param in adapters.adapter_parameters(model, "student"):
            param.add_(1e-5)
    expected = {n: p.detach().clone() for n, p in model.named_parameters() if ".student." in n}
    path = tmp_path / "student.safetensors"
    adapters.save_adapter(model, "student", path)
    assert {t.dtype for t in read_safetensors(path, "")[0].values()} == {torch.float32}

    model.delete_adapters("student")
    adapters.load_adapter(model, "student", path, trainable=True)
    for name, param in model.named_parameters():
        if ".student." in name:
            assert param.dtype == torch.float32 and torch.equal(param.detach(), expected[name])

    # a bf16 file (e.g. written by another tool) is upcast exactly into float32 factors
    bf16_path = tmp_path / "bf16.safetensors"
    tensors, metadata = read_safetensors(path, "")
    save_safetensors_atomic({k: v.bfloat16() for k, v in tensors.items()}, bf16_path, metadata=metadata)
    adapters.load_adapter(model, "from_bf16", bf16_path, trainable=False)
    for name, param in model.named_parameters():
        if ".from_bf16." in name:
            original = expected[name.replace(".from_bf16.", ".student.")]
            assert param.dtype == torch.float32 and torch.equal(param.detach(), original.bfloat16().float())
