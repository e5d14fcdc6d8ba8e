"""What an app ships: correspondences and a model in, rectified K and pose out.

rectifier (the staged pipeline), checks (its input and fallback rules), fast (the hot path's
faster twins), features and grid (the network's input), inference (features -> Delta K -> the
K-bounds rule, for batches), model and spec (the ONNX model and its ``dimenet-model/1`` spec),
uncertainty (the run-time covariance model) and map_fit (mode map). Imports nothing from
formats, sim, ingest, evaluation or cli.
"""
