"""Weights files of trained networks, shared by training, inference and export (none of which the others import
for it): the checkpoint format (:mod:`.checkpoint`: ``checkpoint.pt`` to resume, ``.safetensors``
weights that leave a run), the pose networks a checkpoint describes (:mod:`.pose_nets`:
``PoseNetConfig`` -> ``build_pose_net``) and checkpoints -> models ready for inference
(:mod:`.loaders`: ``PoseModel``, ``load_pose_model``, ``load_detector``). Nothing is imported here."""
