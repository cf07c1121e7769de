"""Convert a published ViewFormer codebook checkpoint (`model.ckpt`, a torch file whose `state_dict`
holds the VQ-VAE's parameters and the quantizer's buffers) into the .npz that pyvf.Codebook loads:
`pyvf convert torch-codebook path/model.ckpt --config config.json -o codebook.npz` (needs torch,
imported only here). Keys outside the model (LPIPS, a discriminator, optimizer state) are skipped.
"""

import json

import numpy as np

from pyvf import _checks
from pyvf.models.codebook import BUFFERS, Codebook, CodebookConfig, parameter_shapes


def convert(state_dict, config):
    """state_dict: name -> tensor or array (a leading 'model.' is dropped; a name given both with
    and without it raises). Returns (the model's name -> numpy array, skipped names)."""
    want = set(parameter_shapes(config)) | set(BUFFERS)
    out, keys, skipped = {}, {}, []
    for key, value in state_dict.items():
        name = key[len("model."):] if key.startswith("model.") else key
        if name not in want:
            skipped.append(key)
            continue
        if name in out:
            raise ValueError(f"two state_dict keys map to {name!r}: {keys[name]!r} and {key!r}")
        value, problem = _checks.checkpoint_array(key, value)  # a tensor numpy cannot hold: named
        if problem is not None:
            raise problem[0](problem[1])
        out[name], keys[name] = np.asarray(value), key
    return out, skipped


def convert_checkpoint(checkpoint, config_json, output):
    """Read the torch checkpoint `checkpoint` (model.ckpt: a dict with a state_dict, or a
    state_dict itself) of the CodebookConfig in the JSON file `config_json`, check it and write
    it to `output` (.npz). Returns (the number of arrays written, the keys skipped)."""
    try:
        import torch
    except ImportError:
        raise ModuleNotFoundError("convert torch-codebook needs torch (pip install torch)") from None
    with open(config_json) as f:
        config = CodebookConfig(**json.load(f))
    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict):
        raise ValueError(f"{checkpoint} holds a {type(ckpt).__name__}, not a checkpoint (a dict with a "
                         "state_dict, or a state_dict)")
    weights, skipped = convert(ckpt.get("state_dict", ckpt), config)
    model = Codebook(config)
    model.load_official(weights)  # every name and shape checked
    model.save(output)
    return len(weights), skipped
