"""Files that survive a killed process: atomic writes, and reads that name the broken file.

An atomic write goes to a temporary file `.{name}.{pid}.{random}.tmp` in the destination's
folder, is fsync'ed, then os.replace'd over the destination: a process killed at any moment leaves
the previous file or the new one. Only SIGKILL or a power cut leaves a temporary file behind, for
remove_stale_temps(path).
"""

import contextlib
import io
import os
import re
import secrets
import zipfile

import numpy as np

__all__ = ["CheckpointError", "atomic_savez", "atomic_write_text", "load_npz", "remove_stale_temps"]


class CheckpointError(ValueError):
    """A file pyvf wrote cannot be read back (truncated, corrupt, an entry missing); names the file."""


def _temp_name(path):
    folder, name = os.path.split(os.path.abspath(path))
    return os.path.join(folder, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def fsync_dir(folder):
    """Make a rename in `folder` durable (POSIX); a no-op where folders cannot be opened."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _atomic_write(path, write):
    """Call write(binary file object) on a temporary file, then move it over `path`."""
    path = os.fspath(path)
    tmp = _temp_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # 0o666 honours the umask (mkstemp: 0600)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(os.path.dirname(os.path.abspath(path)))


def atomic_savez(path, /, **arrays):
    """np.savez(path, **arrays), atomically; `path` is written as given (no ".npz" appended)."""
    _atomic_write(path, lambda f: np.savez(f, **arrays))


def atomic_write_bytes(path, data):
    """Write the bytes-like `data` to `path`, atomically."""
    _atomic_write(path, lambda f: f.write(data))


def atomic_write_png(path, image):
    """Write the PIL image `image` to `path` as a PNG, atomically (encoded in memory first)."""
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_text(path, text):
    """Write the str `text` to `path` (UTF-8), atomically."""
    atomic_write_bytes(path, text.encode())


def load_npz(path, what="file", required=()):
    """Every array of the .npz at `path`, read now: dict name -> array. what: how the errors call
    the file ("checkpoint", ...). A missing file raises FileNotFoundError; a truncated or corrupt
    one, or one without an entry of `required`, CheckpointError (a ValueError), naming the file."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{what} {path} does not exist")
    entry, out = None, {}
    try:
        with np.load(path, allow_pickle=False) as f:
            for entry in f.files:
                out[entry] = f[entry]
    except (TypeError, zipfile.BadZipFile, EOFError, ValueError, KeyError, OSError) as e:
        where = f" (entry {entry!r})" if entry is not None else ""
        raise CheckpointError(f"{what} {path} is truncated or corrupt{where}: {type(e).__name__}: {e}") from e
    missing = [k for k in required if k not in out]
    if missing:
        raise CheckpointError(f"{what} {path} lacks the entries {missing}: not a {what} written by pyvf, "
                              "or written by another version")
    return out


def remove_stale_temps(path):
    """Remove the temporary files atomic writes of `path` left when their process was killed
    outright; call it only where no other process writes `path`. Returns the names removed."""
    folder, name = os.path.split(os.path.abspath(os.fspath(path)))
    # exactly _temp_name's form: `.{name}.*.tmp` would also match other paths' (".model.npz.1.ab.tmp")
    own = re.compile(re.escape(f".{name}.") + r"[0-9]+\.[0-9a-f]+\.tmp")
    removed = []
    for entry in os.listdir(folder) if os.path.isdir(folder) else []:
        if own.fullmatch(entry):
            with contextlib.suppress(FileNotFoundError):  # another cleaner was first
                os.unlink(os.path.join(folder, entry))
                removed.append(entry)
    return removed
