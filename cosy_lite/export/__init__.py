"""ONNX export of the three networks and their onnxruntime backend (:mod:`.onnx_export`,
:mod:`.onnx_models`, :mod:`.quantize`, ``cosy-lite export``: :mod:`.command`)."""
