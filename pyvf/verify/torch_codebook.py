"""The ViewFormer VQ-VAE codebook written again in torch, as the oracle for pyvf's codebook.

Written from docs/math.md §4 independently of pyvf's code (taming-transformers style Encoder /
Decoder with official torch state_dict names, EMA vector quantizer), as plain functions: the
float64 oracle of tests/test_codebook.py and the torch side of `pyvf bench codebook` (the
nn.Module port, which also has the empty code, is torch_ports.CodebookPort). Functional torch only:
F.conv2d, F.group_norm (32 groups, eps 1e-6), nearest upsampling, explicit softmax attention.
Autograd gives the gradients; the EMA update runs without gradient.
"""

import torch
import torch.nn.functional as F


def conv(x, P, name, stride=1, padding=0):
    return F.conv2d(x, P[name + ".weight"], P[name + ".bias"], stride=stride, padding=padding)


def norm(x, P, name):
    return F.group_norm(x, 32, P[name + ".weight"], P[name + ".bias"], eps=1e-6)


def swish(x):
    return x * torch.sigmoid(x)


def resnet_block(x, P, name):
    h = conv(swish(norm(x, P, name + ".norm1")), P, name + ".conv1", padding=1)
    h = conv(swish(norm(h, P, name + ".norm2")), P, name + ".conv2", padding=1)
    if name + ".nin_shortcut.weight" in P:
        x = conv(x, P, name + ".nin_shortcut")
    return x + h


def attn_block(x, P, name):
    B, C, H, W = x.shape
    h = norm(x, P, name + ".norm")
    q, k, v = (conv(h, P, f"{name}.{t}").reshape(B, C, H * W) for t in "qkv")
    w = torch.softmax((q.transpose(1, 2) @ k) * C ** -0.5, dim=-1)  # (B, query, key)
    h = (v @ w.transpose(1, 2)).reshape(B, C, H, W)
    return x + conv(h, P, name + ".proj_out")


def downsample(x, P, name):
    return conv(F.pad(x, (0, 1, 0, 1)), P, name, stride=2)


def upsample(x, P, name):
    return conv(F.interpolate(x, scale_factor=2, mode="nearest"), P, name, padding=1)


def encoder(x, P, cfg):
    L, res = len(cfg.ch_mult), cfg.image_size
    h = conv(x, P, "encoder.conv_in", padding=1)
    for l in range(L):
        for i in range(cfg.num_res_blocks):
            h = resnet_block(h, P, f"encoder.down.{l}.block.{i}")
            if res in cfg.attn_resolutions:
                h = attn_block(h, P, f"encoder.down.{l}.attn.{i}")
        if l != L - 1:
            h = downsample(h, P, f"encoder.down.{l}.downsample.conv")
            res //= 2
    h = resnet_block(h, P, "encoder.mid.block_1")
    h = attn_block(h, P, "encoder.mid.attn_1")
    h = resnet_block(h, P, "encoder.mid.block_2")
    return conv(swish(norm(h, P, "encoder.norm_out")), P, "encoder.conv_out", padding=1)


def decoder(z, P, cfg):
    L = len(cfg.ch_mult)
    res = cfg.image_size // 2 ** (L - 1)
    h = conv(z, P, "decoder.conv_in", padding=1)
    h = resnet_block(h, P, "decoder.mid.block_1")
    h = attn_block(h, P, "decoder.mid.attn_1")
    h = resnet_block(h, P, "decoder.mid.block_2")
    for l in reversed(range(L)):
        for i in range(cfg.num_res_blocks + 1):
            h = resnet_block(h, P, f"decoder.up.{l}.block.{i}")
            if res in cfg.attn_resolutions:
                h = attn_block(h, P, f"decoder.up.{l}.attn.{i}")
        if l != 0:
            h = upsample(h, P, f"decoder.up.{l}.upsample.conv")
            res *= 2
    return conv(swish(norm(h, P, "decoder.norm_out")), P, "decoder.conv_out", padding=1)


def ema_update(buffers, z_flat, codes, cfg):
    """docs/math.md §4 EMA step (no gradient); returns a new buffers dict."""
    with torch.no_grad():
        z_flat = z_flat.detach()
        emb = buffers["quantize.embeddings"]
        onehot = F.one_hot(codes, cfg.n_embed).to(z_flat.dtype)  # (M, n_embed)
        N = onehot.sum(0).to(emb.dtype)  # (n_embed,)
        S = (z_flat.T @ onehot).to(emb.dtype)  # (embed_dim, n_embed)
        d = cfg.decay
        hcs = buffers["quantize.ema_cluster_size_hidden"]
        hdw = buffers["quantize.ema_dw_hidden"]
        hcs = hcs + (1 - d) * (N - hcs)
        hdw = hdw + (1 - d) * (S - hdw)
        counter = int(buffers["quantize.counter"]) + 1
        cs = hcs / (1 - d ** counter)
        dw = hdw / (1 - d ** counter)
        n = cs.sum()
        cs = (cs + cfg.eps) / (n + cfg.n_embed * cfg.eps) * n
        return {"quantize.embeddings": dw / cs[None, :], "quantize.ema_cluster_size_hidden": hcs,
                "quantize.ema_dw_hidden": hdw, "quantize.counter": counter}


def forward(P, buffers, images, cfg, codebook_weight=1.0, train=True):
    """See module doc / pyvf tests: returns reconstruction, codes, z, rec_loss,
    commitment_loss, loss and the (new) buffers dict."""
    z = conv(encoder(images, P, cfg), P, "quant_conv")  # (B, embed_dim, k, k)
    B, D, k, _ = z.shape
    emb = buffers["quantize.embeddings"]  # (D, n_embed), codes are columns
    z_flat = z.permute(0, 2, 3, 1).reshape(-1, D)
    with torch.no_grad():
        dist = ((z_flat.detach()[:, :, None] - emb[None]) ** 2).sum(1)  # (M, n_embed), exact
        codes = dist.argmin(1)
    e = emb.T[codes].reshape(B, k, k, D).permute(0, 3, 1, 2).detach()  # old codes
    commitment = ((e - z) ** 2).mean()
    zq = z + (e - z).detach()
    rec = decoder(conv(zq, P, "post_quant_conv"), P, cfg)
    rec_loss = (images - rec).abs().mean()
    if train:
        new_buffers = ema_update(buffers, z_flat, codes, cfg)
    else:
        new_buffers = dict(buffers)
    return {"reconstruction": rec, "codes": codes.reshape(B, k, k), "z": z, "rec_loss": rec_loss,
            "commitment_loss": commitment, "loss": rec_loss + codebook_weight * commitment,
            "buffers": new_buffers}
