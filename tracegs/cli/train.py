"""`tracegs-train`: train one stage: baseline (A), Stage 1 or Stage 2 (conf/train.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.train import train

main = hydra_app("train")(train)

if __name__ == "__main__":
    main()
