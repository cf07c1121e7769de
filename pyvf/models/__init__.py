"""The pretrained models shipped with pyvf, and the check that a codebook and a transformer fit.

    codebook, transformer = load_pretrained()                       # the package's SM7 pair
    codebook, transformer = load_pretrained("runs/cb/codebook.npz", "runs/tf/transformer.npz")
    check_pair(codebook, transformer)                               # ValueError when they do not fit

The shipped pair is two package data files beside this module (Codebook.save, Transformer.save
output), trained on procedural SM7 scenes of seed 0 (pyvf.scenes).
"""

import importlib.resources
import os
import warnings

from .codebook import Codebook
from .transformer import Transformer

__all__ = ["PRETRAINED", "TRAIN_HINT", "check_pair", "load_pretrained"]

# kind -> file name of the shipped model (package data of pyvf.models)
PRETRAINED = {"codebook": "sm7-codebook.npz", "transformer": "sm7-transformer.npz"}

# How to make the pair yourself (the step counts of pyvf/train/loops.py's example; ~2 s a step on 2 cores).
TRAIN_HINT = """\
train a pair yourself (pyvf's training commands; each resumes when run again):
    pyvf scenes --out data/sm7 --scenes 2000 --seed 0
    pyvf train-codebook --data data/sm7 --out runs/cb --steps 20000
    pyvf tokenize --codebook runs/cb/codebook.npz --data data/sm7 --out runs/tokens.npz
    pyvf train-transformer --tokens runs/tokens.npz --out runs/tf --steps 50000
then pass them: --codebook runs/cb/codebook.npz --transformer runs/tf/transformer.npz"""


def _resolve(kind, path):
    """path, or the shipped file when path is None -> an existing path (FileNotFoundError otherwise)."""
    if path is None:  # pyvf is installed as files (scikit-build-core wheel), not zipped
        path = importlib.resources.files(__name__).joinpath(PRETRAINED[kind])
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{kind} file {path} does not exist.\n{TRAIN_HINT}")
    return path


def check_pair(codebook, transformer):
    """ValueError unless the transformer reads this codebook's tokens: the same codebook size V,
    the same token image side k and the codebook it was trained with (its fingerprint; a warning
    where a file does not record it)."""
    cb, tf = codebook.config, transformer.config
    if tf.n_embeddings != cb.n_embed:
        raise ValueError(f"the transformer and the codebook do not fit: the transformer reads "
                         f"n_embeddings={tf.n_embeddings} codes, the codebook has n_embed={cb.n_embed}")
    if tf.token_image_size != cb.token_size:
        raise ValueError(f"the transformer and the codebook do not fit: the transformer reads "
                         f"{tf.token_image_size}x{tf.token_image_size} token images, the codebook makes "
                         f"{cb.token_size}x{cb.token_size} (image_size {cb.image_size}, "
                         f"{len(cb.ch_mult) - 1} downsamplings)")
    cb_name = f"codebook {codebook.source}" if codebook.source else "the codebook"
    tf_name = f"transformer {transformer.source}" if transformer.source else "the transformer"
    if transformer.codebook_fingerprint is None and transformer.source:  # a file saved before pyvf recorded it
        warnings.warn(f"{tf_name} does not record the codebook it was trained with (saved before pyvf recorded "
                      f"it): its pairing with {cb_name} could not be checked")  # once: one location
    elif transformer.codebook_fingerprint not in (None, codebook.fingerprint()):
        raise ValueError(f"{tf_name} was trained on the tokens of another codebook (fingerprint "
                         f"{transformer.codebook_fingerprint}) than {cb_name} ({codebook.fingerprint()}): its codes "
                         "would mean something else. Pass the codebook its tokens came from (--codebook "
                         "RUN/codebook.npz: the `pyvf tokenize --codebook` of its tokens file)")


def load_pretrained(codebook=None, transformer=None):
    """(Codebook, Transformer): the shipped SM7 pair, or the files given (None: the shipped one)."""
    cb_path = _resolve("codebook", codebook)
    tf_path = _resolve("transformer", transformer)
    cb = Codebook.load(cb_path)
    tf = Transformer.load(tf_path)
    check_pair(cb, tf)
    return cb, tf
