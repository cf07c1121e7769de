"""One training step of the transformer and of the codebook, for a loop to call (docs/math.md §5).

    model = Transformer(cfg)
    opt = AdamW(model.params, lr=WarmupCosine(1e-4, 2000, 120_000), weight_decay=0.01)
    for tokens, poses in batches:
        loss, grad_norm = train_step(model, opt, tokens, poses, max_grad_norm=1.0)
"""

from ..geometry import make_relative
from .optim import clip_grad_norm, global_norm


def transformer_step(model, optimizer, tokens, poses, *, max_grad_norm=None, clip_mode="global"):
    """Forward, backward, optional clipping, optimiser step: tokens (B, N, L) ints, poses (B, N, 7),
    made relative to each sequence's first view first (geometry.make_relative), as the published
    input pipeline does. max_grad_norm: clip_grad_norm's (clip_mode "global" as torch's
    clip_grad_norm_, "per_tensor" as tf.clip_by_norm, the published choice). optimizer holds
    model.params. Returns (the TransformerOutput of the forward before the update, the gradient
    norm before clipping: a float, or {name: norm} with clip_mode "per_tensor")."""
    if optimizer.params is not model.params:
        raise ValueError("optimizer must be built on model.params (AdamW(model.params, ...))")
    out = model.forward(tokens, make_relative(poses)[0])
    grads = model.backward()
    if max_grad_norm is not None:
        norm = clip_grad_norm(grads, max_grad_norm, mode=clip_mode)
    else:  # no clipping: the global norm all the same (nan or inf where a gradient is not finite)
        norm = global_norm(grads)
    optimizer.step(grads)
    return out, norm


def train_step(model, optimizer, tokens, poses, *, max_grad_norm=None, clip_mode="global"):
    """transformer_step -> (the loss before the step, the gradient norm before clipping)."""
    out, norm = transformer_step(model, optimizer, tokens, poses, max_grad_norm=max_grad_norm, clip_mode=clip_mode)
    return out.loss, norm


def codebook_train_step(codebook, optimizer, images, pixel_weights=None):
    """One codebook step: forward with the EMA update (train=True), backward, optimiser step, e.g.
    with the published `Adam(codebook.params, 1.584e-3, betas=(0.5, 0.9))` (the codes are not
    parameters: the EMA moves them). pixel_weights: Codebook.forward's. Returns the step's
    CodebookOutput. A step that raises leaves the codebook as it was: the EMA buffers the forward
    moved are put back (a retried step would otherwise move them twice)."""
    if optimizer.params is not codebook.params:
        raise ValueError("optimizer must be built on codebook.params (Adam(codebook.params, ...))")
    saved = codebook.quantizer.state_dict()  # copies; the buffers are (D, K): small beside the step
    out = codebook.forward(images, train=True, pixel_weights=pixel_weights)  # puts them back itself if it raises
    try:
        optimizer.step(codebook.backward())
    except BaseException:
        codebook.quantizer.load_state_dict(saved)
        raise
    return out
