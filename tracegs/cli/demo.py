"""`tracegs-demo`: the whole pipeline on the embedded default, ending with the results table (conf/demo.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("demo")(tasks.demo)

if __name__ == "__main__":
    main()
