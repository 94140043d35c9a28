"""cosy_lite: a CosyPose-style 6D object pose estimation baseline for the BOP benchmark."""

__version__ = "0.1.0"
