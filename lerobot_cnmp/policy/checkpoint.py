"""Checks on a checkpoint's files before LeRobot reads them, so that a damaged file is named in the error.

A ``model.safetensors`` is an 8-byte little-endian header length ``n``, ``n`` bytes of JSON (each tensor's
dtype, shape and ``data_offsets`` ``[begin, end)`` into the data that follows), then the tensors' bytes. The
``safetensors`` reader stops on a cut file with "Error while deserializing header: ..." and no file name; this
module reads the same layout and says which file is truncated or corrupt.
"""

from __future__ import annotations

import json
from pathlib import Path

LENGTH_BYTES = 8  # the header length, a little-endian u64


class CorruptCheckpointError(ValueError):
    """A checkpoint file is truncated or corrupt."""


def _broken(path: Path, why: str) -> CorruptCheckpointError:
    return CorruptCheckpointError(
        f"{path} is truncated or corrupt ({why}): copy or download it again, or save the checkpoint again")


def check_weights_file(path: str | Path) -> None:
    """Raise :class:`CorruptCheckpointError` naming ``path`` unless it holds a whole safetensors file: a header
    length, a JSON header of that length, and every tensor's bytes."""
    path = Path(path)
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(LENGTH_BYTES)
        if len(head) < LENGTH_BYTES:
            raise _broken(path, f"{size} bytes, fewer than the {LENGTH_BYTES} of a safetensors header length")
        n = int.from_bytes(head, "little")
        if n > size - LENGTH_BYTES:
            raise _broken(path, f"its header declares {n} bytes, the file holds {size - LENGTH_BYTES} after it")
        try:
            header = json.loads(f.read(n))
            ends = [int(t["data_offsets"][1]) for name, t in header.items() if name != "__metadata__"]
        except (ValueError, AttributeError, KeyError, TypeError, IndexError) as e:  # ValueError: bad JSON too
            raise _broken(path, f"its header is not a safetensors JSON header: {type(e).__name__}") from e
    need = LENGTH_BYTES + n + max(ends, default=0)
    if need > size:
        raise _broken(path, f"its tensors end at byte {need}, the file has {size}")
