"""What a cluster week needs before its first job: the released weights fetched and verified, and each SLURM job
sized, timed and requeued from measured figures."""
