"""The smallest size of the embedded experiment, for the tests that run its tasks through their console
scripts."""

# Counts only (steps, clips, scenes, iterations, reverse steps): every mode stays the embedded default's.
SMALLEST = (
    "experiment.baseline_steps=1",
    "experiment.stage1_steps=1",
    "experiment.stage2_steps=1",
    "experiment.stage2_warmup_steps=0",
    "experiment.clips_per_scene=1",
    "experiment.batch_size=1",
    "data.synthetic.train_seeds=[0]",
    "data.synthetic.test_seeds=[100]",
    "data.synthetic.val_seeds=[50]",
    "data.prepare.fit.iterations=20",
    "data.prepare.fit.snapshot_iters=[5,10,20]",
    "deploy.total_iters=20",
    "deploy.repair_iters=[5,10,15]",
    "deploy.max_clips_per_round=1",
    "evaluation.views=[3]",
    "backbone.schedule.deploy_steps=5",  # M = the embedded Stage-2 rollout N (a stage's own setting)
)
