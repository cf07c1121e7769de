"""Checking pyvf against other implementations, and bringing their weights in (docs/verify.md).
torch_ports imports torch; this package's __init__ does not, so `import pyvf.verify` stays NumPy only."""
