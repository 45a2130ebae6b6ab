"""The benchmark's official scenes: the only scenes its ranked tables hold.

A results folder may hold runs on any scene a user evaluated (a smoke test, a scene of their own, a
preset generated into a folder of another name); the leaderboard shows those in an unranked section, so
that a user's run never changes a ranked mean or a method's scene count.

Official are the seven synthetic presets modelled on the paper's scenes (at the committed generator's
version: a run on another version is left out of every table, :func:`benchmark.results.comparable_runs`)
and the four D-NeRF scenes with committed annotation files (``annotations/scenes/dnerf/``). A test checks
that each synthetic name is a registered preset and each D-NeRF name has its annotation file.
"""

from __future__ import annotations

from typing import Optional

OFFICIAL_SCENES: dict[str, tuple[str, ...]] = {
    "synthetic": ("americano", "chickchicken", "cook-spinach", "espresso", "keyboard", "split-cookie",
                  "torchocolate"),
    "dnerf": ("bouncingballs", "jumpingjacks", "lego", "standup"),
}
"""Dataset (as results files file it) -> its official scenes."""

GENERATED_DATASET = "synthetic"
"""The dataset of generated scenes: there a scene is official only when generated from the preset of its
name (a folder named after a preset but made from another is not that preset)."""


def is_official(dataset: str, scene: str, generated_preset: Optional[str] = None) -> bool:
    """Whether a run on ``scene`` of ``dataset`` belongs in the ranked tables. ``generated_preset``: the
    preset a generated scene was made from (a results file's ``scene_info.generated.preset``)."""
    if scene not in OFFICIAL_SCENES.get(dataset, ()):
        return False
    return dataset != GENERATED_DATASET or generated_preset == scene


def official_note(dataset: str, scene: str) -> str:
    """One line for a user whose run is not on an official scene: where its results show."""
    return (f"{dataset}/{scene} is not one of the benchmark's official scenes: `bench4d leaderboard` lists its "
            "results under \"Other scenes (not ranked)\", never in the ranked tables")
