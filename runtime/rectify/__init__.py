"""What an app ships: correspondences and a model in, rectified K and pose out.

rectifier (the thin ``Rectifier``), stages (its stages, each frame/batch pair side by side),
results (what it returns), checks (its input and fallback rules, and validation), features and
grid (the network's input), inference (features -> Delta K -> the K-bounds rule, for batches),
model and spec (the ONNX model, its loading and its ``dimenet-model/1`` spec), uncertainty (the
run-time covariance model) and map_fit (mode map). Hot-path twins stand beside their references. Imports nothing from
formats, sim, ingest, evaluation or cli.
"""
