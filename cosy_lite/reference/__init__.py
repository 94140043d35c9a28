"""Scoring of reference models (:mod:`~cosy_lite.reference.score_refiner`); their files are in
``models/NAME/`` of the repository, installed as ``cosy_lite/reference/weights/NAME/``
(:mod:`cosy_lite.weights.reference_models`)."""
