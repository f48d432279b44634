"""`tracegs-restore`: restore and refine a COLMAP capture of your own from K views (conf/restore.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("restore")(tasks.restore)

if __name__ == "__main__":
    main()
