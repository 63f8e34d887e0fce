"""Variation: ranges and seeds, physics drawn into a spec, looks drawn onto a recorded model, textures, distractors."""
