"""Task families, and what each scores an episode by.

A task's family comes from its id: `runner` for the Learning to Run runner (`l2r/Run-v0` and
`l2r/RunOpenSim-v0`), `pixels` for the camera tasks of `l2r.control` (`l2r/dmc-cartpole-swingup-v0`:
the DeepMind Control suite seen through 84 × 84 frames), `standard` for any other gymnasium task
(Hopper-v5, Walker2d-v5), `photo` for the photo-finishing tasks of `l2r.photo` (`l2r/PhotoTune-v0`,
`l2r/PhotoEnhance-v0`).
The family picks the
recipe a job trains with (l2r.recipes) and its score: what `l2r up` keeps `learner/best.pt` by and
names the best evaluation episode by, and what the status line, the final report, summary.json,
the evaluators' log and `l2r eval` speak of.

This module imports nothing of the daemons', so each of them and every command can ask it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RUNNER, PIXELS, PHOTO, STANDARD = "runner", "pixels", "photo", "standard"
FAMILIES = (RUNNER, PIXELS, PHOTO, STANDARD)


RUNNER_IDS = "l2r/Run"  # the prefix of the runner's ids (l2r.sim's PORT_ID and OPENSIM_ID), no other l2r/ task's
CAMERA_IDS = "l2r/dmc-"  # the prefix of l2r.control's ids
PHOTO_IDS = "l2r/Photo"  # the prefix of l2r.photo's ids


def family_of(env_id: str) -> str:
    for prefix, family in ((RUNNER_IDS, RUNNER), (CAMERA_IDS, PIXELS), (PHOTO_IDS, PHOTO)):
        if env_id.startswith(prefix):
            return family
    return STANDARD


@dataclass(frozen=True)
class Score:
    """What a family's episodes are judged by: the higher, the better."""

    name: str
    """Its name in words and in files: its column of episodes.csv and evaluation.csv, the status
    figures `eval_<name>` and `best_eval_<name>`, `mean_<name>` in best.pt's evaluation."""
    unit: str
    """Printed after a value ("m"); "" for a plain number."""
    field: str
    """The EpisodeSummary field that holds it."""

    def of(self, episode) -> float:
        """This score of an EpisodeSummary (or anything with its field); NaN where the field is
        unset (an episode summary from an actor older than the field)."""
        value = getattr(episode, self.field)
        return math.nan if value is None else float(value)

    def shown(self, value: float | None, spec: str = ".2f") -> str:
        """'12.34 m', '3012.50'; '-' for no value."""
        return "-" if value is None else format(value, spec) + (f" {self.unit}" if self.unit else "")

    def text(self, value: float | None, spec: str = ".2f") -> str:
        """'distance 12.34 m', 'return 3012.50'."""
        return f"{self.name} {self.shown(value, spec)}"


SCORES = {
    RUNNER: Score("distance", "m", "distance"),  # how far the pelvis went
    STANDARD: Score("return", "", "episode_return"),  # the sum of the task's own rewards
    PIXELS: Score("return", "", "episode_return"),  # the suite's rewards, as DrQ-v2 reports them
    PHOTO: Score("psnr", "dB", "psnr_db"),  # the last image's PSNR to its goal, as RLPixTuner reports its tuner
}


def score_of(env_id: str) -> Score:
    """The score of the family of `env_id`."""
    return SCORES[family_of(env_id)]
