"""Photos and video in, masks, COLMAP, the scene contract and its importers, normalization, object region, sky."""
