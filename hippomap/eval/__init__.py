"""Evaluation of a map against ground truth: trajectory metrics through evo (:mod:`~hippomap.eval.evaluation`:
ATE, RPE), which of the ground truth's revisits the map's loop closures closed
(:mod:`~hippomap.eval.revisits`) and place-recognition precision/recall (:mod:`~hippomap.eval.vpr_eval`,
``hippomap eval-vpr``).

Needs the ``eval`` extra (evo, matplotlib): ``pip install 'hippomap[eval]'``.
"""
