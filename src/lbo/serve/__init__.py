"""Observers at work: lbo.Observer on a log or step by step, the engines it runs on
(PyTorch, TorchScript, ONNX Runtime), and MLflow serving."""
