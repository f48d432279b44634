"""`tracegs-report`: merge evaluation or prepare shards, or build Table 3 from an ablation sweep (conf/report.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("report")(tasks.report)

if __name__ == "__main__":
    main()
