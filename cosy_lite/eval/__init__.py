"""Pose evaluation: BOP19 errors (VSD, MSSD, MSPD), ADD/ADI, scoring (AR) and the ``eval`` command.

``pose_errors`` (numpy, metres) -> ``scoring`` (matching, recalls, AR, AUC) -> ``evaluator``
(dataset + results CSV -> :class:`~cosy_lite.eval.evaluator.EvalResult`). Nothing is imported here.
"""
