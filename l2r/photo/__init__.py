"""Photo finishing as a reinforcement-learning task.

Importing this package registers `l2r/PhotoTune-v0` (l2r.photo.env): a goal-conditioned tuner of
the nine parameters of RLPixTuner's photo-finishing pipeline (l2r.photo.pipeline), on the
photographs that ship in installed wheels (l2r.photo.photos). The photos load at an env's first
reset, so reading its spaces costs nothing:

    import gymnasium, l2r.photo
    env = gymnasium.make("l2r/PhotoTune-v0")              # the training photos
    env = gymnasium.make("l2r/PhotoTune-v0", split="test")  # the held-out ones

and `l2r/PhotoTuneStats-v0`, the same task observed through statistics of both images alone (no
images), which a small MLP learns from on a CPU, and `l2r/PhotoTuneCompare-v0`, those statistics
and a comparison of the two images pixel for pixel (`comparison_features`), and
`l2r/PhotoTuneCompareDetail-v0`, that comparison and the two working images' fine detail compared
(`detail_features`: sharpening shows there alone). `l2r/PhotoEnhance-v0` and
`l2r/PhotoEnhanceStats-v0` (l2r.photo.env.PhotoEnhanceEnv) are the enhancer's task: a crop degraded
by hidden random edits is to be brought back to its original, which the observation does not show.
"""

import gymnasium

TUNE_ID = "l2r/PhotoTune-v0"
TUNE_STATS_ID = "l2r/PhotoTuneStats-v0"
TUNE_COMPARE_ID = "l2r/PhotoTuneCompare-v0"
TUNE_DETAIL_ID = "l2r/PhotoTuneCompareDetail-v0"
TUNE_IDS = (TUNE_ID, TUNE_STATS_ID, TUNE_COMPARE_ID, TUNE_DETAIL_ID)
ENHANCE_ID = "l2r/PhotoEnhance-v0"
ENHANCE_STATS_ID = "l2r/PhotoEnhanceStats-v0"
ENHANCE_IDS = (ENHANCE_ID, ENHANCE_STATS_ID)

# The envs end their episodes themselves (10 queries, or a collapsed image), so no max_episode_steps.
gymnasium.register(id=TUNE_ID, entry_point="l2r.photo.env:PhotoTuneEnv")
gymnasium.register(id=TUNE_STATS_ID, entry_point="l2r.photo.env:PhotoTuneEnv", kwargs={"view": "statistics"})
gymnasium.register(id=TUNE_COMPARE_ID, entry_point="l2r.photo.env:PhotoTuneEnv", kwargs={"view": "comparison"})
gymnasium.register(id=TUNE_DETAIL_ID, entry_point="l2r.photo.env:PhotoTuneEnv",
                   kwargs={"view": "comparison", "detail": True})
gymnasium.register(id=ENHANCE_ID, entry_point="l2r.photo.env:PhotoEnhanceEnv")
gymnasium.register(id=ENHANCE_STATS_ID, entry_point="l2r.photo.env:PhotoEnhanceEnv", kwargs={"view": "statistics"})
