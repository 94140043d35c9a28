"""Inference: detector -> coarse -> refiner -> optional depth ICP (``icp.py``) -> BOP estimates."""
