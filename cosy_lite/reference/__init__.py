"""Scoring of reference models (:mod:`~cosy_lite.reference.score_refiner`); their files are in
``cosy_lite/reference/weights/NAME/`` (:mod:`cosy_lite.model_files.reference_models`)."""
