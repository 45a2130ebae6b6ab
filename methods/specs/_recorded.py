"""Reading a method config back from a record: a results file's ``method_config``, a fit's saved config.

Records hold a config in its nested form (``{"autoencoder": {"latent_dim": 3}, ...}``); records written
before the options were grouped hold it flat (``{"latent_dim": 3, "ae_learning_rate": ...}``).
:data:`FLAT_OPTION_PATHS` maps those flat names onto the dotted paths, and :func:`recorded_options` reads
either form: every reader of a recorded config goes through it. Imports nothing heavy.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

from benchmark.core.config import recorded_options as _recorded_options
from benchmark.core.config import with_overrides

FLAT_OPTION_PATHS: dict[str, str] = {
    # geometry
    "static_iterations": "geometry.static_iterations",
    "deformation_iterations": "geometry.deformation_iterations",
    "static_model_iterations": "geometry.static_model_iterations",
    "max_gaussians": "geometry.max_gaussians",
    "gaussians_per_foreground_pixel": "geometry.gaussians_per_foreground_pixel",
    "render_backend": "geometry.render_backend",
    # time-agnostic autoencoder and field
    "latent_dim": "autoencoder.latent_dim",
    "ae_hidden_dims": "autoencoder.hidden_dims",
    "ae_cosine_weight": "autoencoder.cosine_weight",
    "ae_learning_rate": "autoencoder.learning_rate",
    "ae_batch_size": "autoencoder.batch_size",
    "ae_epochs": "autoencoder.epochs",
    "ae_min_steps": "autoencoder.min_steps",
    "ae_max_steps": "autoencoder.max_steps",
    "ae_sample_weighting": "autoencoder.sample_weighting",
    "field_iterations": "field.iterations",
    "field_learning_rate": "field.learning_rate",
    "field_loss_weight": "field.loss_weight",
    "field_init_std": "field.init_std",
    # answering
    "uncovered_alpha": "answer.uncovered_alpha",
    "decode_chunk": "answer.decode_chunk",
    "decode_chunk_cuda": "answer.decode_chunk_cuda",
    # captions
    "captioner": "captions.captioner",
    "captions_file": "captions.file",
    "qwen_model": "captions.qwen_model",
    "object_tracks": "captions.object_tracks",
    "visual_prompt": "captions.visual_prompt",
    "text_prompt": "captions.text_prompt",
    "caption_seed": "captions.seed",
    # caption autoencoder
    "tv_latent_dim": "caption_autoencoder.latent_dim",
    "tv_ae_hidden_dims": "caption_autoencoder.hidden_dims",
    "tv_ae_max_steps": "caption_autoencoder.max_steps",
    "tv_ae_min_steps": "caption_autoencoder.min_steps",
    # the time-varying head
    "time_varying": "status.fit",
    "num_states": "status.num_states",
    "weight_mode": "status.weight_mode",
    "status_hidden_dim": "status.hidden_dim",
    "status_init_noise": "status.init_noise",
    "tv_static_iterations": "status.static_iterations",
    "tv_learning_rate": "status.learning_rate",
    "status_iterations": "status.iterations",
    "status_mlp_learning_rate": "status.mlp_learning_rate",
    "status_loss_weight": "status.loss_weight",
    "tv_cache_view_mib": "status.cache_view_mib",
    # departures from the paper
    "unmasked_text": "extensions.unmasked_text",
    "caption_window": "extensions.caption_window",
    "caption_segments": "extensions.caption_segments",
    "choose_states": "extensions.choose_states",
    "skip_static_semantics": "extensions.skip_static_semantics",
    "semantic_change_tolerance": "extensions.semantic_change_tolerance",
    "dynamic_weight_share": "extensions.dynamic_weight_share",
    "min_state_run": "extensions.min_state_run",
    "status_time_tv_weight": "extensions.time_tv_weight",
    "status_entropy_weight": "extensions.entropy_weight",
    "blend_operators": "extensions.blend_operators",
    # feature-3dgs
    "feature_dim": "feature.dim",
    "feature_level": "feature.level",
    "feature_iterations": "feature.iterations",
    "feature_learning_rate": "feature.learning_rate",
    "decoder_learning_rate": "feature.decoder_learning_rate",
    # gaussian-grouping
    "identity_level": "identity.level",
    "identity_dim": "identity.dim",
    "identity_iterations": "identity.iterations",
    "identity_learning_rate": "identity.learning_rate",
    "classifier_learning_rate": "identity.classifier_learning_rate",
    "identity_reg_weight": "identity.reg_weight",
    "identity_reg_k": "identity.reg_k",
    "identity_reg_sample_size": "identity.reg_sample_size",
    "identity_reg_interval": "identity.reg_interval",
    "overlap_association": "association.overlap",
    "association_min_iou": "association.min_iou",
}
"""Flat option name of a record written before the options were grouped -> its dotted path now. Names
that are still options where they stand (``shared_cache_dir``, ``match_rule``) need no entry; the
query rules such records also hold (``threshold_variant``, ...) are the protocol's, read by
:func:`benchmark.results.protocol_of`."""


RETIRED_OPTIONS: dict[str, str] = {
    "camera_weight": "the old nearest-frame floor's camera term (its answers were today's nearest-frame-masks'; "
                     "both floors now weigh time against viewing angle by time_weight)",
}
"""Options records of retired code hold, and what they were: no option of today reads them, and a record
holding one describes no config of today (:func:`holds_retired_options`)."""
RETIRED_AS: dict[str, str] = {"camera_weight": "nearest-frame-masks"}
"""Retired option -> the registered method whose answers a record holding it gave (the leaderboard shows the
run under that name: :func:`methods.registry.recorded_method`)."""


def holds_retired_options(recorded: Optional[Mapping[str, Any]]) -> bool:
    """Whether ``recorded`` (a record's method config) holds an option of :data:`RETIRED_OPTIONS`."""
    return isinstance(recorded, Mapping) and any(name in recorded for name in RETIRED_OPTIONS)


def recorded_options(cls: type, recorded: Optional[Mapping[str, Any]]) -> dict[str, Any]:
    """Dotted path -> value of the options of config class ``cls`` in the recorded config ``recorded``
    (nested, or flat as :data:`FLAT_OPTION_PATHS` reads it); other keys are left out."""
    return _recorded_options(cls, recorded, renames=FLAT_OPTION_PATHS)


def config_from_record(cls: type, recorded: Optional[Mapping[str, Any]], *, what: str = "recorded config") -> Any:
    """An instance of ``cls`` with the options ``recorded`` gives (:func:`recorded_options`), the rest default."""
    return with_overrides(cls(), recorded_options(cls, recorded), what=what)
