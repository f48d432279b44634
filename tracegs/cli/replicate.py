"""`tracegs-replicate`: Table 3 at the embedded scale over training seeds, with one report (conf/replicate.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.replicate import replicate

main = hydra_app("replicate")(replicate)

if __name__ == "__main__":
    main()
