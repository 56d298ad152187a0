"""Where the table, figure and benchmark commands write.

By default every run gets a fresh folder, ``outputs/<command>/<YYYY-mm-dd_HH-MM-SS>/`` (relative to
the working directory, like the Hydra apps' run directories; ``outputs/`` is git-ignored), so a
run never rewrites a tracked file and never resumes from someone else's records. ``--publish``
(``publish=true`` for the Hydra apps) writes the command's files into their place under
``results/`` instead, replacing the ones there: ``results/`` holds the current output of each
command, and only when asked.

    ap = argparse.ArgumentParser()
    outputs.add_arguments(ap, published="results/figures")
    out = outputs.folder(ap.parse_args(argv), "dss-fig-gradient1d")
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

__all__ = ["OUTPUTS", "fresh_folder", "link_latest", "add_arguments", "folder", "publish_files"]

OUTPUTS = Path("outputs")


def fresh_folder(command: str, root: Path | str = OUTPUTS) -> Path:
    """``<root>/<command>/<timestamp>``, created; ``_2``, ``_3``, ... when that second is taken.
    ``<root>/<command>/latest`` then points at it (:func:`link_latest`)."""
    base = Path(root) / command / time.strftime("%Y-%m-%d_%H-%M-%S")
    path, n = base, 1
    while True:
        try:
            path.mkdir(parents=True, exist_ok=False)
            link_latest(path)
            return path
        except FileExistsError:
            n += 1
            path = base.with_name(f"{base.name}_{n}")


LATEST = "latest"


def link_latest(run_dir: Path | str) -> Path | None:
    """Point ``<run_dir's parent>/latest`` at ``run_dir`` (a relative symlink, so the tree can move),
    replacing the link atomically: a reader sees the previous run or this one, never no link.
    Returns the link, or None where it cannot be made (a file or folder of that name that is not
    a link, a file system without symlinks), which costs the run nothing."""
    run_dir = Path(run_dir)
    link = run_dir.parent / LATEST
    if run_dir.name == LATEST or (link.exists() and not link.is_symlink()):
        return None
    tmp = run_dir.parent / f".{LATEST}.{os.getpid()}.tmp"
    try:
        tmp.unlink(missing_ok=True)
        os.symlink(run_dir.name, tmp, target_is_directory=True)
        os.replace(tmp, link)  # rename(2): atomic, and it replaces an existing link
    except OSError:
        tmp.unlink(missing_ok=True)
        return None
    return link


def add_arguments(ap: argparse.ArgumentParser, published: str, what: str = "output folder") -> None:
    """``--out`` (default: a fresh ``outputs/<command>/<timestamp>`` folder) and ``--publish``
    (write to ``published`` under the working directory, the command's place in ``results/``)."""
    ap.add_argument("--out", default=None,
                    help=f"{what} (default: a fresh outputs/<command>/<timestamp> folder)")
    ap.add_argument("--publish", action="store_true",
                    help=f"write to {published} (tracked in git: the published result) instead")
    ap.set_defaults(_published=published)


def folder(args: argparse.Namespace, command: str, name: str | None = None) -> Path:
    """The output location chosen by :func:`add_arguments`' options: ``--out`` as given,
    ``--publish``'s place, or a fresh folder; with ``name`` the path of that file (or prefix)
    inside a fresh folder. ``--out`` and ``--publish`` together are refused."""
    if args.out and args.publish:
        raise SystemExit(f"{command}: error: give --out or --publish, not both")
    if args.publish:
        return Path(args._published)
    if args.out:
        return Path(os.path.expanduser(args.out))
    fresh = fresh_folder(command)
    return fresh / name if name else fresh


def publish_files(src: Path | str, dest: Path | str, names: list[str], stale: list[str] = ()) -> list[Path]:
    """Copy ``src/<name>`` for each of ``names`` into ``dest`` (created), each atomically, and
    delete ``dest/<s>`` for each of ``stale`` (files or folders an earlier version of the
    command left there), so that ``dest`` holds this run's files only. Returns the written paths."""
    src, dest = Path(src), Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for n in names:
        s, d = src / n, dest / n
        if not s.is_file():
            raise FileNotFoundError(f"{s}: not written by the run, nothing to publish")
        tmp = d.with_name(f".{d.name}.{os.getpid()}.tmp")
        shutil.copyfile(s, tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, d)
        written.append(d)
    for n in stale:
        p = dest / n
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    return written
