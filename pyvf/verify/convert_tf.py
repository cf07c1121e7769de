"""Convert a published ViewFormer transformer checkpoint (TensorFlow: model.index, model.data-*)
into the .npz that pyvf.Transformer loads: `pyvf convert tf-transformer path/model --config
config.json -o model.npz` (--config: TransformerConfig fields as JSON; needs tensorflow, imported
only here). Keys match the official names whichever way TensorFlow wrote them (name-based
`migt/h.0/attn/c_attn/weight`, object-based `.../.ATTRIBUTES/VARIABLE_VALUE`); every official name
must be found once, anything else (optimizer slots, counters) is skipped.
"""

import json

import numpy as np

from pyvf.models.transformer import Transformer, TransformerConfig, parameter_shapes

SKIP_MARKERS = ("/.OPTIMIZER_SLOT/", "optimizer/", "save_counter", "global_step", "_CHECKPOINTABLE_OBJECT_GRAPH",
                "/m/", "/v/", "Adam")


def checkpoint_key_to_name(key):
    """The official name a checkpoint key stands for, or None for keys that are not weights."""
    if any(marker in key for marker in SKIP_MARKERS):
        return None
    name = key.removesuffix("/.ATTRIBUTES/VARIABLE_VALUE").removesuffix(":0")
    if "migt/" in name:  # drop anything before the model's scope, e.g. "model/" or "transformer/"
        name = name[name.index("migt/") + len("migt/"):]
    return name


def convert(reader, config):
    """reader: anything with get_variable_to_shape_map() and get_tensor(key) (tf.train.load_checkpoint).
    Returns (weights: official name -> float32 array, skipped keys)."""
    shapes = parameter_shapes(config)
    weights, skipped = {}, []
    for key in sorted(reader.get_variable_to_shape_map()):
        name = checkpoint_key_to_name(key)
        if name not in shapes:
            skipped.append(key)
            continue
        if name in weights:
            raise ValueError(f"two checkpoint keys map to {name!r} (second: {key!r})")
        weights[name] = np.asarray(reader.get_tensor(key), dtype=np.float32)
    missing = [n for n in shapes if n not in weights]
    if missing:
        raise ValueError(f"{len(missing)} weights not found in the checkpoint, e.g. {missing[:5]}; "
                         f"its keys include {skipped[:5]}")
    return weights, skipped


def convert_checkpoint(checkpoint, config_json, output):
    """Read the TensorFlow checkpoint `checkpoint` (a prefix, beside model.index) of the
    TransformerConfig in the JSON file `config_json`, check it and write it to `output` (.npz).
    Returns (the number of weights written, the checkpoint keys skipped)."""
    try:
        import tensorflow as tf
    except ImportError:
        raise ModuleNotFoundError("convert tf-transformer needs tensorflow (the tf extra: pip install 'pyvf[tf]', or tensorflow-cpu)") from None
    with open(config_json) as f:
        config = TransformerConfig(**json.load(f))
    weights, skipped = convert(tf.train.load_checkpoint(str(checkpoint)), config)
    model = Transformer(config)
    model.load_official(weights)  # checks every shape
    model.save(output)
    return len(weights), skipped
