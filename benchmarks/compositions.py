"""How many times each command composes and validates its config: the cost of finding the products it builds on.

A command composes its own config (the command-line check before Hydra writes anything, then Hydra's own); an
earlier product it looks up is a projection of that config (tracegs.pipeline.upstream), which composes only the
declaration of a variant whose sections it needs (the default variant's for A and Stage 1), once per process.
The demo's steps are composed in its process, once each. This script makes the smallest demo in a temporary root
(about half a minute on two cores), then runs each command again on that finished root, in this process through
its console entry point, counting Hydra's compositions (``ConfigLoaderImpl.load_configuration``) and the
cross-field validations (``tracegs.config.validate.validate``). Every command finds its product finished, so the
counts are those of a lookup, not of the training.

Last line: JSON ``{"compositions": {command: n}, "validations": {command: n}}``.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import io
import json
import subprocess
import sys
import tempfile
from collections import Counter
from importlib import import_module
from pathlib import Path
from unittest import mock

REPOSITORY = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPOSITORY / "tests"))

from support.tasks import SMALLEST  # noqa: E402

COMMANDS = {
    "tracegs-train stage=baseline": ("train", ["stage=baseline"]),
    "tracegs-train stage=stage1": ("train", ["stage=stage1"]),
    "tracegs-train stage=stage2": ("train", ["stage=stage2"]),
    "tracegs-evaluate (the demo's held-out split)": ("evaluate", ["data.prepare.split=test"]),
    "tracegs-demo": ("demo", []),
}
COUNTS_MARK = "COUNTS "


def count_one(app: str, argv: list[str]) -> None:
    """Run ``tracegs-<app> <argv>`` through its entry point in this (fresh) process with both functions wrapped
    before any project module imports them; print the counts on exit."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    import tracegs.config.validate as validation

    counts: Counter = Counter()
    compose, validate = ConfigLoaderImpl.load_configuration, validation.validate

    def counted_compose(self, *args, **kwargs):
        counts["compositions"] += 1
        return compose(self, *args, **kwargs)

    def counted_validate(*args, **kwargs):
        counts["validations"] += 1
        return validate(*args, **kwargs)

    ConfigLoaderImpl.load_configuration = counted_compose
    validation.validate = counted_validate
    atexit.register(lambda: print(COUNTS_MARK + json.dumps(counts), file=sys.stderr, flush=True))
    main = import_module(f"tracegs.cli.{app}").main
    with mock.patch.object(sys, "argv", [f"tracegs-{app}", *argv]), contextlib.redirect_stdout(io.StringIO()):
        main()


def counted(app: str, argv: list[str]) -> Counter:
    """The counts of one command, run in a child process."""
    result = subprocess.run([sys.executable, __file__, "--count", app, *argv], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"tracegs-{app} {' '.join(argv)} failed: {result.stderr[-2000:]}")
    (line,) = [line for line in result.stderr.splitlines() if line.startswith(COUNTS_MARK)]
    return Counter(json.loads(line.removeprefix(COUNTS_MARK)))


def main(args: list[str] | None = None) -> dict:
    args = sys.argv[1:] if args is None else args
    if args[:1] == ["--count"]:
        count_one(args[1], args[2:])
        return {}
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, help="a root holding the smallest demo (default: make one)")
    options = parser.parse_args(args)
    with tempfile.TemporaryDirectory() as scratch:
        root = options.root or Path(scratch)
        common = [f"paths.root_dir={root}", *SMALLEST]
        if options.root is None:
            print(f"making the smallest demo in {root} ...", flush=True)
            subprocess.run([str(Path(sys.executable).with_name("tracegs-demo")), *common], cwd=root,
                           capture_output=True, check=True)
        figures: dict[str, dict[str, int]] = {"compositions": {}, "validations": {}}
        for label, (app, extra) in COMMANDS.items():
            counts = counted(app, [*common, *extra])
            for kind in figures:
                figures[kind][label] = counts[kind]
            print(f"{label}: {counts['compositions']} compositions, {counts['validations']} validations", flush=True)
    print(json.dumps(figures))
    return figures


if __name__ == "__main__":
    main()
