"""Task families, and what each scores an episode by.

A task's family comes from its id: `runner` for the Learning to Run runner (`l2r/Run-v0` and
`l2r/RunOpenSim-v0`), `standard` for any other gymnasium task (Hopper-v5, Walker2d-v5; the camera
tasks of `l2r.control` score by return too). The family picks the
recipe a job trains with (l2r.recipes) and its score: what `l2r up` keeps `learner/best.pt` by and
names the best evaluation episode by, and what the status line, the final report, summary.json,
the evaluators' log and `l2r eval` speak of.

This module imports nothing of the daemons', so each of them and every command can ask it.
"""

from __future__ import annotations

from dataclasses import dataclass

RUNNER, STANDARD = "runner", "standard"
FAMILIES = (RUNNER, STANDARD)


RUNNER_IDS = "l2r/Run"  # the prefix of the runner's ids (l2r.sim's PORT_ID and OPENSIM_ID), no other l2r/ task's


def family_of(env_id: str) -> str:
    return RUNNER if env_id.startswith(RUNNER_IDS) else STANDARD


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
        """This score of an EpisodeSummary."""
        return float(getattr(episode, self.field))

    def shown(self, value: float | None, spec: str = ".2f") -> str:
        """'12.34 m', '3012.50'; '-' for no value."""
        return "-" if value is None else format(value, spec) + (f" {self.unit}" if self.unit else "")

    def text(self, value: float | None, spec: str = ".2f") -> str:
        """'distance 12.34 m', 'return 3012.50'."""
        return f"{self.name} {self.shown(value, spec)}"


SCORES = {
    RUNNER: Score("distance", "m", "distance"),  # how far the pelvis went
    STANDARD: Score("return", "", "episode_return"),  # the sum of the task's own rewards
    # Photo tasks will score by PSNR in dB, once their episode summaries carry it.
}


def score_of(env_id: str) -> Score:
    """The score of the family of `env_id`."""
    return SCORES[family_of(env_id)]
