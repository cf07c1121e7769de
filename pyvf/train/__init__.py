"""Training: optimisers and schedules (optim.py), one step and the loops that checkpoint
and resume exactly (loops.py, the run folder: _run.py), the torch engines (torch_engine.py) and
the whole pipeline (pipeline.py)."""

from .loops import (TINY_CODEBOOK, TINY_TRANSFORMER, RunOptions, TransformerRecipe, codebook_batch,
                    codebook_train_step, load_tokens, save_tokens, tokenize, train_codebook, train_step,
                    train_transformer, transformer_batch)

__all__ = ["TINY_CODEBOOK", "TINY_TRANSFORMER", "RunOptions", "TransformerRecipe", "codebook_batch",
           "codebook_train_step", "load_tokens", "save_tokens", "tokenize", "train_codebook", "train_step",
           "train_transformer", "transformer_batch"]
