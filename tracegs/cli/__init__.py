"""Thin Hydra entry points: one module per console script (pyproject.toml's ``[project.scripts]``), named as its
command (``tracegs-<command>``: ``tracegs.cli.<command>:main``). Each composes its config and hands it to the
pipeline module of the same name (``tracegs.pipeline.<command>``), which does the work and is called the same way
from Python and by the runner of the demo's and tracegs-replicate's steps: the names repeat on purpose, one pair
per command. tracegs-deploy runs the first half of an evaluation (``tracegs.pipeline.evaluate``); tracegs-view and
tracegs-weights call their engines directly. The other modules (``app``, ``failures``, ``multirun``,
``precheck``, ``relaunch``) are what the entry points share.
"""
