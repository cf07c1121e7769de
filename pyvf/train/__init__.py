"""Training: one step (step.py), the loops that checkpoint and resume exactly (loops.py), and
the `pyvf` training commands (commands.py). The run folder's files are described in _run.py."""

from .commands import cli_register, cmd_tokenize, cmd_train_codebook, cmd_train_transformer
from .loops import (
    TINY_CODEBOOK,
    TINY_TRANSFORMER,
    codebook_batch,
    load_tokens,
    save_tokens,
    tokenize,
    train_codebook,
    train_transformer,
    transformer_batch,
)
from .step import codebook_train_step, train_step, transformer_step

__all__ = [
    "TINY_CODEBOOK",
    "TINY_TRANSFORMER",
    "cli_register",
    "cmd_tokenize",
    "cmd_train_codebook",
    "cmd_train_transformer",
    "codebook_batch",
    "codebook_train_step",
    "load_tokens",
    "save_tokens",
    "tokenize",
    "train_codebook",
    "train_step",
    "train_transformer",
    "transformer_batch",
    "transformer_step",
]
