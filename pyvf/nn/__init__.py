"""The layers: each a forward and a backward pass side by side (docs/math.md).

    attention   branching attention (the tree's masked softmax) and the attention layer
    layers      linear, LayerNorm, GELU, the MLP, embeddings
    conv        convolutions, GroupNorm, up- and downsampling (the codebook's)
    losses      cross-entropy with label smoothing, the pose loss
    quantizer   the EMA vector quantizer
"""
