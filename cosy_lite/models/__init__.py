"""Networks: backbones, the pose network (tensor in, tensor out), the detector, losses."""
