"""The ``template`` captioner (ORACLE track): captions written from a generated scene's semantic states.

Stands in for the MLLM so that the time-varying field can be measured apart from caption quality.
For a tracked object (a truth ``whole`` id, :func:`methods.captioners.tracks.truth_tracks`) at a
training frame:

* if the object, or one of its parts, has a state timeline, the caption is one of that state's
  paraphrases (the generator's truth lists several per state), drawn per frame with a seeded
  generator, as an MLLM words the same state differently from frame to frame; several stateful
  parts are joined with ``"; "``;
* otherwise the caption is the object's name, the same in every frame (its semantics never change).

``noise`` names a level of :mod:`benchmark.core.caption_noise` (``clean``: the state's paraphrases as above;
``mllm``: also a stated share of captions of another state, and captions that lag the change); ``"scene"``
(default) takes the level the scene declares (``caption_noise`` in its truth: the synthetic presets with time
queries declare ``mllm``; a scene that declares none, ``clean``). A lagged or wrong state is one the object
shows at a training time, so the noise too is derived from the training frames' states only.

Only the truth of TRAINING frames is read (``SceneTruth.state_at`` refuses other time indices).
Images are not looked at, so the visual and text prompts change nothing here: on the oracle track
the prompt ablation measures the caption and text-encoder path only.
"""

from __future__ import annotations

import zlib
from typing import Any, Optional, Sequence

import numpy as np

from benchmark.core.caption_noise import DEFAULT_CAPTION_NOISE, CaptionNoise, caption_noise, split_lag, with_extra_lag
from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Captioner
from .tracks import whole_of


class TemplateCaptioner(Captioner):
    name = "template"
    track = "oracle"
    uses_images = False

    def __init__(self, scene: Scene, *, seed: int = 0, paraphrases: bool = True, noise: str = "scene") -> None:
        """
        Args:
            seed: seed of the per-frame paraphrase draw (and of the noise draws).
            paraphrases: draw one of the state's paraphrases per frame (True) or always use the first.
            noise: caption noise level (:data:`benchmark.core.caption_noise.CAPTION_NOISE`), or ``"scene"``:
                the level the scene's truth declares; either may carry an extra lag (``scene+lag:0.1``).
        """
        from methods.supervision.truth_access import open_truth

        self.truth = open_truth(scene)
        self.scene_name = scene.name
        self.seed = int(seed)
        self.paraphrases = bool(paraphrases)
        self.noise = self._noise_level(noise)
        self._stateful = self._stateful_by_whole()
        self._train_times = sorted({f.time_index for f in scene.train_frames})
        self._lag = self.noise.lag_steps(self.truth.num_frames)
        self._shown: dict[str, list[dict]] = {}  # node -> the states its training frames show

    def _noise_level(self, noise: str) -> CaptionNoise:
        base, extra = split_lag(noise, field="captions.noise")
        if base == "scene":  # the declared level, with any extra lag asked for (scene+lag:0.1)
            declared = self.truth.doc.get("caption_noise", DEFAULT_CAPTION_NOISE)
            return with_extra_lag(caption_noise(declared, where=self.truth.root, field="caption_noise"), extra,
                                  field="captions.noise")
        return caption_noise(noise, field="captions.noise")

    def config(self) -> dict[str, Any]:
        out = {"name": self.name, "seed": self.seed, "paraphrases": self.paraphrases,
               "generator_version": self.truth.generator_version}
        if not self.noise.is_clean:  # only when noisy: clean captions keep their cache keys
            out["noise"] = self.noise.describe()
        return out

    def _stateful_by_whole(self) -> dict[int, list[str]]:
        """Whole id -> names of the stateful nodes inside it (itself or its parts), in truth order."""
        out: dict[int, list[str]] = {}
        for name in self.truth.stateful_objects:
            level, ids = self.truth.ids_named(name)
            for id_ in ids:
                whole = whole_of(self.truth, level, id_)
                if name not in out.setdefault(whole, []):
                    out[whole].append(name)
        return out

    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        # What the object is; its course of states would reveal evaluated times, so it is not told.
        return self._name(obj)

    def _name(self, obj: int) -> str:
        if int(obj) not in self.truth.catalogue["whole"]:
            raise InputError(None, "template captioner", f"object {obj} is no whole-level object of the truth "
                             f"of {self.scene_name!r}: the template captioner needs truth tracks")
        return self.truth.name("whole", int(obj)) or f"object {obj}"

    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        if frame.split != "train":
            from methods.supervision.truth_access import EVAL_TRUTH_MESSAGE, EvaluatedFrameTruthError

            raise EvaluatedFrameTruthError(f"frame {frame.name!r} is a {frame.split} frame: {EVAL_TRUTH_MESSAGE}")
        name = self._name(obj)
        stateful = self._stateful.get(int(obj), [])
        if not stateful:
            return name
        rng = np.random.default_rng([self.seed, zlib.crc32(frame.name.encode()), int(obj)])
        # the noise draws have a stream of their own: clean captions are the paraphrases drawn as before
        noise_rng = np.random.default_rng([self.seed, zlib.crc32(frame.name.encode()), int(obj), 1])
        parts = []
        for node in stateful:
            options = self.described_state(node, frame.time_index, noise_rng)["captions"]
            parts.append(options[int(rng.integers(len(options)))] if self.paraphrases else options[0])
        return "; ".join(parts)

    def lagged_time(self, time_index: int) -> int:
        """The training time whose state a caption at training time ``time_index`` describes: the latest
        training time at or before ``time_index - lag`` (the first training time when there is none)."""
        k = int(np.searchsorted(self._train_times, int(time_index) - self._lag, side="right")) - 1
        return self._train_times[max(k, 0)]

    def shown_states(self, node: str) -> list[dict]:
        """The distinct states (``SceneTruth.state_at`` entries) ``node`` shows at the training times, in order
        of first appearance."""
        if node not in self._shown:
            seen: dict[str, dict] = {}
            for t in self._train_times:
                state = self.truth.state_at(node, t)
                seen.setdefault(state["state"], state)
            self._shown[node] = list(seen.values())
        return self._shown[node]

    def described_state(self, node: str, time_index: int, rng: np.random.Generator) -> dict:
        """The state a caption of ``node`` at training time ``time_index`` describes under the noise level:
        the state at the lagged training time, replaced with probability ``wrong_state_rate`` by another
        state the training frames show (``rng`` draws; none when the level is clean)."""
        if self.noise.is_clean:
            return self.truth.state_at(node, time_index)
        state = self.truth.state_at(node, self.lagged_time(time_index))
        wrong = rng.random() < self.noise.wrong_state_rate
        others = [s for s in self.shown_states(node) if s["state"] != state["state"]]
        if wrong and others:
            state = others[int(rng.integers(len(others)))]
        return state
