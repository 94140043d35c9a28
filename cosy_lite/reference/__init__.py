"""Scoring of reference models (:mod:`~cosy_lite.reference.score_refiner`); their files are in ``models/``
(:mod:`cosy_lite.inference.reference_models`)."""
