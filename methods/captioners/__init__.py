"""Captioners (MLLM, template, file) and the object-wise visual prompts they see."""
