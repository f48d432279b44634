"""`tracegs-report`: merge evaluation shards, or build Table 3 from an ablation sweep (conf/report.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.report import report

main = hydra_app("report")(report)

if __name__ == "__main__":
    main()
