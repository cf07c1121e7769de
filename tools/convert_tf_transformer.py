"""Convert a published ViewFormer transformer checkpoint (TensorFlow: model.index, model.data-*)
into the .npz that pyvf.Transformer loads.

    python tools/convert_tf_transformer.py path/to/checkpoint/model --config config.json -o model.npz

--config is a JSON file of TransformerConfig fields (n_embeddings, n_head, d_model, n_layer,
token_image_size, sequence_size, n_loss_skip, ...). Needs tensorflow (only here: pyvf itself
never imports it). The checkpoint's keys are matched to the official names of
spec/official-transformer-*.json, whichever way TensorFlow wrote them:

    name-based (tf.compat.v1 Saver):   migt/h.0/attn/c_attn/weight
    object-based (Keras save_weights): migt/h.0/attn/c_attn/weight/.ATTRIBUTES/VARIABLE_VALUE

Every official name must be found exactly once with its shape; anything else (optimizer slots,
the step counter, the save counter) is listed and skipped. pyvf.Transformer.load_official then
checks names, shapes and values again.
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from pyvf.transformer import Transformer, TransformerConfig, parameter_shapes  # noqa: E402

SKIP_MARKERS = ("/.OPTIMIZER_SLOT/", "optimizer/", "save_counter", "global_step", "_CHECKPOINTABLE_OBJECT_GRAPH",
                "/m/", "/v/", "Adam")


def checkpoint_key_to_name(key):
    """The official name a checkpoint key stands for, or None for keys that are not weights."""
    if any(marker in key for marker in SKIP_MARKERS):
        return None
    name = key
    for suffix in ("/.ATTRIBUTES/VARIABLE_VALUE", ":0"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    if "migt/" in name:  # drop anything before the model's scope, e.g. "model/" or "transformer/"
        name = name[name.index("migt/") + len("migt/"):]
    return name


def convert(reader, config):
    """reader: anything with get_variable_to_shape_map() and get_tensor(key) (tf.train.load_checkpoint).
    Returns (weights: official name -> float32 array, skipped keys)."""
    shapes = parameter_shapes(config)
    weights, skipped = {}, []
    for key, shape in sorted(reader.get_variable_to_shape_map().items()):
        name = checkpoint_key_to_name(key)
        if name not in shapes:
            skipped.append(key)
            continue
        if name in weights:
            raise ValueError(f"two checkpoint keys map to {name!r} (second: {key!r})")
        if tuple(shape) != shapes[name]:
            raise ValueError(f"checkpoint key {key!r} has shape {tuple(shape)}, expected {shapes[name]} for {name!r}")
        weights[name] = np.asarray(reader.get_tensor(key), dtype=np.float32)
    missing = [n for n in shapes if n not in weights]
    if missing:
        raise ValueError(f"{len(missing)} weights not found in the checkpoint, e.g. {missing[:5]}; "
                         f"its keys include {skipped[:5]}")
    return weights, skipped


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", help="checkpoint prefix, e.g. path/model (beside model.index)")
    ap.add_argument("--config", required=True, help="JSON file of TransformerConfig fields")
    ap.add_argument("-o", "--output", required=True, help="the .npz to write")
    args = ap.parse_args(argv)
    try:
        import tensorflow as tf
    except ImportError:
        sys.exit("convert_tf_transformer: needs tensorflow (pip install tensorflow-cpu)")
    with open(args.config) as f:
        config = TransformerConfig(**json.load(f))
    weights, skipped = convert(tf.train.load_checkpoint(args.checkpoint), config)
    model = Transformer(config)
    model.load_official(weights)  # checks everything once more
    model.save(args.output)
    print(f"wrote {args.output}: {len(weights)} weights; skipped {len(skipped)} other keys")


if __name__ == "__main__":
    main()
