"""dimenet.export: MLP -> ONNX with its model spec."""
