"""Reference-guided video restorer (supplement A.1-A.3), one code path for both scales.

- ``config``: dataclasses (embedded defaults; the paper's CogVideoX-5B-I2V values: conf/backbone/cogvideox5b.yaml).
- ``transformer.ReferenceGuidedTransformer``: diffusers CogVideoX + reference cross-attention, retrieval read-out.
- ``adapters``: named peft LoRA adapters (teacher / student) on one frozen base.
- ``codec``: ``EmbeddedCodec`` (block DCT) and ``CogVideoXCodec`` (AutoencoderKLCogVideoX).
- ``encoders``: reference (embedded / DINOv2 + VGGT) and text (embedded / T5) encoders.
- ``schedules``: ``RectifiedFlowSchedule`` and ``VPredictionDDIMSchedule`` behind ``NoiseSchedule``.
- ``sampler``: ``sample`` and ``RestorationPipeline``; ``build``: ``build_backbone`` and loaders.

Submodules are imported explicitly so that ``tracegs.restorer.config`` stays free of heavy imports.
"""
