"""Map files (checkpoints) read safely: a file never runs code, and any file that is not a readable checkpoint of
this version is refused with one line that says what it is and what to do.

torch.save writes a zip archive: the tensors' bytes, and a pickle of the containers around them. Unpickling can
call any function a file names, so the pickle is read only by torch.load(weights_only=True), which rebuilds
tensors and plain values and refuses everything else. Before that, the file must be a zip archive whose entries
all pass their CRC check: a plain pickle (which torch would hand to its legacy reader), random bytes, a truncated
copy or flipped bits are refused without being unpickled at all.
"""
from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

ZIP_MAGIC = b"PK\x03\x04"
RERUN = "re-run `eslam run` (or save the map again) to make a new one"


class CheckpointError(ValueError):
    pass


def read_checkpoint(path: Path | str, version: int) -> dict:
    """The state dict in a checkpoint written by torch.save, if it is of `version`; CheckpointError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path} (an `eslam run --out DIR` writes DIR/checkpoint.pt)")
    with path.open("rb") as f:
        magic = f.read(len(ZIP_MAGIC))
    if magic != ZIP_MAGIC:
        raise CheckpointError(f"{path} is not an ESLAM checkpoint (not an archive written by torch.save); "
                              f"give the checkpoint.pt of a run")
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()  # the first entry whose CRC does not match, None if all do
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        raise CheckpointError(f"{path} is damaged (truncated or corrupt archive: {_first_line(e)}); {RERUN}") from None
    if damaged is not None:
        raise CheckpointError(f"{path} is damaged (corrupt data in {damaged}); {RERUN}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch's message suggests weights_only=False, i.e. running the file's code: never for a map file.
        raise CheckpointError(f"{path} is not an ESLAM checkpoint: it holds Python objects other than tensors "
                              f"and plain values, refused unread (a map file never runs code)") from None
    except (RuntimeError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise CheckpointError(f"{path} is damaged (unreadable archive: {_first_line(e)}); {RERUN}") from None
    if not isinstance(state, dict) or "version" not in state:
        raise CheckpointError(f"{path} is not an ESLAM checkpoint (a torch file without a map inside)")
    if state["version"] != version:
        raise CheckpointError(f"{path} is a version {state['version']} checkpoint, this eslam reads version "
                              f"{version}; {RERUN} with this version")
    return state


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0][:160] if text else type(e).__name__
