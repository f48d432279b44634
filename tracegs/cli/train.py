"""`tracegs-train`: train one stage: baseline (A), Stage 1 or Stage 2 (conf/train.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("train")(tasks.train)

if __name__ == "__main__":
    main()
