"""`tracegs-prepare`: generate scenes and build the paired-clip cache (conf/prepare.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.prepare import prepare

main = hydra_app("prepare")(prepare)

if __name__ == "__main__":
    main()
