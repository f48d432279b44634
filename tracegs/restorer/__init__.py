"""Reference-guided video restorer: transformer, LoRA adapters, codecs, encoders, schedules, sampler."""
