"""Networks (tensor in, tensor out) and the render-and-compare engine around them: backbones, the
pose networks, the coarse scorer, the detector, losses, templates. The weights they are loaded
from live in :mod:`cosy_lite.weights`; the meshes of the objects in :mod:`cosy_lite.inference.object_meshes`."""
