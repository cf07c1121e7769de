"""Options more than one command takes, defined and checked here once."""

import argparse

KERNEL_THREADS = "threads for pyvf's C++ kernels"


def positive_int(text):
    """argparse type: a positive integer (an error naming the option otherwise)."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def add_threads(parser, default=None, help=KERNEL_THREADS):
    """--threads: a positive integer, or `default`. The command applies it through
    pyvf.set_num_threads or pyvf.threads (the kernels and numpy's BLAS together), or hands it to
    the library function that does."""
    parser.add_argument("--threads", type=positive_int, default=default, help=help)


def context_sizes(text):
    """argparse type: comma-separated positive integers, e.g. 1,3,5 -> (1, 3, 5)."""
    try:
        sizes = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers separated by commas, e.g. 1,3,5; got {text!r}")
    return sizes


def names(parser, value, choices, what):
    """The comma-separated names of an option (all of choices when it was not given), each one
    checked against choices: an unknown name is the parser's error, naming the choices."""
    chosen = tuple(n.strip() for n in value.split(",")) if value else tuple(choices)
    unknown = [n for n in chosen if n not in choices]
    if unknown:
        parser.error(f"unknown {what} {', '.join(unknown)}; choose from {', '.join(choices)}")
    return chosen
