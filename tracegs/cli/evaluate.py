"""`tracegs-evaluate`: deploy 3DGS / baseline / TRACE-GS at 3, 6, 9 views, write results.json (conf/evaluate.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.evaluate import evaluate

main = hydra_app("evaluate")(evaluate)

if __name__ == "__main__":
    main()
