"""From a trained field to a coloured mesh: extraction on a grid (`extraction`), and the field and mesh seen from the
photos — depth, visibility, colour baking, texturing (`photos`). The pure-array work (marching cubes, cleaning,
raster, export) is `recon.geometry`'s."""
