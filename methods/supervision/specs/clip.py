from methods.supervision.registry import SourceSpec

SPEC = SourceSpec(
    name="clip", kind="image_text", track="real",
    description="OpenCLIP ViT-B-16 laion2b_s34b_b88k on masked crops prepared as the release (box crop, zeroed "
                "background, square pad, 224 px, CLIP normalisation); weights from a local path",
    entry_point="methods.supervision.clip:create",
    requires=("transformers (backend='hf') or open_clip_torch + torchvision (backend='open_clip')",),
)
