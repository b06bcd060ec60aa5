"""Readers of posed images as they come: NeRF-synthetic ``transforms.json`` layouts, COLMAP
models, capture images and their distortion."""
