"""The ONNX opsets the exporter writes: torch-free, so `dimenet export`'s flags know them without loading
the exporter (onnx_export)."""

DEFAULT_OPSET = 17
# Erf (exact GELU) needs opset 9; 20 is the TorchScript exporter's newest.
MIN_OPSET, MAX_OPSET = 9, 20
