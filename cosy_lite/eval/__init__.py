"""Pose evaluation: BOP19 errors (VSD, MSSD, MSPD), ADD/ADI, scoring (AR) and the ``eval`` command.

``pose_errors`` (the definitions, numpy, metres) -> ``object_errors`` (the same MSSD/MSPD/ADD/ADI,
exact and fast, per object) and ``depth_renderer`` (windowed depth for VSD) -> ``image_errors``
(one image's targets, the toolkit's shortcuts) -> ``scoring`` (matching, recalls, AR, AUC) ->
``evaluator`` (dataset + results CSV -> :class:`~cosy_lite.eval.evaluator.EvalResult`) ->
``command`` (``cosy-lite eval``). Nothing is imported here.
"""
