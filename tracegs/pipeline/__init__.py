"""The glue above the engines: what each console script does with its composed config, and the pipeline's
steps (prepare -> A -> Stage 1 -> Stage 2 -> evaluate -> report) declared once for the demo and tracegs-replicate.

A command's module here bears its console script's name, as its entry point in :mod:`tracegs.cli` does
(``tracegs.cli.prepare`` composes and calls ``tracegs.pipeline.prepare``); the other modules are what those share
(the upstream lookup, run records, variants, the steps and their runner).

Layering: :mod:`tracegs.cli` imports this package; this package imports the engines (``splat``, ``restorer``,
``data``, ``training``, ``deploy``, ``eval``) and ``config``; nothing below imports upward.
"""
