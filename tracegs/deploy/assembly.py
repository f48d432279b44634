"""Assembly of the deployed restorers (Algorithm 1, bottom): variant A and TRACE-GS on ONE frozen backbone.

Variant A is the frozen base theta; TRACE-GS is theta plus the Stage-2 student adapter (main paper Sec. 3.4).
Both are built on the same backbone and the student's LoRA is switched off for variant A (peft's
``disable_adapters`` through ``sampler.using_adapter``), so a paper-scale evaluation holds one 5B transformer,
one VAE and one set of encoders instead of two. A disabled peft LoRA layer returns its base layer's output
unchanged, so each method restores exactly what a backbone built for it alone restores
(tests/deploy/test_assembly.py checks this bitwise).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from tracegs.content import names_and_bytes_digest
from tracegs.data.captions import captioner_dtype
from tracegs.deploy.restorers import DiffusionRestorer
from tracegs.devices import accelerator
from tracegs.products import STAGE2
from tracegs.restorer import adapters
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.memory import Holding, deployment_holdings
from tracegs.restorer.sampler import RestorationPipeline

STUDENT_LABEL = "student"


@dataclass
class AdapterFile:
    """An adapter file to load on the shared backbone; ``field`` is the config field that names it (errors),
    ``label`` its name in the restorer's identity and ``stage`` the training stage that must have written it."""

    path: Path
    field: str
    label: str
    stage: str = STAGE2.value


@dataclass
class RestorerArtifacts:
    """What the deployed restorers are made of: variant A's transformer folder (None = the backbone's own
    ``pretrained_path``) and the Stage-2 student adapter file; ``ablation`` only names the run that writes it."""

    baseline_weights: str | None = None
    student_adapter: str | None = None
    ablation: str = "<variant>"


def shared_restorers(cfg: BackboneConfig, baseline_weights: str | None, adapter_files: dict[str, AdapterFile | None],
                     batch: int, steps: int | None = None,
                     device: torch.device | str | None = None) -> dict[str, DiffusionRestorer]:
    """Name -> restorer on ONE frozen backbone: each name's adapter file is loaded under that name (None = the
    bare base, adapters switched off). Files are checked by the caller."""
    if baseline_weights is not None:
        if not Path(baseline_weights).is_dir():
            raise FileNotFoundError(f"artifacts.baseline_weights: no baseline restorer at {baseline_weights} "
                                    "(run tracegs-train stage=baseline)")
        cfg = replace(cfg, transformer=replace(cfg.transformer, pretrained_path=baseline_weights))
    base = cfg.transformer.pretrained_path
    identity = f"base={names_and_bytes_digest(base)}" if base else "base=random-init"
    backbone = build_backbone(cfg, device=device or accelerator())
    restorers = {}
    for name, file in adapter_files.items():
        if file is not None:
            adapters.load_adapter(backbone.transformer, name, file.path, trainable=False, expected=cfg.lora,
                                  field=file.field, stage=file.stage)
        restorers[name] = DiffusionRestorer(
            RestorationPipeline(backbone, adapter=None if file is None else name), batch=batch,
            identity=identity if file is None else f"{identity} {file.label}={names_and_bytes_digest(file.path)}", steps=steps)
    return restorers


def build_restorers(cfg: BackboneConfig, artifacts: RestorerArtifacts, methods: Sequence[str],
                    batch: int, steps: int | None = None, device: torch.device | str | None = None) -> dict:
    """Method name -> restorer (None = plain 3DGS, no restoration): variant A (``baseline``, the bare base) and
    TRACE-GS (``tracegs``, base + student adapter) share one backbone."""
    files: dict[str, AdapterFile | None] = {}
    for method in methods:
        if method == "baseline":
            files[method] = None
        elif method == "tracegs":
            student = Path(str(artifacts.student_adapter))
            if artifacts.student_adapter is None or not student.exists():
                raise FileNotFoundError(
                    f"artifacts.student_adapter: no student adapter at {artifacts.student_adapter} "
                    f"(run tracegs-train stage=stage2 ablation={artifacts.ablation} with the same settings)")
            files[method] = AdapterFile(student, "artifacts.student_adapter", STUDENT_LABEL)
    restorers = shared_restorers(cfg, artifacts.baseline_weights, files, batch, steps, device) if files else {}
    return {m: restorers.get(m) for m in methods}


def restorer_holdings(cfg: BackboneConfig, methods: Sequence[str], captioner: str | None,
                      device: str | None = None) -> list[Holding]:
    """What ``build_restorers(cfg, ..., methods)`` and the run's captioner will hold on each device, counted on
    the meta device before anything is loaded (restorer/memory.py): the diffusion methods share one backbone,
    so the base, the VAE and the encoders appear once and each adapter is one more LoRA on the base."""
    if all(m == "3dgs" for m in methods):
        return []
    device = device or accelerator()
    return deployment_holdings(cfg, [STUDENT_LABEL] if "tracegs" in methods else [],
                               None if captioner is None else (captioner, captioner_dtype(device)), device)
