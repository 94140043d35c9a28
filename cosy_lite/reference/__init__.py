"""Reference models shipped with the package: one data folder per dataset (weights, cards; found by
:mod:`cosy_lite.inference.reference_models`) and :mod:`~cosy_lite.reference.score_refiner`."""
