"""Checking pyvf against other implementations, and bringing their weights in (docs/verify.md).
The torch modules (torch_ports, torch_transformer, torch_codebook) import torch; this package's
__init__ imports none of them, so `import pyvf.verify` stays NumPy only."""
