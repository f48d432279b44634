"""The glue above the engines: what each console script does with its composed config, and the pipeline's
steps (prepare -> A -> Stage 1 -> Stage 2 -> evaluate -> report) declared once for the demo and tracegs-replicate.

Layering: :mod:`tracegs.cli` imports this package; this package imports the engines (``splat``, ``restorer``,
``data``, ``training``, ``deploy``, ``eval``) and ``config``; nothing below imports upward.
"""
