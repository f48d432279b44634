"""`tracegs-deploy`: restore-refine deployment of the test scenes with one restorer (conf/deploy.yaml)."""

from tracegs.cli.app import hydra_app
from tracegs.pipeline.evaluate import deploy

main = hydra_app("deploy")(deploy)

if __name__ == "__main__":
    main()
