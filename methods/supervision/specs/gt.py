from methods.supervision.registry import SourceSpec

SPEC = SourceSpec(
    name="gt", kind="segmenter", track="oracle",
    description="generator truth id maps of TRAINING frames (subpart/part/whole = small/middle/large)",
    entry_point="methods.supervision.gt:create",
)
