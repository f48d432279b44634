"""`tracegs-weights`: fetch, list or verify the released models the paper scale reads (tracegs.cluster.weights)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from tracegs.cli.failures import exit_with_one_line
from tracegs.cluster.weights import MANIFEST, check_tree, dry_run, fetch, print_plan, record_manifest
from tracegs.errors import TraceGSError


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="tracegs-weights", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Fetches the released models the paper scale reads (GSFixer, CogVideoX's VAE and T5, DINOv2,\n"
                    "VGGT, BLIP-2, VGG16) into the folders paths.weights_dir expects, records every file's bytes and\n"
                    f"SHA-256 in <weights-dir>/{MANIFEST}, and verifies a tree against it without network.",
        epilog="Examples:\n"
               "  tracegs-weights --dry-run                       # repositories, files and bytes\n"
               "  tracegs-weights --weights-dir /data/weights     # fetch, then record the manifest\n"
               "  tracegs-weights --weights-dir /data/weights --check")
    parser.add_argument("--weights-dir", type=Path, default=Path(os.environ.get("TRACEGS_WEIGHTS", "weights")),
                        help="paths.weights_dir of the runs (default: weights, or $TRACEGS_WEIGHTS)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--dry-run", action="store_true", help="list repositories, files and bytes; fetch nothing")
    mode.add_argument("--check", action="store_true", help="verify the tree against its manifest (no network)")
    mode.add_argument("--record", action="store_true", help="write the manifest of a tree fetched another way")
    parser.add_argument("--offline", action="store_true", help="--dry-run from the declared list only")
    parser.add_argument("--sizes-only", action="store_true", help="--check bytes, not SHA-256 (seconds, not minutes)")
    args = parser.parse_args(argv)
    try:
        if args.dry_run:
            print_plan(dry_run(args.offline))
        elif args.check:
            verified = check_tree(args.weights_dir, args.sizes_only)
            print(f"{args.weights_dir}: {verified['files']} files, {verified['bytes']:,} B match the manifest "
                  f"({verified['verified']})")
        else:
            manifest = record_manifest(args.weights_dir) if args.record else fetch(args.weights_dir)
            print(f"{args.weights_dir / MANIFEST}: {len(manifest['files'])} files recorded")
    except TraceGSError as error:
        exit_with_one_line("weights", error)


if __name__ == "__main__":
    main()
