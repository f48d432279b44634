"""Helpers that more than one test module uses, imported as ``support.<module>``.

tests/ is on sys.path (pytest puts the root conftest's folder there), so a test anywhere below it writes
``from support.scenes import random_scene``. A test module never imports another test module or a conftest:
conftests hold fixtures, which may call these helpers.
"""
