"""`tracegs-restore`: restore and refine a COLMAP capture of your own from K views (conf/restore.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.restore import restore

main = hydra_app("restore")(restore)

if __name__ == "__main__":
    main()
