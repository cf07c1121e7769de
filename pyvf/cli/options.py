"""Options more than one command takes, and the checks of the paths a command reads and writes,
run before its work, with the one-line error they print."""

import argparse
import os
import sys

from .._threads import MAX_THREADS

INTERRUPTED = 130  # a command's exit status after Ctrl-C: the shell's for a process ended by SIGINT (128 + 2)


def _number(cast, lo, expected, hi=float("inf")):
    """An argparse type: text -> cast(text) in [lo, hi] (NaN and inf refused), else an error naming
    the option."""
    def parse(text):
        try:
            v = cast(text)
        except ValueError:
            v = float("nan")
        if not lo <= v <= hi or abs(v) == float("inf"):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v
    return parse


positive_int = _number(int, 1, "a positive integer")
non_negative_int = _number(int, 0, "a non-negative integer")
non_negative_float = _number(float, 0, "a finite number >= 0")
thread_count = _number(int, 1, f"a positive integer of at most {MAX_THREADS}", MAX_THREADS)  # pyvf.threads'


def add_threads(parser, default=None, help="threads for pyvf's C++ kernels"):
    """--threads: a thread count for the kernels and numpy's BLAS together (pyvf.threads)."""
    parser.add_argument("--threads", type=thread_count, default=default, help=help)


def context_sizes(text):
    """argparse type: comma-separated positive integers, e.g. 1,3,5 -> (1, 3, 5)."""
    try:
        sizes = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers separated by commas, e.g. 1,3,5; got {text!r}")
    return sizes


# paths: checked before a command's work starts. Each check returns None, or what is wrong as a
# phrase naming the path, which the command passes to fail().


def fail(command, message):
    """A mistake in a command's arguments found after parsing: one line on stderr, exit status 2."""
    print(f"pyvf {command}: error: {message}", file=sys.stderr)
    return 2


def folder_to_make(path):
    """A folder the command will create (or write into): None unless a file is in the way."""
    if not path:
        return "expected a folder, got an empty path"
    above = os.path.abspath(path)
    while not os.path.lexists(above):  # the nearest existing path at or above it
        above = os.path.dirname(above)
    if not os.path.isdir(above):
        return f"cannot create the folder {path!r}: {above!r} is a file, not a folder"
    return None


def file_to_write(path):
    """A file the command will write: None when its folder exists and is writable."""
    if not path:
        return "expected a file, got an empty path"
    if os.path.isdir(path):
        return f"{path!r} is a folder, not a file"
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        return f"cannot write {path!r}: the folder {folder!r} does not exist"
    if not os.access(folder, os.W_OK):
        return f"cannot write {path!r}: the folder {folder!r} is not writable"
    return None


def file_to_read(path):
    """A file the command will read: None when it exists, is a file and opens, else why not."""
    try:
        with open(path, "rb"):
            return None
    except OSError as e:  # missing, a folder, no permission
        return f"cannot read {path!r}: {e.strerror}"


def _path_type(check):
    """An argparse type: text, refused with check(text)'s problem, if any."""
    def parse(text):
        if problem := check(text):
            raise argparse.ArgumentTypeError(problem)
        return text
    return parse


output_file = _path_type(file_to_write)  # a file a command writes at its end
output_dir = _path_type(folder_to_make)  # a folder a command writes into
