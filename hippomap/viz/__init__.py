"""Figures of the model's state for people: :mod:`~hippomap.viz.place_field_figure` draws how the place
cells settled on a position (the figure the server serves and the viewer shows).

Needs matplotlib, which the ``viz`` extra installs (``pip install 'hippomap[viz]'``; ``eval`` includes it).
"""
