"""`tracegs-prepare`: generate scenes and build the paired-clip cache (conf/prepare.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("prepare")(tasks.prepare)

if __name__ == "__main__":
    main()
