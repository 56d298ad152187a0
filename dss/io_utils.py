"""Atomic file writing: a temp file in the target folder, then ``os.replace``.

An interrupted run therefore never leaves a half-written file under the final name.
"""

from __future__ import annotations

import io
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

__all__ = [
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_save_npz",
    "atomic_savefig",
    "atomic_path",
]


class atomic_path:
    """Context manager yielding a temporary path that is renamed onto ``path`` on success.

    Use it for writers that insist on a file name (open3d, matplotlib, torch.onnx)::

        with atomic_path("out.ply") as tmp:
            o3d.io.write_point_cloud(str(tmp), pcd)

    The temp name keeps the final suffix, so writers that pick a format from it still work.
    On an exception the temp file is removed and the target is left untouched. With
    ``exclusive`` an existing target is never replaced: the result goes to the first free
    ``<stem>-<n><suffix>`` instead, and ``.path`` names where it went.
    """

    def __init__(self, path: str | os.PathLike, exclusive: bool = False):
        self.path = Path(path)
        self.exclusive = exclusive

    def __enter__(self) -> Path:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.path.stem}.", suffix=f".tmp{self.path.suffix}", dir=self.path.parent
        )
        os.close(fd)
        # mkstemp creates 0600 files; give the result the usual permissions (0666 & ~umask).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        self.tmp = Path(tmp)
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and self.tmp.exists() and self.tmp.stat().st_size > 0:
            if self.exclusive:
                self.path = _link_free(self.tmp, self.path)
                self.tmp.unlink()
            else:
                os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
            if exc_type is None:
                raise OSError(f"{self.path}: the writer produced no data")


def _link_free(tmp: Path, path: Path) -> Path:
    """Hard-link ``tmp`` to ``path``, or (when something else created ``path`` meanwhile) to the
    first free ``<stem>-<n><suffix>`` beside it: a link never replaces an existing file, so
    neither result is lost. Returns the name used."""
    n = 0
    while True:
        target = path if n == 0 else path.with_name(f"{path.stem}-{n}{path.suffix}")
        try:
            os.link(tmp, target)
        except FileExistsError:
            n += 1
            continue
        if n:
            log.warning("%s appeared while this run was writing it; this run's result is %s", path, target)
        return target


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=False, default=_json_default) + "\n")


def atomic_save_npz(path: str | os.PathLike, **arrays) -> Path:
    """Uncompressed ``np.savez`` written atomically (bytes are deterministic for equal inputs)."""
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def atomic_savefig(fig, path: str | os.PathLike, **kwargs) -> Path:
    """Save a matplotlib figure atomically (PNG by default)."""
    path = Path(path)
    buf = io.BytesIO()
    kwargs.setdefault("dpi", 120)
    kwargs.setdefault("bbox_inches", "tight")
    fig.savefig(buf, format=path.suffix.lstrip(".") or "png", **kwargs)
    return atomic_write_bytes(path, buf.getvalue())


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    try:
        import torch

        if isinstance(o, torch.Tensor):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")
