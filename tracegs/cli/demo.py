"""`tracegs-demo`: the whole pipeline on the embedded default, ending with the results table (conf/demo.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.demo import demo

main = hydra_app("demo")(demo)

if __name__ == "__main__":
    main()
