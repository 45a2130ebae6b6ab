from methods.supervision.registry import SourceSpec

SPEC = SourceSpec(
    name="oracle-text", kind="image_text", track="oracle",
    description="text embedding of each mask's ground-truth name (training frames only)",
    entry_point="methods.supervision.oracle_text:create",
)
