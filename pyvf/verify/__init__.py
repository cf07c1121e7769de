"""Checking pyvf against other implementations, and bringing their weights in.

    torch_transformer   the transformer written again in torch from docs/math.md §3 (the oracle)
    torch_codebook      the VQ-VAE codebook written again in torch from docs/math.md §4 (the oracle)
    torch_ports         both models as a port author writes them (nn.Modules named as published),
                        with the typical port bugs to plant (tests/test_teacher.py, docs/verify.md)
    convert_tf          a published TensorFlow transformer checkpoint -> pyvf .npz
    convert_torch       a published torch codebook checkpoint -> pyvf .npz

The torch oracles import torch when imported; this package's __init__ imports none of them, so
`import pyvf.verify` stays NumPy only.
"""
