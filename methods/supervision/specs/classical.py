from methods.supervision.registry import SourceSpec

SPEC = SourceSpec(
    name="classical", kind="segmenter", track="real",
    description="Felzenszwalb graph segmentation at three scales, nested into a hierarchy, ids carried "
                "across frames by overlap (no weights needed)",
    entry_point="methods.supervision.classical:create",
)
