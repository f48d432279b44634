"""`tracegs-deploy`: restore-refine deployment of the test scenes with one restorer (conf/deploy.yaml)."""

from tracegs import tasks
from tracegs.cli.app import hydra_app

main = hydra_app("deploy")(tasks.deploy)

if __name__ == "__main__":
    main()
