"""hydo's deploy side: ONNX policy, cameras, perception, safety, executors. Never imports torch."""
