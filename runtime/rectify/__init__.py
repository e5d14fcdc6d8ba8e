"""What an app ships: correspondences and a model in, rectified K and pose out.

rectifier (the staged pipeline), checks (input and fallback rules), features and grid (the
network's input), model and spec (the ONNX model and its ``dimenet-model/1`` spec),
uncertainty (the run-time covariance model) and map_fit (mode map). Imports nothing from
formats, sim, ingest, evaluation or cli.
"""
