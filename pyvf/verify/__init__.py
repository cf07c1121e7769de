"""Checking pyvf against other implementations, and bringing their weights in.

    torch_ports         both models as a port author writes them (nn.Modules named as published,
                        from docs/math.md), with the typical port bugs to plant (tests/test_teacher.py)
    torch_transformer   the port as a function of a parameter dict, and the losses (the oracle, the bench's torch side)
    torch_codebook      the codebook port as a function of a parameter dict, with the EMA step
    convert_tf          a published TensorFlow transformer checkpoint -> pyvf .npz
    convert_torch       a published torch codebook checkpoint -> pyvf .npz

The torch oracles import torch when imported; this package's __init__ imports none of them, so
`import pyvf.verify` stays NumPy only.
"""
