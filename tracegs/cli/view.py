"""`tracegs-view <run folder>`: the folder's refined 3DGS, cameras and held-out views in the browser
(tracegs.eval.viewer); prints the URL and serves until Ctrl-C."""

from __future__ import annotations

import argparse
import os
import time

from tracegs.cli.failures import exit_with_one_line
from tracegs.errors import TraceGSError
from tracegs.eval.viewer import serve


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="tracegs-view", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Serves a run folder's refined 3DGS in the browser (viser): each method's splats (3DGS, A,\n"
                    "TRACE-GS), switched in place from the same viewpoint; the captured and held-out cameras with\n"
                    "their images; a held-out view's render beside its ground truth. Prints the URL to open.",
        epilog="Examples:\n"
               "  tracegs-view outputs/embedded/demo/<run>\n"
               "  tracegs-view outputs/embedded/restore/F/<run> --port 8081\n"
               "  tracegs-view outputs/embedded/restore/F/<run> --host 0.0.0.0   # reachable from other machines")
    parser.add_argument("folder", help="a folder tracegs-demo, tracegs-evaluate or tracegs-restore wrote")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (the next free one if taken)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on; 0.0.0.0 serves other machines too (default: this one only)")
    args = parser.parse_args(argv)
    try:
        viewer = serve(args.folder, args.host, args.port)
    except TraceGSError as error:
        if os.environ.get("TRACEGS_TRACEBACK"):
            raise
        exit_with_one_line("view", error)
    print(f"tracegs-view: {args.folder}: {viewer.url} (Ctrl-C stops)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:  # the way a server is stopped, not a failure
        viewer.stop()


if __name__ == "__main__":
    main()
