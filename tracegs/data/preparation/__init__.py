"""Paired-clip preparation (paper Sec. 4.1 "Training Data"; supplement A.2 and A.4).

For every scene and view set V_b (sparse K = 3, 6, 9 and dense 12, 18, all) a 3DGS is fitted with
snapshots; the student condition R_s comes from the early snapshots (paper 7k / 17k) of the sparse fits,
the teacher condition R_d from the final snapshot (paper 30k). Each clip belongs to one student view count K
(the scene's clips divided evenly among K, ``clip_view_counts``) and follows deployment's rule for K captured
views: its trajectory P is a round of ``round_clips`` on the K-view set, starting and ending at two of its
views. Along P it renders that K's student snapshots, the teacher conditions (dense sets, and the smallest
sparse set's final snapshot: variant B's teacher) and the pseudo-target, which comes from ground truth, the
dense rendering, or a frozen restorer applied to R_d (the paper's choice). Frozen encoders run once here: the
cache holds codec latents, reference tokens and text embeddings (layout: ``cache_keys``), so training never
loads them.

Work units and resumability: one PLY per (scene, view set, snapshot) in ``work_dir`` and one safetensors
shard per (scene, clip) in ``cache_dir``, written after the scene files it indexes; every file is written
atomically, finished units are skipped, and ``force`` redoes them. Runs can be sharded by scene
(``shard_index`` / ``num_shards``); each shard writes its own manifest, and the last to finish joins them all
into the cache's manifest (``merge_manifests``).

Modules, in the order a run uses them: ``plan`` (scenes, view sets and clips to make), ``fits`` (the 3DGS fits),
``renders`` (each clip's conditions along its trajectory), ``encode`` (pseudo-target and frozen encoders),
``shards`` (a clip's files and their validity), ``manifests`` (the cache's index) and ``driver`` (the worker pool and
the run end to end, ``run_prepare``).
"""
