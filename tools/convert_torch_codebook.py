"""Convert a published ViewFormer codebook checkpoint (`model.ckpt`: a torch file whose
`state_dict` holds the VQ-VAE's parameters and the quantizer's EMA buffers) into the .npz that
pyvf.Codebook loads.

    python tools/convert_torch_codebook.py path/model.ckpt --config config.json -o codebook.npz

--config is a JSON file of CodebookConfig fields (ch, ch_mult, num_res_blocks, attn_resolutions,
z_channels, embed_dim, n_embed, image_size, ...). Uses torch here only; pyvf never imports it.
Keys outside the model (a loss's LPIPS network, a discriminator, optimizer state) are listed and
skipped; every model name must be present with its shape (pyvf.Codebook.load_official checks).
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from pyvf.codebook import BUFFERS, Codebook, CodebookConfig, parameter_shapes  # noqa: E402


def convert(state_dict, config):
    """state_dict: name -> tensor or array (a leading 'model.' is dropped). Returns (the model's
    name -> numpy array, skipped names)."""
    want = set(parameter_shapes(config)) | set(BUFFERS)
    out, skipped = {}, []
    for key, value in state_dict.items():
        name = key[len("model."):] if key.startswith("model.") else key
        if name not in want:
            skipped.append(key)
            continue
        out[name] = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
    return out, skipped


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--config", required=True)
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    import torch
    with open(args.config) as f:
        config = CodebookConfig(**json.load(f))
    ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    weights, skipped = convert(ckpt.get("state_dict", ckpt), config)
    model = Codebook(config)
    model.load_official(weights)  # every name and shape checked
    model.save(args.output)
    print(f"wrote {args.output}: {len(weights)} arrays; skipped {len(skipped)} other keys")


if __name__ == "__main__":
    main()
