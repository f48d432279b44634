"""The Hydra config tree, installed as the package ``tracegs.conf`` (see pyproject.toml).

This file only makes the folder importable, so ``importlib.resources`` (and with it Hydra's search path)
finds the YAML files both in an editable install and in a wheel.
"""
