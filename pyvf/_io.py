"""Files that survive a killed process: atomic writes, and reads that name the broken file.

    atomic_savez("run/checkpoint.npz", step=np.array(3), w=w)     # all or nothing
    atomic_write_text("run/config.json", json.dumps(cfg))
    atomic_write_png("views.png", Image.fromarray(rgb))              # the same for a picture
    arrays = load_npz("run/checkpoint.npz", "checkpoint", required=("step",))

An atomic write goes to a temporary file in the destination's folder (same file system, so
the rename is atomic), is flushed and fsync'ed, then os.replace'd over the destination, and
the folder is fsync'ed so the rename itself is on disk. A process killed at any moment leaves
either the previous file or the new one, never a mix; an exception (KeyboardInterrupt
included) removes the temporary file. Only SIGKILL or a power cut can leave one behind:
remove_stale_temps(path) clears those (they are named `.{name}.{pid}.{random}.tmp`).

A model file (a model's configuration and state) is written and read by pyvf.models.io, on
these primitives.
"""

import io
import os
import re
import secrets
import zipfile

import numpy as np

__all__ = ["CheckpointError", "atomic_savez", "atomic_write_text", "load_npz", "remove_stale_temps"]


class CheckpointError(ValueError):
    """A file pyvf wrote cannot be read back: truncated, corrupt, or missing an entry.
    The message names the file (and the entry where one is at fault)."""


def _temp_name(path):
    folder, name = os.path.split(os.path.abspath(path))
    return os.path.join(folder, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def fsync_dir(folder):
    """Make a rename in `folder` durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write(path, write):
    """Call write(binary file object) on a temporary file, then move it over `path`."""
    path = os.fspath(path)
    tmp = _temp_name(path)
    # os.open with 0o666 honours the umask, as open(path, "wb") would (mkstemp would force 0600)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as e:  # a missing folder, a file in the path, no permission: name the destination
        raise type(e)(e.errno, f"cannot write {path}: {e.strerror} (creating its temporary file {tmp})") from e
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    fsync_dir(os.path.dirname(os.path.abspath(path)))


def atomic_savez(path, /, **arrays):
    """np.savez(path, **arrays), atomically; `path` is written as given (no ".npz" appended).
    Every value must convert to a non-object array (a str becomes a 0-d unicode array), so that
    the file loads with allow_pickle=False: an object array raises TypeError naming it."""
    arrays = {key: np.asarray(value) for key, value in arrays.items()}
    for key, a in arrays.items():
        if a.dtype.hasobject:
            raise TypeError(f"atomic_savez: {key!r} is an object array (it would need pickle)")
    _atomic_write(path, lambda f: np.savez(f, **arrays))


def atomic_write_bytes(path, data):
    """Write the bytes-like `data` to `path`, atomically (e.g. a PNG encoded into a BytesIO)."""
    _atomic_write(path, lambda f: f.write(data))


def atomic_write_png(path, image):
    """Write the PIL image `image` to `path` as a PNG, atomically (encoded in memory first)."""
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_text(path, text, encoding="utf-8"):
    """Write the str `text` to `path`, atomically."""
    data = text.encode(encoding)
    _atomic_write(path, lambda f: f.write(data))


def load_npz(path, what="file", required=()):
    """Every array of the .npz at `path`, read now (the file is closed on return): dict name -> array.

    path: a str or os.PathLike.
    what: how the error messages call the file ("checkpoint", "codebook", ...).
    required: entries that must be present. A missing file raises FileNotFoundError; a
    truncated or corrupt one, or a missing entry, CheckpointError (a ValueError); both name
    the file, and the entry being read when it broke. Opened with allow_pickle=False."""
    path = name = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{what} {path} does not exist")
    entry = None
    try:
        with np.load(path, allow_pickle=False) as f:
            out = {}
            for entry in f.files:
                out[entry] = f[entry]
    except (TypeError, zipfile.BadZipFile, EOFError, ValueError, KeyError, OSError) as e:
        where = f" (entry {entry!r})" if entry is not None else ""
        raise CheckpointError(f"{what} {name} is truncated or corrupt{where}: {type(e).__name__}: {e}") from e
    missing = [k for k in required if k not in out]
    if missing:
        raise CheckpointError(f"{what} {name} lacks the entries {missing}: not a {what} written by pyvf, "
                              "or written by another version")
    return out


def remove_stale_temps(path):
    """Remove the temporary files an atomic write of `path` left behind when its process was
    killed outright (SIGKILL, power cut). Call it only where no other process writes `path`.
    Returns the names removed."""
    folder, name = os.path.split(os.path.abspath(os.fspath(path)))
    # exactly _temp_name's `.{name}.{pid}.{hex}.tmp`: a looser `.{name}.*.tmp` would also match the
    # temporary files of other paths (".model.npz.1.ab.tmp" for "model"), perhaps being written now
    own = re.compile(re.escape(f".{name}.") + r"[0-9]+\.[0-9a-f]+\.tmp")
    removed = []
    try:
        entries = os.listdir(folder)
    except FileNotFoundError:
        return removed
    for entry in entries:
        if own.fullmatch(entry):
            try:
                os.unlink(os.path.join(folder, entry))
                removed.append(entry)
            except FileNotFoundError:
                pass
    return removed
