"""``python -m firhc_jax cache``: what the commands keep on disk, listed, and cleared with ``--clear``.

Every command keeps XLA's compilations (JAX's persistent compilation cache)
and the applications keep their traced decisions (``_exported``) in one
folder (``cli.cache_folder``): ``$JAX_COMPILATION_CACHE_DIR`` when set, else
``$XDG_CACHE_HOME/firhc_jax``, else ``~/.cache/firhc_jax``. Nothing there is
ever removed by a run: each setting adds its files. The listing names each
kept decision's application, size and date, and marks those this
installation never reads again (written by another version, source or
platform, or unreadable).

    python -m firhc_jax cache            # the folder, each kept decision, XLA's compilations in all
    python -m firhc_jax cache --clear    # remove both (other files in the folder stay)
"""
from __future__ import annotations

import datetime
from pathlib import Path

from ._exported import FOLDER, SUFFIX, Refused, installation, key_lines, read_header

HELP = "list the compilations and decisions the commands keep on disk, or clear them"
DESCRIPTION = ("Every command keeps XLA's compilations and the applications' traced decisions in one folder: "
               "$JAX_COMPILATION_CACHE_DIR when set, else $XDG_CACHE_HOME/firhc_jax, else ~/.cache/firhc_jax. "
               "Lists each kept decision with its size, and XLA's compilations in all; --clear removes both.")
XLA_SUFFIXES = ("-cache", "-atime")  # JAX's persistent cache: an entry and its last access time


def register(subparsers) -> None:
    """Add the ``cache`` subcommand."""
    p = subparsers.add_parser("cache", help=HELP, description=DESCRIPTION)
    p.add_argument("--clear", action="store_true",
                   help="remove the kept decisions and XLA's compilations from the folder (with "
                        "$JAX_COMPILATION_CACHE_DIR, those of every JAX program using it); other files stay")
    p.set_defaults(func=run, uses_cache=False)


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB"


def _state(path: Path) -> tuple[str, str]:
    """``(application, note)`` of a kept file: the note says why this installation never reads it, if so."""
    try:
        header, _ = read_header(path.read_bytes())
    except Refused as e:
        return "?", f"never read: {e}"
    except OSError as e:
        return "?", f"never read: cannot be read ({e.strerror or e})"
    kept = key_lines(str(header["key"]))
    other = [name for name, value in installation().items() if kept.get(name) != value]
    return str(header["label"]) or "?", f"never read: written by another {', '.join(other)}" if other else ""


def listing(folder: Path) -> tuple[list[Path], list[Path], str]:
    """``(kept decisions, XLA's entries, the text that lists them)`` in ``folder``."""
    kept = sorted((folder / FOLDER).glob(f"*{SUFFIX}"), key=lambda p: p.stat().st_mtime, reverse=True) \
        if (folder / FOLDER).is_dir() else []
    xla = sorted(p for p in folder.iterdir() if p.is_file() and p.name.endswith(XLA_SUFFIXES)) \
        if folder.is_dir() else []
    lines = [f"folder: {folder}", f"kept decisions ({FOLDER}/): {len(kept)} files, "
                                  f"{_size(sum(p.stat().st_size for p in kept))}"]
    for p in kept:
        app, note = _state(p)
        when = datetime.datetime.fromtimestamp(p.stat().st_mtime).strftime("%Y-%m-%d %H:%M")
        lines.append(f"  {p.stem[:12]}  {app:<20} {_size(p.stat().st_size):>9}  {when}"
                     + (f"  ({note})" if note else ""))
    lines.append(f"XLA's compilations: {sum(p.name.endswith('-cache') for p in xla)} entries, "
                 f"{_size(sum(p.stat().st_size for p in xla))}")
    return kept, xla, "\n".join(lines)


def run(args) -> int:
    """List the folder's kept files, or remove them with ``--clear``; exit status."""
    from ..cli import cache_folder

    folder = cache_folder()
    kept, xla, text = listing(folder)
    if not args.clear:
        print(text)
        return 0
    removed = 0
    for p in (*kept, *xla):
        try:
            size = p.stat().st_size
            p.unlink()
            removed += size
        except FileNotFoundError:  # removed since it was listed (another process, JAX's own eviction)
            continue
        except OSError as e:
            raise SystemExit(f"cache: cannot remove {p}: {e.strerror or e}") from None
    print(f"removed {len(kept)} kept decisions and {len(xla)} files of XLA's compilations ({_size(removed)}) "
          f"from {folder}")
    return 0
