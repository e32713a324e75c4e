"""The side panels of a session viewer: one module a panel (camera, evidence, loops, place cells, stats,
layers) and :mod:`web.panels.view`, what one browser sees (its layers, the time slider, the camera)."""
