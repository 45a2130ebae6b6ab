from methods.supervision.registry import SourceSpec

SPEC = SourceSpec(
    name="sam", kind="segmenter", track="real",
    description="Segment Anything automatic masks split into small/middle/large by multimask output (as the "
                "release), ids carried across frames by overlap; weights from a local path",
    entry_point="methods.supervision.sam:create",
    requires=("transformers (backend='hf') or segment-anything + torchvision (backend='segment-anything')",),
)
