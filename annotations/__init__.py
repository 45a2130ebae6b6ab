"""Ground-truth annotations: the data model, the project's JSON format, importers and exporters."""

from .format import load_annotations, save_annotations, validate_against_scene
from benchmark.core.annotation import (AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask,
                    normalise_intervals)

__all__ = ["AnnotatedFrame", "AnnotationSet", "Query", "decode_mask", "encode_mask",
           "load_annotations", "normalise_intervals", "save_annotations", "validate_against_scene"]
