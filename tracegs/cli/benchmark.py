"""`tracegs-benchmark`: the embedded benchmark over training seeds, ending with one report (conf/benchmark.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.benchmark import benchmark

main = hydra_app("benchmark")(benchmark)

if __name__ == "__main__":
    main()
