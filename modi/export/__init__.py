"""Trained models as files other programs run: ONNX graphs of a GANimator run and of a MoDi generator.

* ``onnx``        -- the export (torch, onnx, onnxscript): ``export_onnx(source, "model.onnx")`` writes the graph and
  its JSON sidecar (skeleton, fps, unit, the inputs' shapes and ranges, the outputs' meaning)
* ``onnx_runner`` -- NumPy + onnxruntime only (no torch, nothing else of modi): checks inputs against the sidecar's
  contract, runs the graph, writes BVH; also a standalone script (``python onnx_runner.py model.onnx out.bvh``)

Nothing is imported here, so ``python -m modi.export.onnx_runner`` loads neither torch nor the rest of modi.
"""
