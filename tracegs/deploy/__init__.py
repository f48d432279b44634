"""Deployment: restore-refine loop and the DeploymentRefinement callback."""
