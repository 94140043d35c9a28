"""ONNX export of the networks: detector, coarse, refiner and coarse scorer (:mod:`.onnx_export`,
:mod:`.quantize`, the export's :mod:`.manifest`, ``cosy-lite export``: :mod:`.command`); the
exported networks run through :mod:`cosy_lite.inference.onnx_runtime`."""
