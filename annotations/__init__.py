"""Ground-truth annotations: the data model, the project's JSON format, importers and exporters."""

from .model import (AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask,
                    normalise_intervals)

__all__ = ["AnnotatedFrame", "AnnotationSet", "Query", "decode_mask", "encode_mask",
           "normalise_intervals"]
