"""`tracegs-train`: train one stage: baseline (A), Stage 1 or Stage 2 (conf/train.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.train import train_and_validate

# The job returns the validation metric (None without a held-out cache), which a Hydra sweeper such as Optuna's
# maximises (conf/hparams_search/).
main = hydra_app("train")(train_and_validate)

if __name__ == "__main__":
    main()
