"""`pyvf scenes`: its arguments; the work is pyvf.scenes.make.make_dataset."""

import sys

from ..scenes.dataset import DatasetExistsError
from ..scenes.make import PREVIEW_SCENES, make_dataset
from .options import INTERRUPTED, fail, file_to_write, folder_to_make


def cmd_scenes(args):
    """Render a Shepard-Metzler-7 dataset (docs/math.md §7) into .npz shards and a manifest.
    An interrupted run is resumed by the same command: the shards it finished are kept."""
    for option, problem in (("--out", folder_to_make(args.out)),
                            ("--preview", args.preview is not None and file_to_write(args.preview))):
        if problem:  # before the rendering, which can take minutes
            return fail("scenes", f"argument {option}: {problem}")
    try:
        make_dataset(args.out, args.scenes, args.seed, views=args.views, size=args.size, shard_size=args.shard_size,
                     preview=args.preview, progress=not args.quiet, overwrite=args.overwrite)
    except DatasetExistsError as e:
        return fail("scenes", f"argument --out: {str(e).replace('overwrite=True', '--overwrite')}")
    except (ValueError, TypeError) as e:
        return fail("scenes", str(e))
    except OSError as e:  # a folder that cannot be written (a read-only or virtual file system, a full disk)
        return fail("scenes", f"cannot write {e.filename if e.filename is not None else args.out!r}: "
                              f"{e.strerror or e}")
    except KeyboardInterrupt:
        print(f"\npyvf scenes: interrupted; the same command resumes it, keeping the shards in {args.out} that "
              "are finished", file=sys.stderr)
        return INTERRUPTED
    return 0


def register(subparsers):
    p = subparsers.add_parser("scenes", help="render a Shepard-Metzler-7 dataset (.npz shards + manifest)",
                              description=cmd_scenes.__doc__)
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write the shards and manifest.json into")
    p.add_argument("--scenes", type=int, required=True, metavar="N", help="number of scenes")
    p.add_argument("--seed", type=int, required=True, metavar="S",
                   help="dataset seed: scene i draws from numpy.random.default_rng([S, i])")
    p.add_argument("--views", type=int, default=15, help="views per scene (default 15, as SM7)")
    p.add_argument("--size", type=int, default=64, help="image side in pixels (default 64, as SM7)")
    p.add_argument("--shard-size", type=int, default=500, metavar="N", help="scenes per shard (default 500)")
    p.add_argument("--preview", default=None, metavar="PNG",
                   help=f"also write a PNG grid of the first {PREVIEW_SCENES} scenes' views")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_scenes)
    return p
