"""Convert a published ViewFormer codebook checkpoint (`model.ckpt`, a torch file whose `state_dict`
holds the VQ-VAE's parameters and the quantizer's buffers) into the .npz that pyvf.Codebook loads:
`pyvf convert torch-codebook path/model.ckpt --config config.json -o codebook.npz` (needs torch,
imported only here). Keys outside the model (LPIPS, a discriminator, optimizer state) are skipped.
"""

import json

from pyvf.models.codebook import BUFFERS, Codebook, CodebookConfig, parameter_shapes


def convert(state_dict, config):
    """state_dict: name -> tensor or array -> (the model's entries, as given, for load_official,
    which drops a leading 'model.' and checks each; the keys skipped, outside the model)."""
    want = set(parameter_shapes(config)) | set(BUFFERS)
    weights = {k: v for k, v in state_dict.items() if k.removeprefix("model.") in want}
    return weights, [k for k in state_dict if k not in weights]


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
    weights, skipped = convert(ckpt.get("state_dict", ckpt), config)
    model = Codebook(config)
    model.load_official(weights)  # every entry checked, named
    model.save(output)
    return len(weights), skipped
