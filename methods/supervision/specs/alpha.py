from methods.supervision.registry import SourceSpec

SPECS = (
    SourceSpec(name="alpha", kind="segmenter", track="oracle",
               description="object / background masks from the alpha channel of TRAINING frames (D-NeRF)",
               entry_point="methods.supervision.alpha:create_segmenter"),
    SourceSpec(name="object-name", kind="image_text", track="oracle",
               description="text embedding of the scene's object name on the alpha mask, 'background' elsewhere "
                           "(TRAINING frames only; D-NeRF)",
               entry_point="methods.supervision.alpha:create_encoder"),
)
