"""``python -m firhc_jax cache``: what the commands keep on disk, listed, and cleared with ``--clear``.

Every command keeps XLA's compilations (JAX's persistent compilation cache)
and the applications keep their traced decisions (``_exported``) in one
folder (``cli.cache_folder``): ``$JAX_COMPILATION_CACHE_DIR`` when set (a
``~`` in it is the home folder), else ``$XDG_CACHE_HOME/firhc_jax``, else
``~/.cache/firhc_jax``. Nothing there is ever removed by a run: each setting
adds its files. The listing names each kept decision's application, size and
date, and marks those this installation never reads again (written by
another version, source, platform or format, or with a damaged header).

Only files known by their name and contents are listed and cleared: kept
decisions (``<SHA-256>.jaxexport`` in ``firhc_jax_exported/``, starting with
the line every kept decision of any version starts with), the temporary
files of runs stopped while writing one (``_exported.UNFINISHED_NAME``), and
the entries of JAX's cache, as JAX names them (``<module>-<SHA-256>-cache``
and ``-atime``). Any other file, a file that cannot be read, and anything
but a regular file (a link, a named pipe) is counted and left alone.

    python -m firhc_jax cache            # the folder, each kept decision, XLA's compilations in all
    python -m firhc_jax cache --clear    # remove both (other files in the folder stay)
"""
from __future__ import annotations

import datetime
import re
import stat
from pathlib import Path
from typing import NamedTuple

from ._exported import (
    FOLDER,
    KEPT_NAME,
    MAGIC,
    UNFINISHED_NAME,
    Refused,
    installation,
    key_lines,
    read_header,
    read_regular,
)

HELP = "list the compilations and decisions the commands keep on disk, or clear them"
DESCRIPTION = ("Every command keeps XLA's compilations and the applications' traced decisions in one folder: "
               "$JAX_COMPILATION_CACHE_DIR when set (~ is the home folder), else $XDG_CACHE_HOME/firhc_jax, else "
               "~/.cache/firhc_jax. Lists each kept decision with its size, and XLA's compilations in all; "
               "--clear removes both. Only files named and written as firhc_jax and JAX write them count: any "
               "other file is only counted, and stays.")
# JAX's persistent cache names an entry <module>-<SHA-256 of its key, in hex>-cache, and its last access -atime.
XLA_NAME = re.compile(r"[\w.-]+-[0-9a-f]{64}-(?:cache|atime)")


def register(subparsers) -> None:
    """Add the ``cache`` subcommand."""
    p = subparsers.add_parser("cache", help=HELP, description=DESCRIPTION)
    p.add_argument("--clear", action="store_true",
                   help="remove the kept decisions (of every version, and those a run stopped while writing) and "
                        "XLA's compilations from the folder (with $JAX_COMPILATION_CACHE_DIR, those of every JAX "
                        "program using it); other files stay")
    p.set_defaults(func=run, uses_cache=False)


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB"


class _File(NamedTuple):
    path: Path
    size: int
    mtime: float


def _entries(folder: Path) -> tuple[list[_File], list[Path]]:
    """``(regular files, every other entry)`` of ``folder``, none when it is not there; an entry that leaves
    the folder while it is looked at (another ``--clear``, JAX's own eviction) is passed over."""
    try:
        paths = list(folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return [], []
    except OSError as e:
        raise SystemExit(f"cache: cannot list {folder}: {e.strerror or e}") from None
    files, others = [], []
    for p in paths:
        try:
            st = p.lstat()  # a link is not followed: it is another entry
        except FileNotFoundError:
            continue
        except OSError:
            others.append(p)
            continue
        if stat.S_ISREG(st.st_mode):
            files.append(_File(p, st.st_size, st.st_mtime))
        else:
            others.append(p)
    return files, others


def _state(data: bytes) -> tuple[str, str]:
    """``(application, note)`` of a kept file's contents: the note says why this installation never reads it, if
    so."""
    try:
        header, _ = read_header(data)
    except Refused as e:
        return "?", f"never read: {e}"
    kept = key_lines(str(header["key"]))
    other = [name for name, value in installation().items() if kept.get(name) != value]
    return str(header["label"]) or "?", f"never read: written by another {', '.join(other)}" if other else ""


class Listing(NamedTuple):
    """What ``cache`` found in a folder; ``--clear`` removes ``kept``, ``unfinished`` and ``xla``."""

    kept: list[_File]  # kept decisions, the newest first
    unfinished: list[_File]  # temporary files of runs stopped while writing a decision
    xla: list[_File]  # the entries of JAX's compilation cache
    others: int  # every other entry of the folder and of FOLDER: left alone
    text: str


def listing(folder: Path) -> Listing:
    """What ``folder`` holds, and the text that lists it."""
    top, top_others = _entries(folder)
    files, others = _entries(folder / FOLDER)
    xla = [f for f in top if XLA_NAME.fullmatch(f.path.name)]
    n_others = len(top) - len(xla) + sum(p != folder / FOLDER for p in top_others) + len(others)
    kept, unfinished, rows = [], [], []
    for f in sorted(files, key=lambda f: f.mtime, reverse=True):
        if UNFINISHED_NAME.fullmatch(f.path.name):
            unfinished.append(f)
            continue
        try:
            data = read_regular(f.path) if KEPT_NAME.fullmatch(f.path.name) else b""
        except FileNotFoundError:
            continue
        except (OSError, Refused):  # not readable, or no longer a regular file: nothing says it is ours
            data = b""
        if not data.startswith(MAGIC):
            n_others += 1
            continue
        kept.append(f)
        app, note = _state(data)
        when = datetime.datetime.fromtimestamp(f.mtime).strftime("%Y-%m-%d %H:%M")
        rows.append(f"  {f.path.stem[:12]}  {app:<20} {_size(f.size):>9}  {when}" + (f"  ({note})" if note else ""))
    lines = [f"folder: {folder}",
             f"kept decisions ({FOLDER}/): {len(kept)} files, {_size(sum(f.size for f in kept))}", *rows]
    if unfinished:
        lines.append(f"unfinished kept decisions (a run stopped while writing them): {len(unfinished)} files, "
                     f"{_size(sum(f.size for f in unfinished))}")
    lines.append(f"XLA's compilations: {sum(f.path.name.endswith('-cache') for f in xla)} entries, "
                 f"{_size(sum(f.size for f in xla))}")
    if n_others:
        lines.append(f"other files, which --clear leaves: {n_others}")
    return Listing(kept, unfinished, xla, n_others, "\n".join(lines))


def run(args) -> int:
    """List the folder's kept files, or remove them with ``--clear``; exit status."""
    from ..cli import cache_folder

    folder = cache_folder()
    found = listing(folder)
    if not args.clear:
        print(found.text)
        return 0
    removed = {"kept": 0, "unfinished": 0, "xla": 0}
    size = 0
    for what in removed:
        for f in getattr(found, what):
            try:
                f.path.unlink()
            except FileNotFoundError:  # removed since it was listed (another process, JAX's own eviction)
                continue
            except OSError as e:
                raise SystemExit(f"cache: cannot remove {f.path}: {e.strerror or e}") from None
            removed[what] += 1
            size += f.size
    unfinished = f" (and {removed['unfinished']} unfinished)" if removed["unfinished"] else ""
    print(f"removed {removed['kept']} kept decisions{unfinished} and {removed['xla']} files of XLA's compilations "
          f"({_size(size)}) from {folder}")
    return 0
